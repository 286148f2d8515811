"""Reading drives: KITTI raw drives and CSV drives of geotagged images, their calibration, the image
size limit, and the frames of a drive described by SIFT as queries.

Imports: ``visloc.errors``, ``visloc.geo``, ``visloc.params``, ``visloc.geometry``, ``visloc.features``.
"""
