"""pyproject.toml's dependency floors, checked where that is cheap (no network, no install).

The full check installs every floor at once and runs the tests: scripts/check_min_versions.sh. This file
keeps the floors from sliding back below what the code is known to need, and every dependency declared.
"""

from __future__ import annotations

import ast
import importlib.metadata
import importlib.util
import re
import sys

import cv2
import numpy as np
import pytest
import sqlite_utils

from helpers import REPO

_spec = importlib.util.spec_from_file_location("min_versions", REPO / "scripts" / "min_versions.py")
min_versions = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(min_versions)

FLOORS, NOT_PLAIN = min_versions.floors(REPO / "pyproject.toml")
RUNTIME_FOLDERS = ("visloc", "db", "dashboard", "bench")  # what the wheel installs

# The lowest version the code works with, and why older ones fail (each measured with check_min_versions.sh).
LOWEST_WORKING = {
    "sqlite-utils": ("4.0", "Database.atomic, the store's transactions, came with 4.0 (3.x: 'super' object "
                            "has no attribute 'atomic')"),
    "numpy": ("2.0", "np.concat came with numpy 2.0"),
    "opencv-python-headless": ("4.13.0.90", "cv2.utils.logging is missing up to 4.12"),
    "faiss-cpu": ("1.9", "1.8 is built for numpy 1: under numpy 2 'numpy.core.multiarray failed to import'"),
    "matplotlib": ("3.8.4", "3.8.0 to 3.8.3 require numpy<2"),
    "setuptools": ("77.0.1", "license = \"MIT\" (PEP 639) needs 77, and 77.0.0 is not on the index"),
}

# APIs the code calls that older releases lack: they must exist in the installed version too.
APIS = {
    "sqlite_utils.Database.atomic": lambda: sqlite_utils.Database.atomic,
    "numpy.concat": lambda: np.concat,
    "cv2.utils.logging.setLogLevel": lambda: cv2.utils.logging.setLogLevel,
}


def release(version: str) -> tuple[tuple[int, ...], bool]:
    """(release numbers without trailing zeros, is a pre-release): enough to order the plain versions here."""
    m = re.match(r"\d+(\.\d+)*", version)
    assert m, f"not a version: {version!r}"
    numbers = [int(x) for x in m.group(0).split(".")]
    while numbers and numbers[-1] == 0:
        numbers.pop()
    return tuple(numbers), bool(re.match(r"[.-]?(a|b|rc|dev|alpha|beta|c)\d*", version[m.end():]))


def at_least(version: str, floor: str) -> bool:
    (v, v_pre), (f, f_pre) = release(version), release(floor)
    return v > f or (v == f and (f_pre or not v_pre))


def test_the_version_order_used_here():
    assert at_least("4.2.1", "4.0") and at_least("4.0", "4") and at_least("4.13.0.90", "4.13.0.90")
    assert not at_least("3.39.1", "4.0") and not at_least("4.0rc4", "4.0") and not at_least("4.12.0.88", "4.13.0.90")
    assert at_least("1.11.0.post1", "1.9") and not at_least("1.8.0.post1", "1.9")


def test_every_dependency_has_a_plain_floor():
    assert not NOT_PLAIN, f"not a plain 'name>=X' (or capped 'name>=X,<Y') floor (scripts/check_min_versions.sh pins 'name==X'): {NOT_PLAIN}"
    assert len(FLOORS) == len(min_versions.requirements(REPO / "pyproject.toml")), "a dependency is listed twice"


@pytest.mark.parametrize("name", sorted(LOWEST_WORKING))
def test_no_floor_below_the_lowest_version_that_works(name):
    lowest, why = LOWEST_WORKING[name]
    assert name in FLOORS, f"{name} is no longer a dependency: drop it from LOWEST_WORKING"
    assert at_least(FLOORS[name], lowest), f"{name}>={FLOORS[name]} is too low, the code needs {lowest}: {why}"


@pytest.mark.parametrize("api", sorted(APIS))
def test_the_installed_dependencies_have_the_apis_the_code_calls(api):
    assert APIS[api]() is not None


def test_sqlite_utils_floor_has_database_atomic():
    from visloc.db.connection import Database

    assert issubclass(Database, sqlite_utils.Database)  # its atomic() calls sqlite-utils' for nested transactions
    assert hasattr(sqlite_utils.Database, "atomic"), "the installed sqlite-utils has no Database.atomic"
    assert release(FLOORS["sqlite-utils"])[0][:1] >= (4,), "Database.atomic needs sqlite-utils 4"


@pytest.mark.parametrize("name", sorted(FLOORS))
def test_the_installed_version_meets_the_floor(name):
    installed = importlib.metadata.version(name)
    assert at_least(installed, FLOORS[name]), f"{name} {installed} is installed, below its floor {FLOORS[name]}"


def third_party_imports(folders: tuple[str, ...]) -> dict[str, str]:
    """Top-level module -> a file importing it, for the modules neither stdlib nor the repo's own."""
    local = {"visloc"} | {p.stem for d in ("tests", "scripts", "benchmarks") for p in (REPO / d).glob("*.py")}
    found: dict[str, str] = {}
    for folder in folders:
        for path in sorted((REPO / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for top in (n.split(".")[0] for n in names):
                    if top not in sys.stdlib_module_names and top not in local:
                        found.setdefault(top, str(path.relative_to(REPO)))
    return found


@pytest.mark.parametrize("folders, extras", [(RUNTIME_FOLDERS, False), (("tests",), True)],
                         ids=["installed-code", "tests"])
def test_every_third_party_import_is_a_declared_dependency(folders, extras):
    project = min_versions.tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    # the installed code may also import its optional extra's engine, behind an error that names the extra
    runtime = project["dependencies"] + project["optional-dependencies"]["cluster"]
    declared = {re.split(r"[<>=!~ ;\[]", r, maxsplit=1)[0].lower() for r in runtime}
    if extras:
        declared |= set(FLOORS)
    providers = importlib.metadata.packages_distributions()
    missing = {module: where for module, where in third_party_imports(folders).items()
               if not {d.lower() for d in providers.get(module, [])} & declared}
    assert not missing, f"imported but not declared in pyproject.toml (module: a file importing it): {missing}"
