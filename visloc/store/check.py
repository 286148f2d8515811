"""``visloc check``: is a store whole? SQLite's own integrity check, every table and column the schema
needs, every BLOB against its checksum and the counts its row states (``visloc.db.integrity``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from visloc.db.integrity import Damage, missing_schema, row_counts, scan, sqlite_problems
from visloc.store.workspace import Workspace


@dataclass(frozen=True)
class CheckReport:
    path: Path
    sqlite_problems: tuple[str, ...]  # what SQLite's integrity check found
    missing: tuple[str, ...]  # tables, columns and indexes the schema needs that the store lacks
    damage: tuple[Damage, ...]  # damaged rows, image by image
    counts: dict[str, int] = field(default_factory=dict)  # rows checked per table

    @property
    def clean(self) -> bool:
        return not (self.sqlite_problems or self.missing or self.damage)

    def damaged_images(self) -> dict[str, list[str]]:
        """image ("drive/camera frame N", or "array KEY") -> what is wrong with it, in scan order."""
        out: dict[str, list[str]] = {}
        for d in self.damage:
            out.setdefault(d.image, []).append(d.problem)
        return out

    def summary(self) -> tuple[list[str], bool]:
        return self.lines(), self.clean

    def lines(self) -> list[str]:
        """One line per problem of the file and per damaged image, then the summary."""
        label = str(self.path)
        out = [f"{label}: SQLite integrity check: {p}" for p in self.sqlite_problems]
        out += [f"{label}: missing {m}" for m in self.missing]
        out += [f"  {image}: {'; '.join(problems)}" for image, problems in self.damaged_images().items()]
        names = {"images": ("image", "images"), "structures": ("structure row", "structure rows"),
                 "global_vectors": ("global vector", "global vectors"), "arrays": ("array", "arrays")}
        checked = ", ".join(f"{n} {names.get(table, (table, table))[n != 1]}" for table, n in self.counts.items())
        if self.clean:
            out.append(f"{label}: no damage found ({checked} checked; SQLite's integrity check: ok)")
            return out
        images = {d.image for d in self.damage if d.table == "images"}
        derived = len([d for d in self.damage if d.table != "images"])
        found = [f"{len(images)} image{'s' if len(images) != 1 else ''} damaged"] if images else []
        found += [f"{derived} damaged row{'s' if derived != 1 else ''} of structure, global vectors or "
                  "arrays"] if derived else []
        found += [f"{len(self.missing)} missing table{'s' if len(self.missing) != 1 else ''} or column"
                  f"{'s' if len(self.missing) != 1 else ''}"] if self.missing else []
        found += ["SQLite finds the file damaged"] if self.sqlite_problems else []
        repair = ("re-run 'visloc ingest' of the drives named to repair them" if not self.sqlite_problems
                  else "ingest its drives into a new store")
        out.append(f"{label}: {', '.join(found)} ({checked} checked); {repair}")
        return out


def check_store(path: str | Path, progress: Callable[[int, int], None] | None = None) -> CheckReport:
    """Check the store at ``path`` without changing it."""
    with Workspace.inspect(path) as store:
        problems = tuple(sqlite_problems(store))
        missing = tuple(missing_schema(store))
        damage = tuple(scan(store, progress=progress))
        return CheckReport(Path(path), problems, missing, damage, row_counts(store))


def check_sharded(folder: str | Path, progress: Callable[[int, int], None] | None = None) -> tuple[list[str], bool]:
    """Check a sharded store without changing it: every tile's file against the manifest's checksum, then
    each tile as a store. (lines to print, whether it is whole)."""
    from visloc.db.shards import Manifest
    from visloc.store.sharded import check_tiles

    lines = check_tiles(folder)
    with Manifest(folder, read_only=True) as manifest:
        tiles = manifest.tiles()
    bad = {line.split(": tile ", 1)[0] for line in lines}
    if progress:
        progress(0, len(tiles))
    for n, tile in enumerate(tiles, 1):
        path = Path(folder) / tile.file
        if str(path) not in bad:
            report = check_store(path)
            if not report.clean:
                lines += report.lines()
        if progress:
            progress(n, len(tiles))
    clean = not lines
    lines.append(f"{folder}: {len(tiles)} tiles checked; " + ("no damage found" if clean else
                 "damage found: 'visloc ingest' of its drives into the store writes the damaged tiles again"))
    return lines, clean
