"""The distributed engine a sharded ingest runs on: Dask distributed.

Why Dask and not Ray: it is a pure-Python install of a few megabytes (Ray brings its own object
store and control plane, hundreds of megabytes); its nannies restart a worker process that dies
and its scheduler runs the dead worker's tasks again elsewhere (a task is given up only after it
killed three workers); a worker process per core with one task at a time runs CPU-bound OpenCV work
without contention (a local cluster of fewer workers than cores gives each worker's OpenCV the cores
left over); a real cluster is ``dask scheduler`` on one node and ``dask worker ADDRESS`` on each
other. It is an optional extra (``pip install 'visloc[cluster]'``): a single-file store never needs it.
"""

from __future__ import annotations

import logging
import os
import socket
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from visloc.errors import InputError

LISTENER_TIMEOUT_S = 10.0  # how long ingest waits for anything at an address to accept a connection
WORKERS_TIMEOUT_S = 120.0  # how long ingest waits for a first worker to join a scheduler it was pointed at
# glibc's allocator, as a process starts: the mmap threshold grows with the largest block freed, up to 32 MiB
# on 64-bit, and the heap is trimmed above twice it
MMAP_THRESHOLD_BYTES = 32 * 2**20
TRIM_THRESHOLD_BYTES = 2 * MMAP_THRESHOLD_BYTES

_allocator_restored = False


def restore_allocator() -> bool:
    """Undo, in this worker process, the allocator setting a Dask nanny gives its workers.

    A nanny starts each worker with ``MALLOC_TRIM_THRESHOLD_=65536`` (to give memory back to the system
    promptly), which also turns off glibc's growing mmap threshold: every array of more than 128 KiB is
    then mapped and unmapped afresh, and the structure and self-check tasks, which make many such
    arrays, ran a fifth to a third slower in a worker than in a plain process. Setting the thresholds
    glibc grows to by default makes a worker as fast as a process started without the variable; the
    memory a task frees is kept for its next task, as in a plain process. Once per process; False where
    the C library has no ``mallopt`` (not glibc)."""
    global _allocator_restored
    if _allocator_restored:
        return True
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's malloc.h
    _allocator_restored = bool(mallopt(m_mmap_threshold, MMAP_THRESHOLD_BYTES)
                               and mallopt(m_trim_threshold, TRIM_THRESHOLD_BYTES))
    return _allocator_restored


_opencv_threads: int | None = None


def opencv_threads(n: int) -> int:
    """Let OpenCV use ``n`` threads in this worker process (set once per change); returns what OpenCV
    then reports. The same features and structure either way: OpenCV's SIFT and matching give the
    same bits with any number of threads."""
    global _opencv_threads
    import cv2

    if _opencv_threads != n:
        cv2.setNumThreads(n)
        _opencv_threads = n
    return cv2.getNumThreads()


def _in_worker(threads: int, fn: Callable, *args):
    """``fn(*args)`` in a worker process, its allocator restored first (``restore_allocator``) and
    OpenCV given ``threads`` threads (``opencv_threads``)."""
    restore_allocator()
    opencv_threads(threads)
    return fn(*args)


def _require_dask():
    try:
        import distributed
    except ImportError:
        raise InputError("a sharded ingest runs on Dask distributed, which is not installed: "
                         "pip install 'visloc[cluster]'") from None
    return distributed


class Cluster:
    """A client of a Dask cluster: a local one this process started, or one it joined. ``threads``: the
    OpenCV threads of each worker (one on a joined cluster: a worker per core)."""

    def __init__(self, client, n_workers: int, address: str | None, threads: int = 1):
        self.client = client
        self.n_workers = n_workers
        self.address = address
        self.threads = threads

    def worth_spreading(self, n_items: int) -> bool:
        """A step of ``n_items`` runs on the cluster whatever its size (its workers hold what it needs)."""
        return n_items > 0

    def worker_pids(self) -> dict[str, int]:
        """Worker address -> its process id (for a test that kills one)."""
        return self.client.run(os.getpid)

    def extracted(self, fn: Callable, items: list, name: str) -> Iterator[tuple[object, object]]:
        """(item[0], ``fn(item)`` or the ``InputError`` it raised), in ``items``' order, with at most two
        items per worker in flight. A worker that dies has its items run again by another; an item that
        killed three workers ends the iteration with an ``InputError`` naming it."""
        distributed = _require_dask()
        in_flight: deque = deque()
        pending = iter(items)
        width = 2 * max(self.n_workers, 1)
        while True:
            while len(in_flight) < width and (item := next(pending, None)) is not None:
                in_flight.append((item, self.client.submit(_in_worker, self.threads, fn, item, pure=False)))
            if not in_flight:
                return
            item, future = in_flight.popleft()
            try:
                yield item[0], future.result()
            except InputError as exc:
                yield item[0], exc
            except distributed.KilledWorker:
                raise InputError(f"{name}: describing {getattr(item[0], 'image_path', item[0])} killed three "
                                 "workers in turn (out of memory?); the images finished before are stored: "
                                 "run the same command again to go on") from None

    def run_all(self, fn: Callable, args: list[tuple]) -> Iterator[tuple[tuple, object]]:
        """(args, ``fn(*args)``) for every tuple of ``args``, as each finishes; an error is raised as it comes."""
        distributed = _require_dask()
        futures = {self.client.submit(_in_worker, self.threads, fn, *a, pure=False): a for a in args}
        for future in distributed.as_completed(futures):
            yield futures[future], future.result()


def _require_listener(address: str) -> None:
    """Refuse at once an address where nothing accepts a connection (the scheduler is not started, or the port
    is wrong) instead of waiting out the scheduler's connect timeout; a TCP address only (the scheduler's
    default), and a host that accepts is left to the scheduler's own handshake."""
    scheme, _, rest = address.rpartition("://")
    host, _, port = rest.rpartition(":")
    if scheme not in ("", "tcp") or not host or not port.isdigit():
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=LISTENER_TIMEOUT_S).close()
    except OSError as exc:
        raise InputError(f"--address {address}: no Dask scheduler answers there ({exc})") from None


@contextmanager
def open_cluster(workers: int = 2, address: str | None = None) -> Iterator[Cluster]:
    """A cluster for the ``with`` block: with ``address``, the Dask scheduler there; otherwise a local
    cluster of ``workers`` processes of one task at a time each, shut down at the end; their OpenCV
    shares this machine's cores among them (one thread each with a worker per core)."""
    distributed = _require_dask()
    if address:
        _require_listener(address)
        try:
            client = distributed.Client(address, timeout="30s")
        except (OSError, TimeoutError) as exc:
            raise InputError(f"--address {address}: no Dask scheduler answers there ({exc})") from None
        try:
            try:
                client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S)
            except TimeoutError:
                raise InputError(f"--address {address}: no worker joined that scheduler within "
                                 f"{WORKERS_TIMEOUT_S:g} s (start them with 'dask worker {address}')") from None
            yield Cluster(client, max(len(client.scheduler_info().get("workers", {})), 1), address)
        finally:
            client.close()
        return
    if workers < 1:
        raise InputError(f"--workers {workers}: give at least 1")
    cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                       dashboard_address=":0", silence_logs=logging.ERROR)
    client = distributed.Client(cluster)
    try:
        yield Cluster(client, workers, None, threads=max(1, (os.cpu_count() or 1) // workers))
    finally:
        client.close()
        cluster.close()
