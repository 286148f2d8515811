"""Running a localizer over queries: the one query loop every command uses, and what a query costs.

``steps_of`` (and ``run_queries``, its steps as a list) steps a localizer through queries in order and times each one as a live
system would spend it (``latency_ms``). Where the queries come from is the caller's: stored
features (``QuerySet.query``) or images read and described now (``visloc.sources.queries.extract_queries``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import NamedTuple

from visloc.tracking.localizer import FirstMeasurement, Localizer, StepResult
from visloc.retrieval.matching import MatchCancelled, PairCountCache


class TimedStep(NamedTuple):
    result: StepResult
    latency_ms: float  # see latency_ms()


def latency_ms(result: StepResult, cache: PairCountCache | None = None) -> float:
    """What a live system would spend on this query, ms: its SIFT time, its retrieval, the query
    side of its measurement (matching, RANSAC, PnP; database-side structure building is not
    counted) and the filter step.

    Work a cache answered costs what it took when first done: candidate pairs their recorded
    matching time (``cache``, the counter the retrieval used), a memoised measurement its
    recorded time.
    """
    retrieval_ms = result.timings.retrieval_ms
    if cache is not None:  # take this step's fresh matching out, put every candidate pair's first cost in
        retrieval_ms = max(retrieval_ms - cache.fresh_ms, 0.0) + cache.cost_ms(result.query.key,
                                                                              result.retrieval.candidates)
    return result.query.sift_ms + retrieval_ms + result.measurement.query_side_ms + result.timings.filter_ms


def steps_of(localizer: Localizer, queries: Iterable, *, cache: PairCountCache | None = None,
             cancelled: Callable[[], bool] | None = None, first: FirstMeasurement | None = None) -> Iterator[TimedStep]:
    """The one query loop: step ``localizer`` through ``queries`` (``visloc.Query``) in order, from its
    current state, yielding each step with its latency as soon as it is done (nothing is kept).

    ``cache``: the ``PairCountCache`` the localizer's retrieval counts with, if any (for latency).
    ``cancelled()`` is asked after each query and raises ``MatchCancelled`` when true (wrap the
    counter with ``visloc.retrieval.matching.cancellable`` to stop inside a query too).
    ``first(measurement, retrieval)``: what starts the track, while the filter holds none (``Localizer.step``).
    """
    for query in queries:
        result = localizer.step(query, first=first)
        if cancelled is not None and cancelled():
            raise MatchCancelled()
        yield TimedStep(result, latency_ms(result, cache))


def run_queries(localizer: Localizer, queries: Iterable, *, cache: PairCountCache | None = None,
                cancelled: Callable[[], bool] | None = None,
                progress: Callable[[int], None] | None = None,
                on_step: Callable[[TimedStep], None] | None = None) -> list[TimedStep]:
    """Every step of ``steps_of`` as a list; ``progress(done)`` is told of each query done, ``on_step(step)``
    is handed each step as soon as it is done."""
    out: list[TimedStep] = []
    for step in steps_of(localizer, queries, cache=cache, cancelled=cancelled):
        out.append(step)
        if on_step:
            on_step(step)
        if progress:
            progress(len(out))
    return out
