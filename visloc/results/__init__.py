"""What runs are shown as: tables, JSON and plots (``report``), the paper's Figure 3 (``figures``),
trajectories as GeoJSON and CSV (``export``).

Imports: ``visloc.protocols`` and below.
"""
