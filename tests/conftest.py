"""Shared fixtures: stores, a synthetic drive with a known answer, and the real KITTI drive.

Every expensive artifact (a store of a real drive, an evaluation of it, a pair of synthetic drives in a
store) is made once per test run, whichever pytest-xdist worker asks first, behind a file lock in a
folder all workers share (``helpers.built_once``); a test that writes into one works on its own copy.
The markers tell the truth (``pytest_collection_modifyitems``): a test that reads the real drives (the
``kitti_root`` fixture) is marked ``kitti``, one that drives the browser (``browser``) is marked ``browser``,
both given here from the fixtures, and no other test carries those marks."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest

from helpers import (CSV_PAIR_FRAMES, DRIVE_0005, DRIVE_0005_FRAMES, KITTI_DRIVE, OTHER_MEAS_VAR_M2, OTHER_RUN_NAME,
                     PAPER_CONTRAST, SERIES_STARTS, built_once, copy_store, require_drive, run_cli, write_csv_drive)
from visloc.db import FeatureStore
from visloc.sources.drives import default_data_root


# -- artifacts made once per run, shared by the workers ------------------------------------------------------

@pytest.fixture(scope="session")
def shared_tmp(tmp_path_factory, worker_id) -> Path:
    """A folder every pytest-xdist worker of this run shares (without xdist: the run's own temporary folder)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if worker_id != "master" else base


@pytest.fixture(scope="session", autouse=True)
def _cache_of_the_run(tmp_path_factory):
    """What visloc caches (a log's images, map tiles) goes to this run's temporary folder, never the home
    folder of whoever runs the tests; the commands the tests start inherit it."""
    os.environ["VISLOC_CACHE"] = str(tmp_path_factory.mktemp("visloc_cache"))


@pytest.fixture
def memory_store():
    store = FeatureStore.memory()
    yield store
    store.close()


@pytest.fixture
def tmp_store(tmp_path):
    store = FeatureStore(tmp_path / "store.sqlite", create=True)
    yield store
    store.close()


@pytest.fixture(scope="session")
def kitti_root() -> Path:
    root = default_data_root()
    require_drive(root / "2011_09_26" / (KITTI_DRIVE + "_sync"))
    return root


@pytest.fixture(scope="session")
def store_0005(kitti_root, shared_tmp) -> Path:
    """The first ``DRIVE_0005_FRAMES`` frames of drive 0005's left camera in a store, made once per run by
    ``visloc ingest --limit`` (features, global vectors, structure, self-check). A test that writes into it
    copies it (``copy_store``)."""
    require_drive(kitti_root / "2011_09_26" / f"{DRIVE_0005}_sync")

    def build(folder: Path) -> dict:
        result = run_cli("ingest", kitti_root, "--drive", DRIVE_0005, "--camera", "image_00", "--db",
                         folder / "store.sqlite", "--limit", DRIVE_0005_FRAMES, "--workers", "2", *PAPER_CONTRAST,
                         timeout=1800)
        assert result.returncode == 0, result.stderr
        return {}

    folder, _ = built_once(shared_tmp, "drive_0005", build)
    return folder / "store.sqlite"


@pytest.fixture(scope="session")
def kitti_evaluation(kitti_root, shared_tmp):
    """``visloc evaluate`` on two series (start frames 0 and 50) of the real drive, as a user runs it:
    (folder holding kitti.sqlite and eval.json, the JSON report, stdout). The store then holds both cameras'
    features and the counts of every query frame 0, 10, ..., 100: the queries of a run over the whole drive at
    one a second, the dashboard's first. Shared: a test that writes into the store copies it first
    (``copy_store``)."""
    def build(folder: Path) -> dict:
        result = run_cli("evaluate", kitti_root, "--drive", KITTI_DRIVE, "--db", folder / "kitti.sqlite",
                         "--start-frames", SERIES_STARTS, "--json", folder / "eval.json", *PAPER_CONTRAST, timeout=1800)
        assert result.returncode == 0, result.stderr
        return {"stdout": result.stdout}

    folder, made = built_once(shared_tmp, "kitti_0001", build)
    return folder, json.loads((folder / "eval.json").read_text()), made["stdout"]


@pytest.fixture(scope="session")
def kitti_refined(kitti_evaluation, kitti_root, shared_tmp):
    """The same two series in the refined mode, with the smoother, on a copy of the session's store:
    (the JSON report, stdout)."""
    evaluated, _, _ = kitti_evaluation

    def build(folder: Path) -> dict:
        store = copy_store(evaluated / "kitti.sqlite", folder)
        result = run_cli("evaluate", kitti_root, "--drive", KITTI_DRIVE, "--db", store, "--start-frames", SERIES_STARTS,
                         "--mode", "refined", "--smooth", "--json", folder / "refined.json", timeout=1800)
        assert result.returncode == 0, result.stderr
        return {"stdout": result.stdout}

    folder, made = built_once(shared_tmp, "kitti_0001_refined", build)
    return json.loads((folder / "refined.json").read_text()), made["stdout"]


@pytest.fixture(scope="session")
def kitti_two_runs(kitti_evaluation, kitti_root, shared_tmp):
    """Two saved runs of the same series, as ``evaluate`` wrote them: the session's evaluation (the paper's
    parameters) and the same with the measurement variance R at ``OTHER_MEAS_VAR_M2`` (σ 5 m), filtered from
    the counts a copy of the session's store keeps (no matching), which stays beside them (``kitti.sqlite``: a
    page tuned from that run finds its counts there)."""
    evaluated, _, _ = kitti_evaluation

    def build(folder: Path) -> dict:
        shutil.copy(evaluated / "eval.json", folder / "eval.json")  # the two runs side by side
        store = copy_store(evaluated / "kitti.sqlite", folder)
        result = run_cli("evaluate", kitti_root, "--drive", KITTI_DRIVE, "--db", store, "--start-frames", SERIES_STARTS,
                         "--meas-var-m2", OTHER_MEAS_VAR_M2, "--json", folder / OTHER_RUN_NAME, timeout=1800)
        assert result.returncode == 0, result.stderr
        return {}

    folder, _ = built_once(shared_tmp, "kitti_0001_meas_var_25", build)
    return folder / "eval.json", folder / OTHER_RUN_NAME


@pytest.fixture(scope="session")
def csv_pair(shared_tmp) -> SimpleNamespace:
    """Two synthetic CSV drives of the same strip, ``CSV_PAIR_FRAMES`` frames each at 2 Hz: a database drive
    (folder ``dbdrive``) and a query drive shifted by a quarter frame (``querydrive``, the same times and
    places), and a store of the database drive made by ``visloc ingest`` as a user makes it. Made once per
    run: ``folder``, ``db_csv``, ``query_csv``, ``store``, ``n_frames``; a test that writes into the store
    copies it (``copy_store``)."""
    def build(folder: Path) -> dict:
        db_csv = write_csv_drive(folder / "dbdrive", n_frames=CSV_PAIR_FRAMES)
        write_csv_drive(folder / "querydrive", n_frames=CSV_PAIR_FRAMES, offset_px=30)
        result = run_cli("ingest", db_csv, "--db", folder / "store.sqlite", "--workers", "1")
        assert result.returncode == 0, result.stderr
        assert f"dbdrive/camera: {CSV_PAIR_FRAMES} added, 0 already stored" in result.stdout
        return {}

    folder, _ = built_once(shared_tmp, "csv_pair", build)
    return SimpleNamespace(folder=folder, db_csv=folder / "dbdrive" / "geotags.csv",
                           query_csv=folder / "querydrive" / "geotags.csv", store=folder / "store.sqlite",
                           n_frames=CSV_PAIR_FRAMES)


@pytest.fixture
def csv_drive(tmp_path) -> Path:
    return write_csv_drive(tmp_path / "drive")


CHROMIUM = Path("/usr/bin/chromium")


@pytest.fixture(scope="session")
def browser():
    """One headless Debian chromium for the whole session, driven through playwright (its sync API
    allows one instance per thread, so every browser test shares this one)."""
    if not CHROMIUM.exists():
        if os.environ.get("CI"):
            pytest.fail(f"{CHROMIUM} missing: scripts/test.sh installs it (scripts/install_chromium.sh)")
        pytest.skip(f"{CHROMIUM} not installed (bash scripts/install_chromium.sh)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True,
                              # software compositing: WebGL is drawn by SwiftShader either way, the rest of the
                              # page is cheaper to composite without it (about a fifth less CPU while a page plays)
                              args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                                    "--disable-gpu-compositing", "--disable-background-networking",
                                    "--disable-component-update", "--no-first-run"])
        yield b
        b.close()


@pytest.fixture(autouse=True)
def _close_pages_a_test_opened(request):
    """After a browser test, close the pages it opened and left open (a page left open keeps its 3D view and
    websocket alive for the rest of the run: about a fifth of a core idle, more while its server sends
    updates); a module fixture's page is kept."""
    if "browser" not in request.fixturenames:
        yield
        return
    browser = request.getfixturevalue("browser")
    before = {id(page) for context in browser.contexts for page in context.pages}
    yield
    for context in list(browser.contexts):
        opened = [page for page in context.pages if id(page) not in before]
        for page in opened:
            page.close()
        if opened and not context.pages:
            context.close()


# -- markers that tell the truth ------------------------------------------------------------------------------

# a marker and the fixture that makes it true: a test is marked exactly when it uses the fixture, directly or
# through another fixture. The marks are given here, from the fixtures, so they cannot lie; a test module
# marks only ``slow`` itself.
MARKED_BY_FIXTURE = {"kitti": "kitti_root", "browser": "browser"}
# session fixtures made by one process on one core (a refined evaluation): the tests that use one run on the same
# worker, so that the other worker goes on with other tests instead of waiting for it (about 50 s otherwise)
ONE_WORKER_FIXTURES = {"kitti_refined"}
SLOW_S = 5.0  # a test whose call takes longer is slow; the summary names those not marked so


@pytest.hookimpl(tryfirst=True)  # before ``-m`` selects by the marks
def pytest_collection_modifyitems(config, items):
    wrong = []
    for item in items:
        marks = {m.name for m in item.iter_markers()}
        for mark, fixture in MARKED_BY_FIXTURE.items():
            if fixture in item.fixturenames:
                item.add_marker(mark)
            elif mark in marks:
                wrong.append(f"{item.nodeid}: marked {mark} but does not use the fixture {fixture}")
    if wrong:
        raise pytest.UsageError("markers that do not tell the truth:\n" + "\n".join(wrong))
    # the longest tests first, the rest in their order: the workers end together (the longest-first rule)
    items.sort(key=lambda item: item.get_closest_marker("longest") is None)
    if not config.pluginmanager.hasplugin("xdist"):
        return
    for item in items:  # with pytest-xdist's --dist loadgroup: a module-scoped fixture is made on one worker
        if _module_fixtures(item):
            item.add_marker(pytest.mark.xdist_group(item.module.__name__))
        elif ONE_WORKER_FIXTURES & set(item.fixturenames):
            item.add_marker(pytest.mark.xdist_group(min(ONE_WORKER_FIXTURES & set(item.fixturenames))))


def pytest_runtest_setup(item):
    """A test pytest-xdist should have kept with its group, when the group did not reach its id (pytest-xdist 3.8
    with pytest 9.2): the workers would each build its module's server or store. It fails, saying why."""
    if (getattr(item.config.option, "loadgroup", False) and item.get_closest_marker("xdist_group")
            and "@" not in item.nodeid):
        pytest.fail(f"pytest-xdist's --dist loadgroup does not group with pytest {pytest.__version__}: "
                    "install the pytest that pyproject.toml names", pytrace=False)


def _module_fixtures(item) -> list[str]:
    """The module-scoped fixtures ``item`` uses (a store, a server, made once for its module's tests)."""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return []
    return [name for name, defs in info.name2fixturedefs.items() if defs and defs[-1].scope == "module"]


def pytest_terminal_summary(terminalreporter):
    unmarked = sorted((report.duration, report.nodeid) for report in terminalreporter.stats.get("passed", [])
                      if report.when == "call" and report.duration > SLOW_S and "slow" not in report.keywords)
    if unmarked:
        terminalreporter.section("tests over 5 s that are not marked slow")
        for duration, nodeid in reversed(unmarked):
            terminalreporter.write_line(f"{duration:6.1f} s  {nodeid}")
