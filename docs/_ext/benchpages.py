"""Sphinx extension: one page per ``benchmarks/results/*.json``, generated when the build starts.

Each page gives the command that reproduces the result, the date and commit of the run (the JSON's own
``date`` / ``commit`` where it has them, else the last commit that changed the JSON file, from
``git log``), the machine the JSON records, and the tables of the markdown file the benchmark wrote beside
its JSON (``NAME.md``), converted to reStructuredText. Pages are written to ``docs/benchmarks/`` (ignored
by git) and listed by ``docs/benchmarks.rst`` through a glob toctree.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path
from typing import Any

DOCS = Path(__file__).resolve().parents[1]
ROOT = DOCS.parent
RESULTS = ROOT / "benchmarks" / "results"
OUT = DOCS / "benchmarks"

#: The command that wrote each results file, where it is not ``python benchmarks/NAME.py``.
COMMANDS = {
    "tin_export_1025": "python benchmarks/tin_export.py --side 1025 --repeat 1",
    "suite_cpu": "python benchmarks/suite_cpu.py --reference '66b69d2 (before round 4), 535 tests=1035.7' "
    "--reference '111de1e, 777 tests=1219.2'",
    "build_adaptive_dense": "python benchmarks/build.py --reps 1 --methods adaptive_dense,adaptive "
    "--name build_adaptive_dense",
    "build_ab": "python benchmarks/build_ab.py --baseline-src OLD/src",
    "build_speed": "python benchmarks/build.py   # an earlier run of build.py, kept for the record",
    "identity": "python benchmarks/identity.py --baseline OLD/src",
    "integrity": "python benchmarks/integrity.py --fuzz-minutes 4 --kills 12 --corruptions 20 --seed 17",
    "scale": "python benchmarks/scale.py --repeat 3",
    "scale_adaptive": "python benchmarks/scale.py --method adaptive --name scale_adaptive --repeat 3",
    "scale_adaptive_pinned": "python benchmarks/scale.py --pin --method adaptive --name scale_adaptive_pinned "
    "--repeat 3",
    "scale_cohesion": "python benchmarks/scale.py --method cohesion --name scale_cohesion --repeat 3",
    "scale_pinned": "python benchmarks/scale.py --pin --name scale_pinned --repeat 3",
    "scale_tin": "python benchmarks/scale.py --tin --repeat 3",
    "scale_tin_pinned": "python benchmarks/scale.py --tin --pin --name scale_tin_pinned --repeat 3",
    "change": "python benchmarks/change.py",
    "epochs": "python benchmarks/epochs.py",
    "series_region": "python benchmarks/series_region.py --counts 2 4",
    "region_build": "python benchmarks/region.py --stages build --tiles 16,64,256",
    "region_store_export": "python benchmarks/region.py --stages build --tiles 16,256 "
    "--store-exports quantized-mesh,3dtiles",
}

#: Results files name the methods by the project's paper numbers; the guide names them by their authors.
PAPERS = {
    "paper 000": "Sung, Lee & Shin 2021",
    "paper 001": "Hu & Wang",
    "paper 002": "Li, Liu & Liu",
    "paper 003": "Ai et al. 2019",
}


def command_for(name: str) -> str:
    if name in COMMANDS:
        return COMMANDS[name]
    script = ROOT / "benchmarks" / f"{name}.py"
    return (
        f"python benchmarks/{name}.py" if script.exists() else f"python benchmarks/...   # wrote {name}.json"
    )


def git_run(path: Path) -> tuple[str, str]:
    """(date, short commit) of the last commit that changed ``path``; ('not committed', '') when none."""
    try:
        out = subprocess.run(
            ["git", "log", "-1", "--format=%cs %h", "--", str(path.relative_to(ROOT))],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        out = ""
    if not out:
        return "not committed yet", ""
    date, commit = out.split(" ", 1)
    return date, commit


def _papers(text: str) -> str:
    for old, new in PAPERS.items():
        text = re.sub(re.escape(old), new, text, flags=re.IGNORECASE)
    return text


_CODE = re.compile(r"`([^`]+)`")
_BOLD = re.compile(r"\*\*(.+?)\*\*")


def inline(text: str) -> str:
    """Markdown inline text to reStructuredText: code spans, bold, everything else escaped."""
    text = _papers(text)
    spans: list[tuple[bool, str]] = []  # (is markup, text)
    for i, part in enumerate(_CODE.split(text)):
        if i % 2:  # a code span
            if part.strip():
                spans.append((True, f"``{part.strip()}``"))
            continue
        for j, piece in enumerate(_BOLD.split(part)):
            esc = re.sub(r"([\\*_|`<>\[\]])", r"\\\1", piece)
            spans.append(
                (bool(j % 2 and esc.strip()), f"**{esc.strip()}**" if j % 2 and esc.strip() else esc)
            )
    out = ""
    for k, (markup, piece) in enumerate(spans):
        if markup:
            # rst wants whitespace (or some punctuation) around inline markup: an escaped space always works
            if out and not out[-1].isspace():
                out += "\\ "
            out += piece
            nxt = spans[k + 1][1] if k + 1 < len(spans) else ""
            if nxt and not nxt[0].isspace():
                out += "\\ "
        else:
            out += piece
    return out


EMPTY = "\\ "  # an empty cell: rst's escaped space


def _table(rows: list[str]) -> list[str]:
    cells = [[c.strip() for c in r.strip().strip("|").split("|")] for r in rows]
    cells = [r for r in cells if not all(re.fullmatch(r":?-+:?", c or "-") for c in r)]
    if not cells:
        return []
    width = max(len(r) for r in cells)
    lines = [".. list-table::", "   :header-rows: 1", ""]
    for r in cells:
        r = r + [""] * (width - len(r))
        for k, c in enumerate(r):
            cell = inline(c) if c else EMPTY
            lines.append(f"   {'*' if k == 0 else ' '} - {cell}")
    return lines + [""]


def markdown_to_rst(md: str) -> list[str]:
    """The small markdown the benchmarks write (headings, paragraphs, lists, tables, fences) as rst."""
    lines = md.splitlines()
    out: list[str] = []
    i = 0
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        if line.startswith("```"):
            j = i + 1
            block = []
            while j < len(lines) and not lines[j].startswith("```"):
                block.append(lines[j])
                j += 1
            out += [".. code-block:: text", ""] + [f"   {b}" for b in block] + [""]
            i = j + 1
            continue
        if line.startswith("#"):
            out += [f".. rubric:: {inline(line.lstrip('#').strip())}", ""]
            i += 1
            continue
        if line.lstrip().startswith("|"):
            j = i
            while j < len(lines) and lines[j].lstrip().startswith("|"):
                j += 1
            out += _table(lines[i:j])
            i = j
            continue
        if re.match(r"\s*[-*] ", line):
            j = i
            items: list[str] = []
            while j < len(lines) and lines[j].strip() and not lines[j].lstrip().startswith(("|", "#", "```")):
                if re.match(r"\s*[-*] ", lines[j]):
                    items.append(re.sub(r"^\s*[-*] ", "", lines[j]))
                elif items:
                    items[-1] += " " + lines[j].strip()
                j += 1
            out += [f"- {inline(it)}" for it in items] + [""]
            i = j
            continue
        j = i
        para = []
        while j < len(lines) and lines[j].strip() and not lines[j].lstrip().startswith(("|", "#", "```")):
            para.append(lines[j].strip())
            j += 1
        out += [inline(" ".join(para)), ""]
        i = j
    return out


def _machine(data: Any) -> str:
    m = data.get("machine") if isinstance(data, dict) else None
    if not isinstance(m, dict):
        return "not recorded"
    return ", ".join(f"{k} {v}" for k, v in m.items())


def page(json_path: Path) -> str:
    name = json_path.stem
    data = json.loads(json_path.read_text())
    md_path = json_path.with_suffix(".md")
    md = md_path.read_text() if md_path.exists() else ""
    heading = next((ln.lstrip("#").strip() for ln in md.splitlines() if ln.startswith("#")), name)
    heading = _papers(_CODE.sub(r"\1", heading))
    title = f"{name}: {heading}"
    if isinstance(data, dict) and data.get("date"):
        date, commit, origin = str(data["date"]), str(data.get("commit", "")), "as recorded in the JSON"
    else:
        date, commit = git_run(json_path)
        origin = "from git log of the JSON file"
    lines = [
        f".. _bench-{name}:",
        "",
        title,
        "=" * len(title),
        "",
        "Reproduce (from the repository root, after the set-up):",
        "",
        ".. code-block:: bash",
        "",
        f"   {command_for(name)}",
        "",
        f"- **Run**: {date}" + (f", commit ``{commit}``" if commit else "") + f" ({origin})",
        f"- **Machine**: {inline(_machine(data))}",
        f"- **Files**: ``benchmarks/results/{name}.json``" + (f", ``{name}.md``" if md else ""),
        "",
        "Figures from a shared 2-core development machine with other jobs running: rerun to reproduce; "
        "ratios measured side by side in one run hold better than absolute rates.",
        "",
    ]
    if md:
        lines += markdown_to_rst(md)
    else:
        lines += [".. code-block:: json", ""] + [
            f"   {ln}" for ln in json.dumps(data, indent=1).splitlines()[:200]
        ]
    return "\n".join(lines) + "\n"


def generate(app: Any = None) -> list[Path]:
    OUT.mkdir(exist_ok=True)
    (OUT / ".gitignore").write_text("*\n")
    written = []
    for json_path in sorted(RESULTS.glob("*.json")):
        target = OUT / f"{json_path.stem}.rst"
        text = page(json_path)
        if not target.exists() or target.read_text() != text:  # unchanged pages keep their mtime
            target.write_text(text)
        written.append(target)
    for stale in OUT.glob("*.rst"):
        if stale not in written:
            stale.unlink()
    return written


def setup(app: Any) -> dict[str, Any]:
    app.connect("builder-inited", generate)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
