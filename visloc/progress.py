"""Progress of long work on stderr: a tqdm bar on a terminal, plain lines with an estimate of the
time left otherwise (under nohup, in CI, into a pipe or a log file), so a long run never looks hung.

``progress_reporter(desc, unit)`` returns the ``progress(done, total)`` callback the engine's long
loops accept (ingest, structure, evaluation series, tracked frames). Off a terminal it prints a line
at the first call, at most every ``interval_s`` seconds after, and at the end::

    ingest 2011_09_26_drive_0001/image_00: 40/108 images (37%), 31 s elapsed, about 52 s left
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

INTERVAL_S = 10.0


def duration_text(seconds: float) -> str:
    """``31 s``, ``4 min 05 s``, ``1 h 02 min``."""
    s = max(0, int(round(seconds)))
    if s < 120:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def progress_line(desc: str, unit: str, done: int, total: int, elapsed_s: float) -> str:
    """One plain progress line; the time left assumes the rate so far holds."""
    percent = f" ({100 * done / total:.0f}%)" if total else ""
    head = f"{desc}: {done}/{total} {unit}{percent}"
    if done >= total:
        return f"{head}, done in {duration_text(elapsed_s)}"
    if done <= 0:
        return f"{head}, started"
    left = elapsed_s / done * (total - done)
    return f"{head}, {duration_text(elapsed_s)} elapsed, about {duration_text(left)} left"


def _is_terminal(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def progress_reporter(desc: str, unit: str, *, stream: TextIO | None = None,
                      clock: Callable[[], float] = time.monotonic, interval_s: float = INTERVAL_S,
                      terminal: bool | None = None) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback reporting on ``stream`` (default stderr): a tqdm bar when
    the stream is a terminal (``terminal`` overrides the check), else plain lines. Time counts from
    the first call if it reports 0 done (the work's start), else from the reporter's creation.
    Nothing is printed for work of total 0."""
    stream = sys.stderr if stream is None else stream
    if _is_terminal(stream) if terminal is None else terminal:
        return _bar(desc, unit, stream)
    created = clock()
    state = {"start": None, "last": None, "finished": False}

    def progress(done: int, total: int) -> None:
        now = clock()
        if state["start"] is None:
            state["start"] = now if done <= 0 else created
        if total <= 0 or state["finished"]:
            return
        end = done >= total
        if state["last"] is None or end or now - state["last"] >= interval_s:
            state["last"] = now
            state["finished"] = end
            print(progress_line(desc, unit, done, total, now - state["start"]), file=stream, flush=True)

    return progress


def _bar(desc: str, unit: str, stream: TextIO) -> Callable[[int, int], None]:
    from tqdm import tqdm

    bar: dict = {}

    def progress(done: int, total: int) -> None:
        if "bar" not in bar:
            bar["bar"] = tqdm(total=total, desc=desc, unit=unit, file=stream, leave=False)
        b = bar["bar"]
        b.update(done - b.n)
        if done >= total:
            b.close()

    return progress
