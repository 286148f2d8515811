"""How runs are made and recorded: a step's record against its truth (``records``), the paper's
series protocol (``evaluation``), a whole drive (``drive``, what the dashboard scrubs), every drive
of a data root (``suite``) and every frame at camera rate (``track``).

Imports: ``visloc.tracking`` and every stage below it.
"""
