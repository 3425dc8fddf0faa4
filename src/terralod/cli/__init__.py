"""The ``terralod`` command line, one command per module (rasterio's habit).

User mistakes (missing file, wrong format, no valid samples, unwritable output, corrupt store) print one
line ``terralod: <file>: <problem>`` and exit with code 2; ``-v`` adds diagnostics and the traceback.
Shared by the commands, by concern: :mod:`~terralod.cli._options` (options and their parsing),
:mod:`~terralod.cli._console` (what is printed, progress), :mod:`~terralod.cli._errors` (failures as one line,
exit 2), :mod:`~terralod.cli._inputs` (opening an input as a terrain); a new command
is a module here with one click command, added to :data:`COMMANDS`.
"""

from __future__ import annotations

import importlib
import logging
import sys

import click

from terralod.cli._errors import VERBOSE, quiet_libraries, run_main

#: (module, command name) of every command, in ``--help`` order.
COMMANDS = [
    ("info", "info"),
    ("build", "build"),
    ("amplify", "amplify"),
    ("render", "render"),
    ("flythrough", "flythrough"),
    ("view", "view"),
    ("demo", "demo"),
    ("warmup", "warmup"),
    ("export", "export"),
    ("serve", "serve"),
    ("update", "update"),
    ("epochs", "epochs"),
    ("edit", "edit"),
    ("change", "change"),
    ("check", "check"),
]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", is_flag=True, help="Show diagnostics and tracebacks.")
@click.version_option(package_name="terralod")
def cli(verbose: bool) -> None:
    """terralod: terrain level of detail with measured geometric error."""
    VERBOSE["on"] = verbose
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(name)s: %(message)s")
    quiet_libraries(verbose)
    ctx = click.get_current_context()
    if ctx.invoked_subcommand not in (None, "info", "warmup", "epochs") and not ctx.resilient_parsing:
        from terralod.warmup import COLD_COMPILE_S, kernels_cold

        if kernels_cold():  # say why the first run waits (scripts/install.sh compiles them ahead)
            click.echo(f"terralod: compiling kernels once, about {COLD_COMPILE_S} s (`terralod warmup` does it "
                       "ahead)", err=True)  # fmt: skip


#: The example line that ends each command's ``--help`` (a command may carry its own ``epilog`` instead).
EXAMPLES = {
    "info": "terralod info dem.tif",
    "build": "terralod build dem.tif -o dem.terra",
    "amplify": "terralod amplify dem.tif -o fine.tif --factor 4",
    "render": "terralod render dem.terra -o frame.png",
    "flythrough": "terralod flythrough dem.terra -o fly.mp4",
    "view": "terralod view dem.terra",
    "demo": "terralod demo",
    "warmup": "terralod warmup",
    "export": "terralod export dem.terra --format 3dtiles -o tiles/",
    "serve": "terralod serve dem.terra --port 8000",
    "update": "terralod update dem.terra dem-2024.tif --epoch 2024-06-01",
    "epochs": "terralod epochs dem.terra",
    "edit": "terralod edit dem.terra --polygon pit.geojson --depth-m 12 --epoch pit",
    "change": "terralod change before.tif after.tif -o change/",
    "check": "terralod check dem.terra",
}

for _module, _name in COMMANDS:
    _cmd = getattr(importlib.import_module(f"terralod.cli.{_module}"), _name)
    if not _cmd.epilog and _name in EXAMPLES:
        _cmd.epilog = f"Example: {EXAMPLES[_name]}"
    cli.add_command(_cmd)


def main(argv: list[str] | None = None) -> None:
    """Entry point: run the CLI, turning terralod errors into one line and exit code 2."""
    run_main(cli, sys.argv[1:] if argv is None else argv)


__all__ = ["COMMANDS", "EXAMPLES", "cli", "main"]
