"""The figures the README quotes, kept as JSON files beside the benches that print them.

A bench whose figures the README's "Where it stands" quotes calls :func:`record` (through
its ``--record NAME`` option) after it has printed them. That writes
``bench/results/NAME.json``: the figures as printed, the command line, the commit it ran
on, the machine and its load average before and after. It refuses to write when the code
the figures measure (``measures``: the package and the bench itself by default) has
uncommitted changes, since the commit would then not be the code that was measured.

``python bench/figures.py --write-readme`` renders every result file as one table row into
README.md, between the markers ``<!-- figures:begin -->`` and ``<!-- figures:end -->``.
``python bench/figures.py --check`` (run by the test suite) fails when that block differs
from what the files give, when a file's commit is not in the history, or when the code a
figure measures changed after the commit it was measured at. A figure therefore has to be
measured again, and recorded, whenever the code under it changes.

Usage::

    python bench/figures.py --write-readme
    python bench/figures.py --check
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
README = REPO / "README.md"
BEGIN, END = "<!-- figures:begin -->", "<!-- figures:end -->"


def _git(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, timeout=60)


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def record(name: str, title: str, figures: list[tuple[str, str]], *, bench_file: str,
           measures: list[str] | None = None, load_start: float | None = None, notes: str = "") -> Path | None:
    """Write ``bench/results/NAME.json`` for the README's figures table (see the module text).

    ``figures``: (label, value as printed) pairs, in the order the README shows them;
    ``bench_file``: the bench's ``__file__``; ``measures``: paths, relative to the repository,
    whose code the figures depend on (default: the package and the bench file); ``load_start``:
    the 1-minute load average when the bench started. Returns the path written, or None (with
    a message on stderr) when the measured code has uncommitted changes."""
    bench_rel = str(Path(bench_file).resolve().relative_to(REPO))
    measures = sorted(set(measures or ["orbslam_hgcn"]) | {bench_rel})
    dirty = _git("status", "--porcelain", "--", *measures).stdout.strip()
    if dirty:
        print(f"figures: not recorded: uncommitted changes under {', '.join(measures)}:\n{dirty}", file=sys.stderr)
        return None
    commit = _git("rev-parse", "--short=7", "HEAD").stdout.strip()
    out = {
        "name": name,
        "title": title,
        "figures": [[str(k), str(v)] for k, v in figures],
        "command": "python " + " ".join(shlex.quote(a) for a in [bench_rel, *sys.argv[1:]]),
        "commit": commit,
        "measures": measures,
        "date": time.strftime("%Y-%m-%d", time.gmtime()),
        "machine": f"{_cpu()}, {os.cpu_count()} CPUs",
        "load_start": None if load_start is None else round(float(load_start), 2),
        "load_end": round(os.getloadavg()[0], 2),
        "notes": notes,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(out, indent=2) + "\n")
    shown = path.relative_to(REPO) if path.is_relative_to(REPO) else path.resolve()  # a results folder elsewhere
    print(f"figures: recorded {shown} at {commit}")
    return path


def load_results(folder: Path = RESULTS) -> list[dict]:
    """Every result file, ordered by name."""
    return [json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))]


def render(results: list[dict]) -> str:
    """The README block: one table row per result file."""
    rows = ["| what | figures | command | commit, load |", "|---|---|---|---|"]
    for r in results:
        figs = "; ".join(f"{k} {v}" for k, v in r["figures"])
        load = "" if r.get("load_start") is None else f", load {r['load_start']:.2f}-{r['load_end']:.2f}"
        note = f" ({r['notes']})" if r.get("notes") else ""
        rows.append(f"| {r['title']}{note} | {figs} | `{r['command']}` | {r['commit']}{load} |")
    return "\n".join(rows)


def readme_block(text: str) -> str:
    """The text between the markers of a README (ValueError where they are missing)."""
    if BEGIN not in text or END not in text:
        raise ValueError(f"README.md has no {BEGIN} ... {END} block")
    return text.split(BEGIN, 1)[1].split(END, 1)[0].strip()


def problems(results: list[dict], readme_text: str) -> list[str]:
    """Why the README's figures and the result files disagree (empty when they agree)."""
    out = []
    if readme_block(readme_text) != render(results):
        out.append("the README's figures block differs from bench/results/*.json "
                   "(python bench/figures.py --write-readme)")  # fmt: skip
    for r in results:
        if _git("cat-file", "-e", f"{r['commit']}^{{commit}}").returncode != 0:
            out.append(f"{r['name']}: commit {r['commit']} is not in this repository's history")
            continue
        changed = _git("diff", "--name-only", r["commit"], "HEAD", "--", *r["measures"]).stdout.split()
        if changed:
            out.append(f"{r['name']}: measured at {r['commit']}, but {len(changed)} file(s) it measures changed "
                       f"since ({', '.join(changed[:3])}{', ...' if len(changed) > 3 else ''}): run it again")  # fmt: skip
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--write-readme", action="store_true", help="render the result files into README.md")
    g.add_argument("--check", action="store_true", help="fail when README.md and the result files disagree")
    a = ap.parse_args()
    results = load_results()
    text = README.read_text()
    if a.write_readme:
        before, rest = text.split(BEGIN, 1)
        README.write_text(f"{before}{BEGIN}\n{render(results)}\n{END}{rest.split(END, 1)[1]}")
        print(f"README.md: {len(results)} figure row(s) written")
        return 0
    found = problems(results, text)
    for p in found:
        print(p, file=sys.stderr)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
