"""Shared helpers of the benchmark scripts: real terrains from ../shared/data, result writing."""

from __future__ import annotations

import json
import platform
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "benchmarks" / "results"


def fractal_terrain(
    rows: int, cols: int, seed: int, relief_m: float = 500.0, beta: float = 2.2
) -> np.ndarray:
    """A spectral-synthesis fBm terrain (power ~ f^-beta), float32 metres; deterministic per seed."""
    rng = np.random.default_rng(seed)
    n = max(rows, cols)
    fy = np.fft.fftfreq(n)[:, None]
    fx = np.fft.rfftfreq(n)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f ** (-beta / 2.0)
    amp[0, 0] = 0.0
    spec = amp * (rng.normal(size=amp.shape) + 1j * rng.normal(size=amp.shape))
    z = np.fft.irfft2(spec, s=(n, n))[:rows, :cols]
    z = (z - z.min()) / max(np.ptp(z), 1e-12) * relief_m
    return z.astype(np.float32)


def puget_sound_1k():
    """Puget Sound 1025² at 160 m (elevation = value * 0.1), or None when ../shared/data is absent."""
    from PIL import Image

    from terralod import Heightfield

    p = SHARED / "dem" / "puget_sound_1k_u16.png"
    if not p.exists():
        return None
    z = np.asarray(Image.open(p)).astype(np.float32) * 0.1
    return Heightfield.from_array(z, 160.0, source=str(p))


def mirror_tile(z: np.ndarray, reps: int) -> np.ndarray:
    """Reflect ``z`` reps x reps times sharing edge rows: (n-1)*reps+1 samples a side, C0-continuous."""
    rows = [z if i % 2 == 0 else z[::-1] for i in range(reps)]
    col = np.concatenate([rows[0]] + [r[1:] for r in rows[1:]], axis=0)
    cols = [col if i % 2 == 0 else col[:, ::-1] for i in range(reps)]
    return np.ascontiguousarray(np.concatenate([cols[0]] + [c[:, 1:] for c in cols[1:]], axis=1))


def puget_sound_4k():
    """4097² mirror-tiled from the real Puget Sound 1k (4 x 4 reflections), 160 m; None when absent."""
    from terralod import Heightfield

    hf = puget_sound_1k()
    if hf is None:
        return None
    z = mirror_tile(hf.elevation_m, 4)
    return Heightfield.from_array(z, 160.0, source="puget_sound_1k mirror-tiled 4x4 (4097²)")


def write_results(name: str, payload: dict[str, Any], table_md: str) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    payload = {
        "machine": {"python": sys.version.split()[0], "platform": platform.platform(), "cpus": _cpus()},
        **payload,
    }
    (RESULTS / f"{name}.json").write_text(json.dumps(payload, indent=2, default=float))
    (RESULTS / f"{name}.md").write_text(table_md)
    print(table_md)


def _cpus() -> int:
    import os

    return os.cpu_count() or 1


def md_table(headers: list[str], rows: list[list[Any]]) -> str:
    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:,.3f}" if abs(v) < 1000 else f"{v:,.0f}"
        if isinstance(v, int):
            return f"{v:,}"
        return str(v)

    out = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    out += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(out) + "\n"


def tree_peak_rss(proc: Any, *, max_rss_b: float = float("inf"), timeout_s: float = float("inf"),
                  interval_s: float = 0.05, timeline: list | None = None,
                  timeline_s: float = 5.0) -> tuple[int, str | None]:  # fmt: skip
    """Peak RSS (bytes) summed over ``proc`` (a subprocess.Popen) and its children, sampled every
    ``interval_s`` until it exits; it is killed past ``max_rss_b`` bytes or ``timeout_s`` seconds (the
    machine is shared). Returns (peak, None) or (peak, "rss" | "timeout") when it was killed. With
    ``timeline`` (a list), appends (seconds, peak MiB of the last ``timeline_s`` seconds) to it: where in a
    run its memory rose."""
    import time

    import psutil

    root, peak, t0 = psutil.Process(proc.pid), 0, time.perf_counter()
    window, t_window = 0, t0
    while proc.poll() is None:
        try:
            rss = root.memory_info().rss + sum(c.memory_info().rss for c in root.children(recursive=True))
            peak = max(peak, rss)
            window = max(window, rss)
        except psutil.Error:  # a child that ended between the listing and the read: the next sample has it
            pass
        if timeline is not None and time.perf_counter() - t_window >= timeline_s:
            t_window = time.perf_counter()
            timeline.append((round(t_window - t0, 1), round(window / 2**20, 1)))
            window = 0
        why = "rss" if peak > max_rss_b else "timeout" if time.perf_counter() - t0 > timeout_s else None
        if why is not None:
            proc.kill()
            return peak, why
        time.sleep(interval_s)
    return peak, None
