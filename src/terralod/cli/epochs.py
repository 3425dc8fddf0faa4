"""``terralod epochs STORE [--delete DATE]``: the epochs of a store, or remove one."""

from __future__ import annotations

import json

import click

from terralod.cli._console import console


def epoch_table(rows: list[dict]) -> None:
    from rich.table import Table

    t = Table()
    for col in (
        "epoch",
        "state",
        "kind",
        "from",
        "tiles rebuilt",
        "tiles shared",
        "samples changed",
        "source",
    ):
        t.add_column(col, justify="left" if col in ("epoch", "state", "kind", "from", "source") else "right")
    for r in rows:
        i = r["info"]
        t.add_row(
            r["name"], r["state"], str(i.get("kind", "")), str(i.get("base", "") or ""),
            str(i.get("tiles_rebuilt", "all" if i.get("kind") == "build" else "")),
            str(i.get("tiles_shared", "")), f"{i['changed_samples']:,}" if "changed_samples" in i else "",
            str(i.get("source", ""))[-50:],
        )  # fmt: skip
    console.print(t)


@click.command()
@click.argument("store")
@click.option(
    "--delete", "delete", default=None, metavar="DATE", help="Remove this epoch (and what only it uses)."
)
@click.option("--json", "as_json", is_flag=True, help="Print machine-readable JSON.")
def epochs(store: str, delete: str | None, as_json: bool) -> None:
    """List the epochs of STORE (oldest first; the last is the default), or --delete one."""
    from terralod.store import TileStore, open_store

    if delete is not None:
        with open_store(store) as s:  # refused on a read-only connection: a bad name writes nothing
            s.check_delete(delete)
        with TileStore.open(store, writable=True) as s:
            s.delete_epoch(delete)
            s.vacuum()
        console.print(f"{store}: epoch {delete} deleted")
    with open_store(store) as s:
        rows = s.epoch_rows()
    if as_json:
        click.echo(
            json.dumps([{"name": r["name"], "state": r["state"], **r["info"]} for r in rows], indent=2)
        )
        return
    if not rows:
        console.print(f"{store}: no epochs (built without --epoch; `terralod update` adds the first)")
        return
    epoch_table(rows)
