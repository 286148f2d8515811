"""The images of a log's topic, written once to a cache folder so that the store and the dashboard read them as
files, as they read a KITTI drive's: a compressed image's bytes as they are, a raw one as PNG, each file
written whole (a temporary name, then renamed) and an index of them written last, so that a later command
reads no image message.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

import cv2
import numpy as np

from visloc.errors import InputError
from visloc.sources.log_frames import image_array

CACHE_VERSION = 1


def cache_root() -> Path:
    """Where visloc caches what it reads from elsewhere: ``$VISLOC_CACHE``, else ``~/.cache/visloc``."""
    env = os.environ.get("VISLOC_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "visloc"


def cache_folder(path: Path, topic: str) -> Path:
    """Where the images of ``topic`` go: keyed by the log's path, size and modification time."""
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    stats = [(str(p.resolve()), p.stat().st_size, p.stat().st_mtime_ns) for p in files]
    key = hashlib.sha256(json.dumps([CACHE_VERSION, stats]).encode()).hexdigest()[:16]
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{path.name}-{topic.strip('/')}")[:80]
    return cache_root() / "logs" / f"{slug}-{key}"


def write_atomically(target: Path, write) -> None:
    """``write(path)`` to a temporary name beside ``target``, then renamed to it: never a half file."""
    tmp = target.with_name(f".{target.stem}.tmp{target.suffix}")
    write(tmp)
    os.replace(tmp, target)


def image_file(folder: Path, n: int, message, msgtype: str, where: str) -> Path:
    """The image of message ``n`` as a file in ``folder``, written when missing."""
    if msgtype.endswith("CompressedImage"):
        data = bytes(np.asarray(message.data, np.uint8))
        suffix = ".png" if data[:4] == b"\x89PNG" else ".jpg" if data[:2] == b"\xff\xd8" else ".img"
        target = folder / f"{n:06d}{suffix}"
        if not target.exists():
            write_atomically(target, lambda p: p.write_bytes(data))
        return target
    target = folder / f"{n:06d}.png"
    if not target.exists():
        pixels = image_array(message.encoding, int(message.width), int(message.height), int(message.step),
                             bool(message.is_bigendian), message.data, where)

        def write_png(p: Path) -> None:
            if not cv2.imwrite(str(p), pixels, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
                raise InputError(f"{p}: cannot write the cache of the log's images")

        write_atomically(target, write_png)
    return target


def cached_images(folder: Path) -> list[tuple[int, Path]] | None:
    """(stamp ns, file) of the images the index in ``folder`` records; None when there is none (or it is
    damaged); the folder made when missing."""
    index = folder / "index.json"
    if index.is_file():
        try:
            return [(int(t), folder / name) for t, name in json.loads(index.read_text())["images"]]
        except (ValueError, KeyError, TypeError, OSError):
            pass  # a damaged index: the images are read again
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{folder}: cannot create the cache of the log's images ({exc.strerror or exc}); "
                         "set VISLOC_CACHE to a writable folder") from None
    return None


def record_images(folder: Path, images: list[tuple[int, Path]]) -> None:
    """The index of ``folder``'s images, once all are written."""
    write_atomically(folder / "index.json",
                     lambda p: p.write_text(json.dumps({"images": [[t, f.name] for t, f in images]})))
