"""The engine's side of a store file: building it (``ingest``: SIFT, global vectors, structure and
the self-check), the one door to it (``workspace``), and what is loaded from it as arrays
(``database``). Only ``visloc.db`` speaks SQL; only ``ingest`` and ``workspace`` open a store.

Imports: the stages below it (``visloc.sources``, ``visloc.features``, ``visloc.retrieval``,
``visloc.pose``) and ``visloc.db``.
"""
