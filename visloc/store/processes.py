"""Worker processes on this machine for the steps of a one-file ingest after SIFT (structure and the
self-check), with the interface those steps use on a distributed engine (``visloc.store.cluster``):
``n_workers`` and ``run_all``. The tasks are the same functions on the same chunks, so the store gets
the same rows either way; each worker reads the store file itself (SQLite's WAL lets it read what the
ingest committed while the ingest writes).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager

from visloc.errors import InputError

MIN_ITEMS_PER_WORKER = 4  # a step with fewer images per worker runs in this process
POLL_S = 0.5  # how often a wait for results looks whether a worker process has ended


def worker_ended(executor: ProcessPoolExecutor) -> bool:
    """Whether one of the pool's worker processes has ended (killed, out of memory). CPython's pool says so by
    breaking, except when the worker died halfway through sending a result: its manager thread then waits for
    the rest of the message forever, and so would every wait for a result."""
    processes = getattr(executor, "_processes", None) or {}
    return any(p.exitcode is not None for p in list(processes.values()))


def wait_or_broken(executor: ProcessPoolExecutor, futures) -> set[Future]:
    """The futures of ``futures`` that are done, as soon as one is; ``BrokenProcessPool`` when a worker process
    has ended instead (see ``worker_ended``)."""
    while True:
        done, _ = wait(futures, timeout=POLL_S, return_when=FIRST_COMPLETED)
        if done:
            return done
        if worker_ended(executor):
            raise BrokenProcessPool("a worker process ended without its result")


def stop_now(executor: ProcessPoolExecutor) -> None:
    """Stop the pool at once, on an error or an interruption: its processes killed (their tasks are lost; what
    came back is committed) and its manager thread released without waiting for it. A worker killed while
    sending a result leaves the manager thread reading a message that never ends; closing the result queue's
    last writer ends the read, and the thread, instead of leaving the process unable to exit (the executor
    offers no public way to do either)."""
    processes = list((getattr(executor, "_processes", None) or {}).values())
    for process in processes:
        process.kill()
    for process in processes:
        process.join(timeout=10)
    result_queue = getattr(executor, "_result_queue", None)
    if result_queue is not None:
        result_queue._writer.close()
    executor.shutdown(wait=False, cancel_futures=True)


def _init_worker(opencv_threads: int) -> None:
    import cv2

    cv2.setNumThreads(opencv_threads)  # the cores are shared among the workers
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle


class LocalProcesses:
    """``n_workers`` processes of this machine, each running one task at a time."""

    def __init__(self, executor: ProcessPoolExecutor, n_workers: int, what: str):
        self.executor = executor
        self.n_workers = n_workers
        self.what = what

    def worth_spreading(self, n_items: int) -> bool:
        """Whether a step of ``n_items`` is worth starting the workers for (each imports the pipeline first,
        about a second): at least ``MIN_ITEMS_PER_WORKER`` items each."""
        return n_items >= MIN_ITEMS_PER_WORKER * self.n_workers

    def run_all(self, fn: Callable, args: list[tuple]) -> Iterator[tuple[tuple, object]]:
        """(args, ``fn(*args)``) for every tuple of ``args``, as each finishes, at most two tasks per worker
        handed out at once (so that an interrupted step leaves little work in flight); an error is raised
        as it comes, a worker that died as an ``InputError`` saying so."""
        pending = iter(args)
        running: dict[Future, tuple] = {}
        while True:
            while len(running) < 2 * self.n_workers and (a := next(pending, None)) is not None:
                running[self.executor.submit(fn, *a)] = a
            if not running:
                return
            try:
                finished = [(running.pop(future), future.result())
                            for future in wait_or_broken(self.executor, running)]
            except BrokenProcessPool:
                raise InputError(f"{self.what}: a worker process died (killed, or out of memory); what "
                                 "finished before is stored: run the same command again to go on") from None
            yield from finished


@contextmanager
def local_processes(workers: int, what: str) -> Iterator[LocalProcesses]:
    """A pool of ``workers`` processes for the ``with`` block (spawned: OpenCV's threads and fork do not
    mix), their OpenCV sharing this machine's cores; shut down at the end, and stopped at once when the
    block ends on an error or an interruption."""
    threads = max(1, (os.cpu_count() or 1) // workers)
    executor = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_init_worker,
                                   initargs=(threads,))
    try:
        yield LocalProcesses(executor, workers, what)
    except BaseException:
        # interrupted (Ctrl-C, kill) or failed: what came back is committed; stop the tasks in flight now
        # rather than wait for them
        stop_now(executor)
        raise
    executor.shutdown(wait=True)
