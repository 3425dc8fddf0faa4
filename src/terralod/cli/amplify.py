"""``terralod amplify DEM -o FINE.tif``: fractal (fBm) detail below the DEM's resolution (Hu & Wang)."""

from __future__ import annotations

from typing import Any

import click

from terralod.cli._console import console
from terralod.cli._options import check_output, load, read_options


@click.command()
@click.argument("input_path", metavar="INPUT")
@click.option("-o", "--output", required=True, help="Output GeoTIFF with the finer spacing.")
@click.option("--factor", default=4, show_default=True, help="Refinement factor (power of 2).")
@click.option("--seed", default=0, show_default=True, help="Seed of the world-position hash.")
@click.option("--hurst", type=float, default=None, help="Hurst exponent H (default: estimated per region).")
@click.option("--sigma", type=float, default=None, help="fBm sigma, metres (default: estimated per region).")
@click.option("--overwrite", is_flag=True, help="Replace an existing output file.")
@read_options
def amplify(
    input_path: str, output: str, factor: int, seed: int, hurst, sigma, overwrite: bool, **read: Any
) -> None:
    """Add fractal (fBm) detail below the DEM's resolution (Hu & Wang); every DEM sample is kept exactly."""
    from terralod.fractal import amplify_command

    check_output(output, [input_path], overwrite=overwrite, suffixes=(".tif", ".tiff"), what="output GeoTIFF")

    hf = load(input_path, **read)
    summary = amplify_command(hf, output, factor=factor, seed=seed, hurst=hurst, sigma=sigma)
    console.print(
        f"wrote {output}: {summary['shape_out'][1]}x{summary['shape_out'][0]} samples "
        f"at {summary['spacing_out_m'][0]:.3f} m (x{factor}), mean H {summary['hurst']['mean']:.2f}, "
        f"{summary['seconds']:.2f} s"
    )
