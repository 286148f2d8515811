"""Shared fixtures: stores, a synthetic drive with a known answer, and the real KITTI drive."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from helpers import KITTI_DRIVE, require_drive, run_cli, write_csv_drive
from visloc.db import FeatureStore
from visloc.sources.drives import default_data_root


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
def kitti_evaluation(kitti_root, tmp_path_factory):
    """``visloc evaluate`` on three series (start frames 0, 25, 50) of the real drive, as a user
    runs it: (folder holding kitti.sqlite and eval.json, the JSON report, stdout). The store then
    holds both cameras' features and the counts of every query frame 0, 10, ..., 100."""
    import json

    tmp = tmp_path_factory.mktemp("kitti")
    out = tmp / "eval.json"
    result = run_cli("evaluate", kitti_root, "--drive", KITTI_DRIVE, "--db", tmp / "kitti.sqlite",
                     "--start-frames", "0,25,50", "--json", out, timeout=1800)
    assert result.returncode == 0, result.stderr
    return tmp, json.loads(out.read_text()), result.stdout


@pytest.fixture(scope="session")
def kitti_two_runs(kitti_evaluation, kitti_root):
    """Two saved runs of the same series, as ``evaluate`` wrote them: the session's evaluation (the paper's
    parameters) and the same at τ1 0.7, matched on the same store."""
    tmp, _, _ = kitti_evaluation
    other = tmp / "eval_tau1_0.7.json"
    result = run_cli("evaluate", kitti_root, "--drive", KITTI_DRIVE, "--db", tmp / "kitti.sqlite",
                     "--start-frames", "0,25,50", "--tau1", "0.7", "--json", other, timeout=1800)
    assert result.returncode == 0, result.stderr
    return tmp / "eval.json", other


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
                              args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                                    "--disable-background-networking", "--disable-component-update",
                                    "--no-first-run"])
        yield b
        b.close()


