"""Checks of the files and folders a command will write, made before any slow work.

A command that evaluates for minutes and then cannot write its report loses the minutes; these
checks refuse such a path at once, with one line naming the flag and the path.
"""

from __future__ import annotations

import os
from pathlib import Path

from visloc.errors import InputError


def _probe(path: Path, flag: str) -> None:
    """Open ``path`` for appending (which changes no existing file) and remove it again if it was
    created: the one test that catches a read-only file system, a full quota or missing rights."""
    existed = path.exists()
    try:
        with open(path, "a"):
            pass
    except OSError as exc:
        raise InputError(f"{flag} {path}: cannot write there ({exc.strerror or exc})") from None
    if not existed:
        path.unlink(missing_ok=True)


def require_writable_output(path: Path | str | None, flag: str) -> None:
    """Refuse an output file ``path`` (given by ``flag``) that cannot be written: a folder, a file in a
    folder that does not exist, or a place without write access. None: nothing to check."""
    if path is None:
        return
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{flag} {path}: is a folder; name a file to write")
    parent = path.absolute().parent
    if not parent.exists():
        raise InputError(f"{flag} {path}: folder does not exist")
    if not parent.is_dir():
        raise InputError(f"{flag} {path}: {parent} is not a folder")
    if path.exists() and not path.is_file():
        raise InputError(f"{flag} {path}: is not a regular file")
    _probe(path, flag)


def require_output_folder(folder: Path | str, flag: str, files: tuple[str, ...] = ()) -> None:
    """Refuse an output folder that cannot be made or written: it exists as a file, its parent folder
    does not exist, or it is not writable; ``files``: names the command will write in it, each checked
    too when the folder exists."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{flag} {folder}: exists and is not a folder")
    if not folder.exists():
        parent = folder.absolute().parent
        if not parent.is_dir():
            raise InputError(f"{flag} {folder}: folder {parent} does not exist (only the last folder is created)")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise InputError(f"{flag} {folder}: cannot create a folder in {parent}")
        return
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"{flag} {folder}: cannot write there")
    for name in files:
        require_writable_output(folder / name, flag)
