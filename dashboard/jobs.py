"""One background worker for slow dashboard work: a newer job supersedes older ones.

GUI callbacks only call ``submit``; the job runs on the worker thread and gets a
``cancelled()`` callable that turns true as soon as a newer job is submitted, so
a long matching run stops within a few candidate pairs once it is out of date.
"""

from __future__ import annotations

import threading
import traceback
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

Job = Callable[[Callable[[], bool]], None]


class LatestJobRunner:
    def __init__(self, on_error: Callable[[str, BaseException], None]):
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="visloc-dashboard-job")
        self._lock = threading.Lock()
        self._generation = 0
        self._on_error = on_error
        self._idle = threading.Event()
        self._idle.set()
        self._pending = 0

    def submit(self, name: str, job: Job) -> Future:
        with self._lock:
            self._generation += 1
            generation = self._generation
            self._pending += 1
            self._idle.clear()

        def cancelled() -> bool:
            return self._generation != generation

        def run() -> None:
            try:
                if not cancelled():
                    job(cancelled)
            except Exception as exc:  # shown in the page; the server keeps running
                traceback.print_exc()
                self._on_error(name, exc)
            finally:
                with self._lock:
                    self._pending -= 1
                    if self._pending == 0:
                        self._idle.set()

        return self._executor.submit(run)

    def wait_idle(self, timeout_s: float | None = None) -> bool:
        return self._idle.wait(timeout_s)

    def shutdown(self) -> None:
        with self._lock:
            self._generation += 1  # cancel whatever runs
        self._executor.shutdown(wait=True, cancel_futures=True)
