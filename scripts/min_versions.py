"""The floors of pyproject.toml's dependencies, as exact pins ("name>=X" becomes "name==X").

    python scripts/min_versions.py [pyproject.toml]   # one "name==X" line per dependency, on stdout

Reads [project] dependencies and the "test" extra. Exits 1, one line per offender on stderr, if a
dependency has no ">=" floor (or has a marker, an extra or a lower bound this simple reading would
silently drop), so the pins always cover every dependency. A cap ("name>=X,<Y", for a release known to
break) is allowed: the floor X is what gets pinned. scripts/check_min_versions.sh installs
these pins and runs tests against them; tests/test_dependency_floors.py imports ``floors``.
"""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path

PYPROJECT = Path(__file__).resolve().parent.parent / "pyproject.toml"
EXTRAS = ("test",)
# "name>=X", or "name>=X,<Y", and nothing else: no extras ([...]), no markers (;), no other bound
FLOOR = re.compile(r"^\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*>=\s*([0-9][0-9A-Za-z.+!-]*)\s*(,\s*<\s*[0-9][0-9A-Za-z.+!-]*\s*)?$")


def requirements(pyproject: Path = PYPROJECT) -> list[str]:
    """Every requirement string of [project] dependencies and the extras in ``EXTRAS``."""
    project = tomllib.loads(pyproject.read_text())["project"]
    reqs = list(project.get("dependencies", []))
    for extra in EXTRAS:
        reqs += project.get("optional-dependencies", {}).get(extra, [])
    return reqs


def floors(pyproject: Path = PYPROJECT) -> tuple[dict[str, str], list[str]]:
    """({name: floor version}, [requirements that are not a plain "name>=X"])."""
    found: dict[str, str] = {}
    bad = []
    for req in requirements(pyproject):
        m = FLOOR.match(req)
        if m is None:
            bad.append(req)
        else:
            found[m.group(1).lower()] = m.group(2)
    return found, bad


def main(argv: list[str]) -> int:
    found, bad = floors(Path(argv[1]) if len(argv) > 1 else PYPROJECT)
    for req in bad:
        print(f"min_versions: {req!r} is not a plain 'name>=X' floor", file=sys.stderr)
    if bad:
        return 1
    for name, version in found.items():
        print(f"{name}=={version}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
