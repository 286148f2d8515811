"""A limit on the size of the images visloc decodes, checked from the file's header before any pixel
is decoded.

SIFT's memory grows with the image: about 230 bytes per pixel at full resolution, so a
45-megapixel frame needs some 10 GB in one worker. ``DEFAULT_MAX_IMAGE_MP`` keeps one worker
under about 5 GB; ``visloc ingest --max-image-mp`` raises or lowers it.
"""

from __future__ import annotations

import warnings
from pathlib import Path

from visloc.errors import InputError, ParameterError

DEFAULT_MAX_IMAGE_MP = 20.0  # megapixels (10^6 pixels) per image


def require_max_image_mp(max_image_mp: float) -> float:
    if not (max_image_mp > 0 and max_image_mp < float("inf")):
        raise ParameterError(f"--max-image-mp {max_image_mp}: must be a finite number of megapixels > 0")
    return float(max_image_mp)


def header_size_px(path: Path) -> tuple[int, int] | None:
    """(width, height) from the image file's header without decoding it; None when the header cannot be
    read here (the decoder will then say what is wrong with the file)."""
    from PIL import Image, UnidentifiedImageError  # here: the command line reads this module's limit at start

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Pillow's own size warning: this module applies its own limit
            previous, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
            try:
                with Image.open(path) as image:
                    return int(image.size[0]), int(image.size[1])
            finally:
                Image.MAX_IMAGE_PIXELS = previous
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError):
        return None


def check_image_size(path: Path, size_px: tuple[int, int] | None, max_image_mp: float) -> None:
    """``InputError`` naming ``path`` when the image is larger than ``max_image_mp`` megapixels."""
    if size_px is None:
        return
    width, height = size_px
    if width * height > max_image_mp * 1e6:
        raise InputError(f"{path}: image is {width}x{height} px ({width * height / 1e6:.1f} megapixels), more than "
                         f"the limit of {max_image_mp:g} (raise it with --max-image-mp if this machine has the memory: "
                         "SIFT needs about 230 bytes per pixel)")
