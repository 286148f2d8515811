"""The architecture's rules, checked on the source: layers, sizes, packaging, and docs that match
what was measured."""

from __future__ import annotations

import ast
import functools
import json
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from helpers import REPO

# folder -> the package it installs as (pyproject.toml's package-dir)
PACKAGES = {"visloc": "visloc", "db": "visloc.db", "dashboard": "visloc.dashboard", "bench": "visloc.bench"}
MAX_MODULE_LINES = 450


@functools.cache
def modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module the wheel installs (subpackages included)."""
    out = {}
    for folder, package in PACKAGES.items():
        for path in sorted((REPO / folder).rglob("*.py")):
            parts = [package, *path.relative_to(REPO / folder).with_suffix("").parts]
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


@functools.cache
def packages() -> tuple[str, ...]:
    """Every package the wheel installs: the folders above and each subpackage of visloc/."""
    subpackages = sorted(f"visloc.{p.parent.name}" for p in (REPO / "visloc").glob("*/__init__.py"))
    return (*PACKAGES.values(), *subpackages)


def imports_of(path: Path, name: str) -> set[str]:
    """The project modules ``path`` imports, anywhere in the file (functions included)."""
    found = set()
    package = name if path.stem == "__init__" else name.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            found.add(base)
            found.update(f"{base}.{a.name}" for a in node.names)
    known = modules()
    return {m for m in found if m in known}


def test_no_import_cycles_between_modules():
    mods = modules()
    graph = {name: imports_of(path, name) - {name} for name, path in mods.items()}
    # a package's __init__ re-exports its modules; an edge into it stands for the modules it names
    state: dict[str, int] = {}
    cycles = []

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if nxt in packages() and node.startswith(nxt + "."):
                continue  # a module importing names from its own package's __init__ is resolved at import time
            if state.get(nxt) == 1:
                cycles.append(stack[stack.index(nxt):] + [nxt] if nxt in stack else [node, nxt])
            elif state.get(nxt) is None:
                visit(nxt, stack + [nxt])
        state[node] = 2

    for name in sorted(graph):
        if state.get(name) is None:
            visit(name, [name])
    assert cycles == [], cycles


def test_no_module_is_over_450_lines():
    long = {name: n for name, path in modules().items() if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES}
    assert long == {}


def test_sql_lives_only_in_the_store():
    sql = re.compile(r"\b(SELECT\s+\S+.*\bFROM|INSERT\s+INTO|CREATE\s+TABLE|ALTER\s+TABLE|UPDATE\s+\w+\s+SET)\b")
    offenders = [name for name, path in modules().items()
                 if not name.startswith("visloc.db") and sql.search(path.read_text())]
    assert offenders == []
    # one door: only the workspace, and ingest (which fills a store through it), open a store
    users = sorted(name for name, path in modules().items()
                   if not name.startswith("visloc.db") and re.search(r"\bFeatureStore\b", path.read_text()))
    assert users == ["visloc.store.ingest", "visloc.store.workspace"]


def test_the_dashboard_uses_only_the_public_api():
    for name, path in modules().items():
        if name.startswith("visloc.dashboard"):
            engine = {m for m in imports_of(path, name) if not m.startswith("visloc.dashboard")}
            assert engine <= {"visloc"}, (name, engine)


# the pipeline's rings, lowest first: a module imports from its own ring or lower ones only, so no import
# runs back up the pipeline (the dashboard reads the engine through its public face, ``visloc``, alone)
RINGS = [
    ("visloc.errors", "visloc.geo", "visloc.progress", "visloc.stats", "visloc.params", "visloc.db"),
    ("visloc.geometry",), ("visloc.features",), ("visloc.sources",), ("visloc.retrieval",), ("visloc.pose",),
    ("visloc.store",), ("visloc.tracking",), ("visloc.protocols",), ("visloc.results",), ("visloc.bench",),
    ("visloc",), ("visloc.dashboard",), ("visloc.cli", "visloc.__main__"),
]


def ring_of(module: str) -> int:
    best = max((prefix for ring in RINGS for prefix in ring if module == prefix or module.startswith(prefix + ".")
                and prefix != "visloc"), key=len, default="visloc" if module == "visloc" else None)
    assert best is not None, f"{module} is on no ring: add its subpackage to RINGS"
    return next(k for k, ring in enumerate(RINGS) if best in ring)


def test_no_import_runs_back_up_the_pipeline():
    up = []
    for name, path in modules().items():
        for target in imports_of(path, name):
            if ring_of(target) > ring_of(name) and not (name.startswith("visloc.dashboard") and target == "visloc"):
                up.append(f"{name} -> {target}")
    assert up == []


def test_every_stage_of_the_pipeline_is_a_subpackage_that_says_what_it_holds_and_may_import():
    stages = [p.parent for p in sorted((REPO / "visloc").glob("*/__init__.py"))]
    assert {p.name for p in stages} >= {"sources", "features", "geometry", "retrieval", "pose", "store", "tracking",
                                         "protocols", "results", "cli", "params"}
    for folder in stages:
        doc = ast.get_docstring(ast.parse((folder / "__init__.py").read_text())) or ""
        assert "Imports" in doc, f"{folder.name}/__init__.py: say what the stage holds and what it may import"
    loose = sorted(p.name for p in (REPO / "visloc").glob("*.py"))
    assert loose == ["__init__.py", "__main__.py", "errors.py", "geo.py", "progress.py", "stats.py"], loose


def test_the_architecture_page_names_every_stage_and_module_of_the_tree():
    """docs/architecture.md's table of the tree stays true: a row per folder of visloc/ naming each of its modules,
    and no row for a folder that is gone."""
    page = (REPO / "docs" / "architecture.md").read_text()
    rows = {m.group(1): m.group(2) for m in re.finditer(r"^\| `(\w+)/` \| [^|]+ \| (.+) \|$", page, re.M)}
    for folder in sorted(p.parent for p in (REPO / "visloc").glob("*/__init__.py")):
        assert folder.name in rows, f"docs/architecture.md: no row for visloc/{folder.name}/"
        have = {p.stem for p in folder.glob("*.py") if not p.stem.startswith("__")}
        named = set(re.findall(r"`(\w+)`", rows[folder.name]))
        assert have <= named, f"visloc/{folder.name}/: {sorted(have - named)} not on the architecture page"
    gone = sorted(name for name in rows if not (REPO / "visloc" / name / "__init__.py").exists())
    assert gone == [], f"docs/architecture.md describes folders visloc/ no longer has: {gone}"


def test_no_private_name_is_imported_from_another_module():
    for name, path in modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("visloc"):
                private = [a.name for a in node.names if a.name.startswith("_")]
                assert private == [], (name, node.module, private)


def test_no_top_level_package_but_visloc(tmp_path):
    """The wheel holds the visloc namespace only: installing it never shadows another db or dashboard."""
    result = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                             "-w", str(tmp_path), str(REPO)], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    (wheel,) = tmp_path.glob("visloc-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/", 1)[0] for n in names if not n.split("/", 1)[0].endswith(".dist-info")}
    assert top == {"visloc"}
    for package in packages():
        assert f"{package.replace('.', '/')}/__init__.py" in names


def test_the_results_page_is_the_digest_rendered():
    """docs/results.md is exactly what scripts/results.py renders from docs/results/digest.json."""
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        import results
    finally:
        sys.path.pop(0)
    digest = json.loads((REPO / "docs" / "results" / "digest.json").read_text())
    assert (REPO / "docs" / "results.md").read_text() == results.render_page(digest)


@pytest.mark.parametrize("path", ["README.md", "docs/method.md", "docs/architecture.md", "docs/results.md",
                                  "docs/formats.md"])
def test_user_facing_text_names_no_issue(path):
    text = (REPO / path).read_text()
    assert not re.search(r"\bissue\s*#?\d", text, re.IGNORECASE), path


def test_the_readme_is_a_users_document():
    readme = (REPO / "README.md").read_text()
    assert len(readme.splitlines()) <= 300
    assert "bash scripts/test.sh" in readme.split("\n## ", 1)[0]  # the test command, first thing
    assert "bash scripts/test.sh" in (REPO / ".ci" / "run").read_text()
