"""``terralod check STORE|DEM...``: verify everything that decodes a store's tiles (:mod:`terralod.integrity`),
or a region of DEM files as an export reads it (:func:`terralod.io.region.check_region`: one grid, every block
of every file decoded, every file with valid samples); a verdict on one screen, one line per problem, exit 0
when sound and 2 otherwise. ``--repair`` drops a store's broken tiles and says what ``build --resume``
rebuilds; ``--upgrade`` brings an older store format to the current one."""

from __future__ import annotations

import json
import sys

import click

from terralod.cli._console import console, one_line

#: Problems printed before "... and N more" (the verdict stays on one screen).
MAX_LINES = 20


@click.command()
@click.argument("paths", nargs=-1, required=True, metavar="STORE|DEM...")
@click.option("--repair", is_flag=True, help="Drop broken tiles; build --resume then rebuilds them.")
@click.option("--upgrade", is_flag=True, help="Upgrade a store of an older format version in place.")
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
def check(paths: tuple[str, ...], repair: bool, upgrade: bool, as_json: bool) -> None:
    """Verify a .terra store (checksums, decoding, monotone errors, shared borders, bounds, epochs) or a region
    of DEM files (several files, a folder, a quoted glob, a VRT: one grid, every block decoded)."""
    from terralod.integrity import check_store, repair_store
    from terralod.store import upgrade_store
    from terralod.terrain import _is_sqlite

    path = paths[0]
    if len(paths) > 1 or not _is_sqlite_file(path, _is_sqlite):
        if repair or upgrade:
            raise click.BadParameter("--repair and --upgrade are for a store", param_hint="STORE")
        _check_region(paths, as_json)
        return

    if upgrade:
        console.print(upgrade_store(path), highlight=False)
    rep = check_store(path)
    if as_json:
        click.echo(json.dumps(rep.as_dict(), indent=2))
    else:
        console.print(f"{path}: {rep.kind}", highlight=False)
        if rep.checked:
            console.print(f"  checked: {'; '.join(rep.checked)}", highlight=False)
        for line in rep.problems[:MAX_LINES]:
            # never wrapped nor cut: a line may end in the command that finishes an interrupted epoch
            console.print(f"  problem: {one_line(line, 2000)}", highlight=False, markup=False, soft_wrap=True)
        if len(rep.problems) > MAX_LINES:
            console.print(f"  ... and {len(rep.problems) - MAX_LINES} more problems", highlight=False)
        n = len(rep.problems)
        verdict = "sound" if rep.sound else f"{n} problem{'s' if n != 1 else ''}"
        console.print(f"verdict: {verdict}", highlight=False)
    if repair and not rep.sound:
        for line in repair_store(path, rep):
            console.print(f"repair: {line}", highlight=False, markup=False)
    if not rep.sound:
        sys.exit(2)


def _is_sqlite_file(path: str, is_sqlite) -> bool:  # noqa: ANN001
    """A store: a SQLite or .terra file, or a missing path that is no glob (left to the store check's
    own message); a folder, a glob or a raster is a region."""
    from pathlib import Path

    from terralod.io.region import _is_glob

    p = Path(path)
    if p.is_dir():
        return False
    if p.is_file():
        return bool(is_sqlite(p)) or p.suffix.lower() == ".terra"
    return not _is_glob(path)


def _check_region(paths: tuple[str, ...], as_json: bool) -> None:
    from terralod.io.region import check_region

    rep = check_region(list(paths))
    if as_json:
        click.echo(json.dumps(rep.as_dict(), indent=2))
    else:
        console.print(f"{rep.name}: region of {rep.files} DEM file(s)", highlight=False, markup=False)
        for line in rep.checked:
            console.print(f"  checked: {line}", highlight=False, markup=False)
        for line in rep.problems[:MAX_LINES]:
            console.print(f"  problem: {one_line(line, 2000)}", highlight=False, markup=False, soft_wrap=True)
        if len(rep.problems) > MAX_LINES:
            console.print(f"  ... and {len(rep.problems) - MAX_LINES} more problems", highlight=False)
        n = len(rep.problems)
        console.print(f"verdict: {'sound' if rep.sound else f'{n} problem' + ('s' if n != 1 else '')}",
                      highlight=False)  # fmt: skip
    if not rep.sound:
        sys.exit(2)
