"""Multi-view geometry as pure functions over numpy arrays: the camera model, transforms,
essential matrix, triangulation, PnP (``projective``); triangulation from several views
(``multiview``); bundle adjustment of a few posed cameras with priors (``bundle``).

Imports: numpy and OpenCV only.
"""
