"""Describing images: SIFT keypoints and descriptors (``sift``), and global (VLAD) vectors that
shortlist similar images (``vlad``).

Imports: ``visloc.errors``, ``visloc.params``.
"""
