"""The inputs and faults visloc is tested against, as data: the tests are parametrised by these
tables and ``scripts/reliability.py`` renders them as docs/reliability.md, so the page lists
exactly what the tests try.

Each fault test module defines ``FAULTS``, a list of ``Fault``, and parametrises its tests with
``params(FAULTS)``; a test (tests/test_reliability_page.py) checks that every fault listed is
also collected as a test and that the page equals what the tables render.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

import pytest

# the test modules holding fault tables, in the order the page shows them
FAULT_MODULES = (
    "test_faults_input",
    "test_faults_store",
    "test_faults_trust",
    "test_faults_process",
    "test_faults_params",
    "test_faults_dashboard",
    "test_faults_shards",
    "test_logs",
)


@dataclass(frozen=True)
class Fault:
    id: str  # the pytest id, unique across all tables
    area: str  # the page's section, e.g. "CSV drive"
    tried: str  # the input or fault, as a user meets it
    gets: str  # what visloc does about it

    def __post_init__(self) -> None:
        assert self.id and " " not in self.id, self.id
        assert "|" not in self.tried + self.gets, "the page is a Markdown table"


def params(faults: list[Fault]) -> list:
    """``pytest.mark.parametrize("fault", params(FAULTS))``: one test per fault, named by its id."""
    ids = [f.id for f in faults]
    assert len(ids) == len(set(ids)), "fault ids must be unique"
    return [pytest.param(f, id=f.id) for f in faults]


def all_faults() -> list[Fault]:
    """Every table, in page order."""
    out: list[Fault] = []
    for name in FAULT_MODULES:
        out.extend(importlib.import_module(name).FAULTS)
    ids = [f.id for f in out]
    assert len(ids) == len(set(ids)), "fault ids must be unique across tables"
    return out
