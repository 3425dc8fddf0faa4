"""A detail-increment TIN model (Ai et al., 2019) inside a ``.terra`` store, and its one-screen summary.

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` §2.2.2 ("the incremental information can be saved to
the external storage in the first run"). The store keeps the model's own checksummed file
(:meth:`terralod.tin.DetailIncrementModel.save`: base mesh, ΔT records, MMQE) as one blob beside the
metadata ``terralod info`` prints, written in one SQLite transaction (:func:`terralod.store.write_tin_store`).
The store never imports this module; this module imports the store.
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path
from typing import Any

from terralod.errors import CorruptStoreError
from terralod.store import read_tin_store, write_tin_store
from terralod.tin.increments import DetailIncrementModel

__all__ = ["load_model_from_store", "model_summary", "save_model_to_store"]


def model_summary(model: DetailIncrementModel) -> dict[str, Any]:
    """Sizes, scales and errors of a model (what ``terralod info`` shows; JSON-ready).

    ``svo_length_m`` gives sqrt(monotone MMQE) at the base (S_0) and at full resolution (S_n), the
    largest over the sub-blocks: the length in metres the SVO rule projects to the screen (§2.3.2);
    ``max_vertical_error_m`` the measured error (an upper bound over the input points) the default scale
    selection projects instead.
    """
    inc = model.increments
    v = model.vertices_m
    # Every slot outside the base is deleted by exactly one record (merged or not).
    base_triangles = int(model.n_slots - inc.del_slot.size)
    mm0 = [float(model.mmqe_m2(b)[0]) for b in range(model.n_blocks) if model.block_n_scales[b] > 0]
    mmn = [float(model.mmqe_m2(b)[-1]) for b in range(model.n_blocks) if model.block_n_scales[b] > 0]
    return {
        "source": model.source,
        "method": "tin",
        "vertices": int(v.shape[0]),
        "triangles": model.n_slots,
        "base_triangles": base_triangles,
        "sub_blocks": model.n_blocks,
        "scales": model.n_scales,
        "records": inc.n_records,
        "collapses_per_record": inc.step,
        "triangle_changes": int(inc.del_slot.size + inc.rep_slot.size),
        "bounds_m": [float(v[:, 0].min()), float(v[:, 1].min()), float(v[:, 0].max()), float(v[:, 1].max())],
        "elevation_range_m": [float(v[:, 2].min()), float(v[:, 2].max())],
        "svo_length_m": {
            "base": math.sqrt(max(mm0)) if mm0 else 0.0,
            "full": math.sqrt(max(mmn)) if mmn else 0.0,
        },
        "max_vertical_error_m": {
            "base": max((float(model.error_m(b)[0]) for b in range(model.n_blocks)), default=0.0),
            "full": 0.0,
        },
        "notes": list(model.notes),
    }


def save_model_to_store(
    model: DetailIncrementModel,
    path: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    workers: int | None = None,
) -> dict[str, Any]:
    """Write ``model`` to a ``.terra`` TIN store (compressed on ``workers`` threads, the same bytes for any
    number); returns its summary with ``size_bytes``."""
    summary = model_summary(model)
    with tempfile.TemporaryDirectory(prefix="terralod-tin-") as tmp:
        f = Path(tmp) / "model.tdim"
        model.save(f, workers=workers)
        blob = f.read_bytes()
    meta = {**summary, "crs": model.crs, "model_bytes": len(blob)}
    summary["size_bytes"] = write_tin_store(path, meta, blob, overwrite=overwrite)
    summary["path"] = str(path)
    return summary


def load_model_from_store(path: str | os.PathLike[str]) -> tuple[DetailIncrementModel, dict[str, Any]]:
    """(model at its base scale, stored metadata) of a TIN store; errors name the store."""
    meta, blob = read_tin_store(path)
    with tempfile.TemporaryDirectory(prefix="terralod-tin-") as tmp:
        f = Path(tmp) / "model.tdim"
        f.write_bytes(blob)
        try:
            model = DetailIncrementModel.load(f)
        except CorruptStoreError as exc:
            raise CorruptStoreError(f"TIN model: {exc.message}", str(path)) from exc
    return model, meta
