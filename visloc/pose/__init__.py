"""What a retrieval tells the filter: the paper's geotag measurement or the refined method's metric
pose (``measurement``, ``refined``, ``viewpose``), the structure triangulated at ingest
(``structure``), the camera-rate pose on it (``fastpose``), a measurement's covariance and its
calibration (``uncertainty``), and the store's self-check (``selfcheck``).

Imports: ``visloc.errors``, ``visloc.params``, ``visloc.features``, ``visloc.geometry``,
``visloc.retrieval``, and ``visloc.db`` (its plain records only).
"""
