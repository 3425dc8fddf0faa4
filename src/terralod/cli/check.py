"""``terralod check STORE``: verify everything that decodes a store's tiles (:mod:`terralod.integrity`);
a verdict on one screen, one line per problem, exit 0 when sound and 2 otherwise. ``--repair`` drops the
broken tiles and says what ``build --resume`` rebuilds; ``--upgrade`` brings an older store format to the
current one."""

from __future__ import annotations

import json
import sys

import click

from terralod.cli._console import console, one_line

#: Problems printed before "... and N more" (the verdict stays on one screen).
MAX_LINES = 20


@click.command()
@click.argument("path")
@click.option("--repair", is_flag=True, help="Drop broken tiles; build --resume then rebuilds them.")
@click.option("--upgrade", is_flag=True, help="Upgrade a store of an older format version in place.")
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
def check(path: str, repair: bool, upgrade: bool, as_json: bool) -> None:
    """Verify a .terra store: checksums, decoding, monotone errors, shared borders, bounds, epochs."""
    from terralod.integrity import check_store, repair_store
    from terralod.store import upgrade_store

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
