"""Integrity campaign: inputs fuzzed, kills survived, corruptions detected (``terralod check``).

``python benchmarks/integrity.py [--fuzz-minutes M] [--kills K] [--corruptions C]``

- **Fuzzed inputs**: the hypothesis (+ atheris when installed) campaign of ``benchmarks/fuzz.py`` over every
  reader; a failure is any outcome but a result or a one-line ``TerralodError`` naming the file.
- **Kills**: builds, resumes and ``--overwrite`` replacements killed by SIGKILL at seeded random tile counts
  and at every creation hook (before/after the temporary is linked into place, before the complete flag,
  before the replacement is installed), each in a forked child (the real builder, no mock). Survived: the
  store at the name is either the old state (whole) or opens, passes ``check`` but for "incomplete", and
  ``--resume`` (or a rerun) gives tile rows identical to an uninterrupted build.
- **Corruptions**: a complete store (and a TIN store) altered one way at a time — one changed character
  in each metadata value, a flipped byte in a tile's geometry, a changed tile error, a deleted tile row,
  the tiles table dropped, random bytes of the file flipped, the file truncated, the TIN payload flipped.
  Detected: ``check_store`` reports a problem. Harmless: the store's tile rows and metadata are unchanged
  (e.g. a flip in free space) and ``check`` says sound. Silent: ``check`` says sound but what it serves
  changed — the case this campaign exists to keep at zero.

Writes ``benchmarks/results/integrity.json`` and ``integrity.md``.
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import sqlite3
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import fuzz  # noqa: E402
import fuzzing  # noqa: E402

from _common import write_results  # noqa: E402

TILE = 9
METHOD = "chunked"


# -- helpers -------------------------------------------------------------------------------------------
def _rows(p: Path) -> list[tuple]:
    con = sqlite3.connect(f"file:{p}?mode=ro", uri=True)
    try:
        return con.execute("SELECT * FROM tiles ORDER BY level, x, y").fetchall()
    finally:
        con.close()


def _state(p: Path) -> Any:
    """(meta rows, tile rows) of a store, or None when unreadable."""
    try:
        con = sqlite3.connect(f"file:{p}?mode=ro", uri=True)
        try:
            meta = con.execute("SELECT key, value FROM meta ORDER BY key").fetchall()
            tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
            tiles = (
                con.execute("SELECT * FROM tiles ORDER BY level, x, y").fetchall()
                if "tiles" in tables
                else None
            )
            tin = con.execute("SELECT * FROM tin_model").fetchall() if "tin_model" in tables else None
            return meta, tiles, tin
        finally:
            con.close()
    except sqlite3.Error:
        return None


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def _killed(fn) -> bool:
    pid = os.fork()
    if pid == 0:
        try:
            fn()
        finally:
            os._exit(0)
    _, status = os.waitpid(pid, 0)
    return os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL


def _dem(seed: int, h: int = 240, w: int = 232):
    from terralod import Heightfield

    from _common import fractal_terrain

    return Heightfield.from_array(fractal_terrain(h, w, seed, relief_m=400.0).astype(np.float64), 20.0)


# -- kills ---------------------------------------------------------------------------------------------
def kill_campaign(folder: Path, n_random: int, seed: int) -> dict[str, Any]:
    import terralod.pyramid.builder as builder
    import terralod.store as store
    from terralod import build_store, open_store
    from terralod.integrity import check_store
    from terralod.store import TileStore

    hf, hf_old = _dem(7), _dem(8)
    ref, old = folder / "ref.terra", folder / "old.terra"
    build_store(hf, ref, tile_size=TILE, method=METHOD, workers=1)
    build_store(hf_old, old, tile_size=TILE, method=METHOD, workers=1)
    ref_rows, old_rows = _rows(ref), _rows(old)
    total = len(ref_rows)
    rng = random.Random(seed)
    cases: list[dict[str, Any]] = []

    def build(out: Path, **kw: Any) -> None:
        build_store(hf, out, tile_size=TILE, method=METHOD, workers=1, **kw)

    def at_tiles(n: int):
        def cb(done: int, total_: int) -> None:
            if done >= n and done > 0:
                _die()

        return cb

    def hooked(hook: str, out: Path, **kw: Any):
        def run() -> None:
            if hook == "before_link":
                store._link_into_place = lambda tmp, p: _die()
            elif hook == "after_link":
                orig = store._link_into_place
                store._link_into_place = lambda tmp, p: (orig(tmp, p), _die())
            elif hook == "before_complete":
                orig_set = TileStore.set_meta
                TileStore.set_meta = lambda self, k, v: _die() if k == "complete" else orig_set(self, k, v)
            elif hook == "before_install":
                builder.install_store = lambda new, p: _die()
            build(out, **kw)

        return run

    def verdict(kind: str, out: Path, replaced: bool) -> None:
        c: dict[str, Any] = {"kind": kind}
        try:
            if replaced:
                c["old_state_whole"] = out.exists() and _rows(out) == old_rows and check_store(out).sound
                build(out, overwrite=True)
            elif not out.exists():
                c["absent"] = True
                build(out)
            else:
                with open_store(out) as s:
                    c["opens"] = s.verify() == []
                probs = check_store(out).problems
                c["check_only_incomplete"] = all("incomplete" in p or "complete" in p for p in probs)
                build(out, resume=True)
            c["identical"] = _rows(out) == ref_rows
            c["no_litter"] = not [f for f in out.parent.iterdir() if f.name.endswith(".tmp")]
        except Exception as exc:  # noqa: BLE001 - a failed survival is a result
            c["error"] = f"{type(exc).__name__}: {exc}"
        c["survived"] = "error" not in c and all(v for k, v in c.items() if k not in ("kind", "survived"))
        cases.append(c)

    for i, n in enumerate(sorted(rng.sample(range(1, total), n_random))):
        out = folder / f"t{i}.terra"
        ok = _killed(lambda out=out, n=n: build(out, progress=at_tiles(n)))
        if ok and i % 2 == 0:  # every other one: kill its resume as well, at a later tile count
            with open_store(out) as s:
                done = len(s.tile_codes())
            _killed(
                lambda out=out, done=done: build(
                    out, resume=True, progress=at_tiles(done + rng.randint(1, 64))
                )
            )
        verdict(f"build at tile {n}" + (" + resume killed" if i % 2 == 0 else ""), out, False)
    for hook in ("before_link", "after_link", "before_complete"):
        out = folder / f"{hook}.terra"
        _killed(hooked(hook, out))
        verdict(f"hook {hook}", out, False)
    for j, point in enumerate(["tiles", "before_install"] + ["tiles"] * 2):
        out = folder / f"ow{j}.terra"
        out.write_bytes(old.read_bytes())
        if point == "tiles":
            n = rng.randrange(1, total)
            _killed(lambda out=out, n=n: build(out, overwrite=True, progress=at_tiles(n)))
            verdict(f"--overwrite at tile {n}", out, True)
        else:
            _killed(hooked("before_install", out, overwrite=True))
            verdict("--overwrite hook before_install", out, True)
    return {"tiles_per_build": total, "cases": cases}


# -- corruptions ---------------------------------------------------------------------------------------
def _change_char(text: str, rng: random.Random) -> str:
    digits = [i for i, ch in enumerate(text) if ch.isdigit()]
    letters = [i for i, ch in enumerate(text) if ch.isalpha()]
    pool = digits or letters or list(range(len(text)))
    i = rng.choice(pool)
    ch = text[i]
    new = str((int(ch) + rng.randint(1, 9)) % 10) if ch.isdigit() else ("x" if ch != "x" else "y")
    return text[:i] + new + text[i + 1 :]


def corruption_campaign(folder: Path, n_each: int, seed: int) -> dict[str, Any]:
    from terralod import build_store
    from terralod.integrity import check_store
    from terralod.tin import DetailIncrementModel
    from terralod.tin.terra import save_model_to_store

    rng = random.Random(seed)
    hf = _dem(9, 120, 104)
    base = folder / "base.terra"
    build_store(hf, base, tile_size=TILE, method="cohesion", workers=1)
    tin = folder / "tin.terra"
    save_model_to_store(DetailIncrementModel.from_heightfield(_dem(10, 40, 36), sub_blocks=1), tin)
    outcomes: list[dict[str, str]] = []

    def trial(kind: str, src: Path, alter) -> None:
        p = folder / "c.terra"
        for side in ("", "-wal", "-shm", "-journal"):
            Path(f"{p}{side}").unlink(missing_ok=True)
        p.write_bytes(src.read_bytes())
        before = _state(p)
        try:
            alter(p)
        except sqlite3.Error:
            pass
        rep = check_store(p)
        after = _state(p)
        if not rep.sound:
            out = "detected"
        elif after == before:
            out = "harmless"
        else:
            out = "SILENT"
        outcomes.append({"kind": kind, "outcome": out, "problem": (rep.problems or [""])[0][:160]})

    def sql(p: Path, *stmts: tuple) -> None:
        con = sqlite3.connect(p)
        for s in stmts:
            con.execute(*s)
        con.commit()
        con.close()

    con = sqlite3.connect(base)
    meta = dict(con.execute("SELECT key, value FROM meta"))
    codes = con.execute("SELECT level, x, y FROM tiles").fetchall()
    con.close()
    for key, value in meta.items():
        changed = _change_char(value, rng)
        trial(
            f"meta '{key}' changed",
            base,
            lambda p, k=key, v=changed: sql(p, ("UPDATE meta SET value=? WHERE key=?", (v, k))),
        )
    for _ in range(n_each):
        code = rng.choice(codes)

        blob_col, r = rng.choice(["vertices", "triangles"]), rng.random()

        def flip_blob(p: Path, code=code, col=blob_col, r=r) -> None:
            con = sqlite3.connect(p)
            b = bytearray(
                con.execute(f"SELECT {col} FROM tiles WHERE level=? AND x=? AND y=?", code).fetchone()[0]
            )
            b[int(r * len(b))] ^= 1 << int(r * 97) % 8
            con.execute(f"UPDATE tiles SET {col}=? WHERE level=? AND x=? AND y=?", (bytes(b), *code))
            con.commit()
            con.close()

        trial("tile geometry byte flipped", base, flip_blob)
        col = rng.choice(["error_m", "vertical_error_m", "z_min_m", "n_vertices", "z0_index"])
        trial(f"tile {col} changed", base, lambda p, code=code, col=col: sql(
            p, (f"UPDATE tiles SET {col} = {col} + 1 WHERE level=? AND x=? AND y=?", code)))  # fmt: skip
        trial("tile row deleted", base, lambda p, code=code: sql(
            p, ("DELETE FROM tiles WHERE level=? AND x=? AND y=?", code)))  # fmt: skip
        size = base.stat().st_size

        offsets = tuple(rng.randrange(size) for _ in range(rng.randint(1, 8)))

        def flip_file(p: Path, offs=offsets) -> None:
            b = bytearray(p.read_bytes())
            for o in offs:
                b[o] ^= 0xFF
            p.write_bytes(bytes(b))

        trial("file bytes flipped", base, flip_file)
        cut = rng.randrange(0, size)
        trial("file truncated", base, lambda p, cut=cut: p.write_bytes(p.read_bytes()[:cut]))
        tsize = tin.stat().st_size
        tin_offs = (rng.randrange(tsize),)
        trial("TIN file bytes flipped", tin, lambda p, offs=tin_offs: flip_file(p, offs))
    trial("tiles table dropped", base, lambda p: sql(p, ("DROP TABLE tiles",)))
    con = sqlite3.connect(tin)
    tmeta = dict(con.execute("SELECT key, value FROM meta"))
    con.close()
    for key, value in tmeta.items():
        changed = _change_char(value, rng)
        trial(
            f"TIN meta '{key}' changed",
            tin,
            lambda p, k=key, v=changed: sql(p, ("UPDATE meta SET value=? WHERE key=?", (v, k))),
        )

    def flip_model(p: Path, r: float) -> None:
        con = sqlite3.connect(p)
        b = bytearray(con.execute("SELECT model FROM tin_model").fetchone()[0])
        b[int(r * len(b))] ^= 0x10
        con.execute("UPDATE tin_model SET model=?", (bytes(b),))
        con.commit()
        con.close()

    for _ in range(n_each):
        r = rng.random()
        trial("TIN payload byte flipped", tin, lambda p, r=r: flip_model(p, r))
    return {"outcomes": outcomes}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fuzz-minutes", type=float, default=2.0)
    ap.add_argument("--kills", type=int, default=12, help="Kills at random tile counts (plus 7 at hooks).")
    ap.add_argument("--corruptions", type=int, default=20, help="Trials of each random corruption kind.")
    ap.add_argument("--seed", type=int, default=17)
    ap.add_argument("--no-atheris", action="store_true")
    args = ap.parse_args()
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="terralod-integrity-") as tmp:
        folder = Path(tmp)
        (folder / "kills").mkdir()
        kills = kill_campaign(folder / "kills", args.kills, args.seed)
        t_kill = time.monotonic() - t0
        (folder / "corrupt").mkdir()
        corr = corruption_campaign(folder / "corrupt", args.corruptions, args.seed)
        t_corr = time.monotonic() - t0 - t_kill
        seeds = fuzzing.make_seeds(folder / "seeds")
        has_atheris = not args.no_atheris and fuzz.atheris_runs({}, folder, 0) is not None
        secs = args.fuzz_minutes * 60.0
        hyp = fuzz.hypothesis_rounds(seeds, folder, secs / 2 if has_atheris else secs, 100)
        ath = fuzz.atheris_runs(seeds, folder, secs / 2) if has_atheris else None
    t_all = time.monotonic() - t0
    rows = []
    for t in seeds:
        h = hyp["targets"][t]
        a = (ath or {}).get(t, {"cases": 0, "failures": []})
        rows.append({"reader": t, "cases": h["cases"] + a["cases"], "hypothesis": h["cases"], "atheris": a["cases"],
                     "failures": len(h["failures"]) + len(a["failures"]), "examples": h["failures"][:2] + a["failures"][:2]})  # fmt: skip
    kc = kills["cases"]
    oc = Counter((o["kind"].split("'")[0].strip() if "meta" in o["kind"] else o["kind"], o["outcome"])
                 for o in corr["outcomes"])  # fmt: skip
    kinds = sorted({k for k, _ in oc})
    payload = {"seconds": {"kills": t_kill, "corruptions": t_corr, "total": t_all}, "fuzz": rows,
               "fuzz_crashes": hyp["crashes"], "atheris": ath is not None, "kills": kills, "corruptions": corr}  # fmt: skip
    n_in = sum(r["cases"] for r in rows)
    n_fail = sum(r["failures"] for r in rows)
    det = sum(1 for o in corr["outcomes"] if o["outcome"] == "detected")
    harmless = sum(1 for o in corr["outcomes"] if o["outcome"] == "harmless")
    silent = sum(1 for o in corr["outcomes"] if o["outcome"] == "SILENT")
    md = [
        "# Integrity: inputs fuzzed, kills survived, corruptions detected", "",
        f"`python benchmarks/integrity.py --fuzz-minutes {args.fuzz_minutes:g} --kills {args.kills} "
        f"--corruptions {args.corruptions} --seed {args.seed}` ({t_all / 60:.1f} min)", "",
        "| campaign | runs | held | failed |", "|---|---:|---:|---:|",
        f"| fuzzed inputs (hypothesis{' + atheris' if ath is not None else ''}, {len(rows)} readers) | {n_in:,} | "
        f"{n_in - n_fail:,} | {n_fail} |",
        f"| fuzz child processes crashed or hung | {len(hyp['crashes'])} | | {len(hyp['crashes'])} |",
        f"| kills (SIGKILL: builds, resumes, --overwrite, creation hooks) | {len(kc)} | "
        f"{sum(c['survived'] for c in kc)} | {sum(not c['survived'] for c in kc)} |",
        f"| corruptions (grid + TIN stores) | {len(corr['outcomes'])} | {det} detected + {harmless} harmless | "
        f"{silent} silent |",
        "", "| reader | cases (hypothesis + atheris) | failures |", "|---|---:|---:|",
    ]  # fmt: skip
    md += [
        f"| {r['reader']} | {r['cases']:,} ({r['hypothesis']:,} + {r['atheris']:,}) | {r['failures']} |"
        for r in rows
    ]
    md += ["", "| corruption | detected | harmless | silent |", "|---|---:|---:|---:|"]
    md += [f"| {k} | {oc[(k, 'detected')]} | {oc[(k, 'harmless')]} | {oc[(k, 'SILENT')]} |" for k in kinds]
    md += ["", "Harmless: the bytes changed were not read (free space of the file); the store serves what it served.",
           "Kills survived: the old store whole, or a store that opens with only committed, checksummed tiles and "
           "that `--resume` finishes into tile rows identical to an uninterrupted build; no temporary left."]  # fmt: skip
    for c in kc:
        if not c["survived"]:
            md.append(f"- kill not survived: {c}")
    for o in corr["outcomes"]:
        if o["outcome"] == "SILENT":
            md.append(f"- silent: {o['kind']}")
    for r in rows:
        for e in r["examples"]:
            md.append(f"- {r['reader']}: `{e[:300]}`")
    write_results("integrity", payload, "\n".join(md) + "\n")


if __name__ == "__main__":
    main()
