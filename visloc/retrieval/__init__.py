"""Image retrieval, the paper's section 3.1: correspondences by equations (1) and (2) and the
backends that count them (``matching``), and which database images a query is compared with, the
best one among them (``retrievers``: the paper's window, the filter's gate and a global-vector
shortlist).

Imports: ``visloc.errors``, ``visloc.params``, ``visloc.features``.
"""
