"""The recorded figures: JSON files beside the benches that print them, rendered into
docs/RESULTS.md (every figure, with plots) and the README's "Where it stands" (a few key lines).

A bench whose figures are quoted calls :func:`record` (through its ``--record NAME`` option)
after it has printed them. That writes ``bench/results/NAME.json``: the figures as printed,
the command line, the commit it ran on, the machine and its load average before and after.
It refuses to write when the code the figures measure (``measures``: the package and the
bench itself by default) has uncommitted changes, since the commit would then not be the
code that was measured.

``python bench/figures.py --write`` (or ``--write-readme``) renders every result file into
docs/RESULTS.md (tables, and PNG plots in docs/figures/) and the key figures into README.md,
between the markers ``<!-- figures:begin -->`` and ``<!-- figures:end -->``.

A figure older than the code it measures (a file under ``measures`` changed between the
commit it was recorded at and HEAD) is marked "code changed since COMMIT" on both pages.
The mark is computed from the result files and the git history only, so the pages are the
same for everyone at one commit. ``python bench/figures.py --check`` (run by the test suite)
lists such figures as notices and still exits 0; it fails (exit 1) when a page differs from
what the files give, when a result file's commit is not in the history, or when a plot the
page shows is missing. The comparison ignores the "code changed since" marks, so committing
code alone never fails it: the marks appear on the pages the next time they are written.

What a figure measures (``measures`` of :func:`record`): the files whose change can change
it, as git pathspecs relative to the repository (the bench file itself is always added). By
default the whole package ``orbslam_hgcn``: right for a bench that runs the SLAM system
(``orbslam-hgcn run``, ``Slam``), where any module can move a figure. A bench whose figures do
not run the system (e.g. bench_track_words.py's families of rendered or photographed
sequences: extraction, tracks, vocabularies and their scoring) passes the packages and files
it exercises, sibling benches it imports included, so that a change elsewhere in the package
does not mark its figures stale. A result file keeps the ``measures`` declared when it was
recorded.

Quoting a figure in prose. A page under docs/ (every ``docs/*.md`` but RESULTS.md) quotes a
recorded figure with an inline marker, invisible once the markdown is rendered::

    <!-- fig NAME | KEY | PART -->VALUE<!-- /fig -->

NAME is a result file (``bench/results/NAME.json``), KEY one of its figure labels, and PART
(optional, with its ``|``) a label inside that figure's value. The quote is the whole value
when PART is left out; otherwise it is found by this rule (:func:`quote`), brackets ``()``
and ``[]`` hiding everything inside them:

1. the first place where PART stands as a label: at the start of the value or after a
   space, followed by a space or ": ". The quote is the text after it (and its ": ") up to
   the next "," or ";" (or the end of the value). ``A0 0.748, A1 0.739, B0 0.753`` with
   PART ``B0`` gives ``0.753``; ``B0-A0 +0.005 [-0.013, +0.026] 8/12 Holm p 1; B1-A0 ...``
   with PART ``B0-A0`` gives ``+0.005 [-0.013, +0.026] 8/12 Holm p 1``; ``3 runs: tracked
   160-160 of 160 frames, resets 0`` with PART ``tracked`` gives ``160-160 of 160 frames``;
   PART ``C`` matches ``C 0.759``, never ``C-att 0.764``; a unit followed by a space is a
   label too: ``46.5 frames/s (1.13x orb)`` with PART ``frames/s`` gives ``(1.13x orb)``;
2. failing that, the first piece between "," and ";" that ends with a space and PART
   (a count before its label): ``tracked 160, 80 keyframes`` with PART ``keyframes`` gives
   ``80``.

``--write`` fills every marker's VALUE from the result files; ``--check`` reports, with the
file and line, a marker whose VALUE differs from the quote (white space aside) and one that
names an unknown result, key or part. The markers carry no "code changed since" mark: the
prose around them names the result, whose mark is on RESULTS.md.

docs/RESULTS.md keeps its lines under :data:`MAX_LINE` characters (the tests check the
page): a result with more than :data:`WIDE` plain figures (one per run, say) is a table of
one row per figure, a value longer than :data:`CELL` cut after each top-level ";" into rows
of their own and wrapped where a piece is still too long; a result with fewer is a table of one row per label
inside the values and one column per figure. A recorded command is shown as recorded; where
it names folders under /tmp, a note says they were temporary.

Usage::

    python bench/figures.py --write
    python bench/figures.py --check
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shlex
import subprocess
import sys
import textwrap
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
README = REPO / "README.md"
RESULTS_PAGE = REPO / "docs" / "RESULTS.md"
DOCS = REPO / "docs"
# Which vocabulary for what, as `orbslam-hgcn vocab info` prints it (package data).
VOCAB_PAGE = REPO / "orbslam_hgcn" / "data" / "WHICH_VOCABULARY.md"
PLOTS = REPO / "docs" / "figures"
BEGIN, END = "<!-- figures:begin -->", "<!-- figures:end -->"

# The README's key lines: (result name, figure label, the parts of its value to quote,
# wording). Parts are the comma-separated pieces of the value; a part is quoted when it
# starts with one of the prefixes (all parts for None). A line whose result or figure is
# not recorded is left out.
KEY_LINES = [
    ("peer_gate_kitti00", "verdict", None,
     "ORB-SLAM3 given the shipped ORB tree (`vocab export orb`), KITTI 00 frames 0-159, paced"),
    ("peer_jpeg_office", "median", None,
     "throughput beside ORB-SLAM3 (same machine, same run; a run where either tracks under 95% is void), a 900-frame "
     "640x480 JPEG render of the fr3 office path, unpaced"),
    ("peer_kitti00", "median", None, "the same, real KITTI 00 frames 0-159 (ORB-SLAM3 unpaced on 2 cores loses its track "
     "in most runs)"),
    ("peer_kitti00_paced", "median", None, "the same at the camera's rate, where both track every frame: the ratio of "
     "frames/s is the pace's; CPU per frame is the comparison"),
    ("peer_kitti00_paced", "median orbslam-hgcn", None,
     "accuracy in the same runs, KITTI 00 at the camera's rate: ours (one map on every run)"),
    ("peer_kitti00_paced", "median ORB-SLAM3", None,
     "ORB-SLAM3, medians over the runs"),
    ("peer_sitting_xyz", "median orbslam-hgcn", None,
     "real TUM fr3 sitting_xyz (148 frames at about 5 Hz, people in view) at the camera's rate beside ORB-SLAM3: ours"),
    ("peer_sitting_xyz", "median ORB-SLAM3", None,
     "ORB-SLAM3, medians over the runs"),
    ("startup_fresh_clone", "median", None,
     "start-up in a fresh clone after `bash tools/setup.sh`, its first runs: from the command to the first frame "
     "handed in (KITTI 00)"),
    ("long_runs_office", "office/unpaced/none", ("peak memory", "tracking", "local mapping", "keyframes", "tracked"),
     "long runs: a 6-lap 240 s rendered office (7200 frames) unpaced, last quarter against the first"),
    ("long_runs_office", "office/paced/none", ("peak memory", "loops", "laps joined", "tracked", "real-time factor"),
     "the same at the camera's rate"),
    ("long_runs_street", "street/unpaced/none", ("peak memory", "tracking", "local mapping", "db query", "keyframes",
                                                 "tracked"),
     "a 450 s rendered street drive (4500 frames, KITTI camera, no revisit) unpaced, last quarter against the first"),
    ("long_runs_street", "street/paced/none", ("tracking", "local mapping", "real-time factor", "dropped"),
     "the same at the camera's rate"),
    ("kitti00_load", "kitti00/none/threaded", ("3 runs", "tracked", "keyframe ATE", "camera ATE", "frame latency"),
     "KITTI 00 frames 0-159, `orbslam-hgcn run` defaults, paced"),
    ("kitti00_load", "kitti00/hog/threaded", ("tracked", "keyframe ATE", "camera ATE"),
     "the same beside a busy process at normal priority"),
    ("words_in_system", "kmeans", ("words", "insert step", "tracked", "keyframe ATE"),
     "KITTI 00 unpaced, k-means words (ratios against the ORB tree)"),
    ("track_words", "8000 words, AP", None, "place recognition AP, 20 rendered offices, 8000 words"),
    ("track_words_street", "8000 words, AP", None, "the same, 8 rendered street drives"),
    ("track_words_photos", "8000 words, AP", None,
     "the same, held-out real CamVid frames (6 units; truth by fundamental-matrix inliers)"),
    ("track_words_kitti", "8000 words, false positives of 44 queries", None,
     "real KITTI 00 (no revisit), false detections of 44 queries"),
]

STALE_WORDS = "code changed since"
MAX_LINE = 400  # the longest line docs/RESULTS.md may have
WIDE = 4  # a result with more plain figures than this is shown one row per figure
CELL = 160  # there, a value longer than this is cut after each top-level ";"
_MARK = re.compile(r" ?\*\*code changed since [0-9a-f]{7,40}\*\*")
_MARK_LINE = re.compile(r"^\*\*code changed since [0-9a-f]{7,40}\*\*:[^\n]*\n\n", re.M)
_CONTRAST = re.compile(r"^(\S+) ([+-]?[\d.]+) \[([+-]?[\d.]+), ([+-]?[\d.]+)\](?: (\d+/\d+))?(?: Holm p (\S+))?$")
_ATE = re.compile(r"keyframe ATE ([\d.]+) cm")


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
    """Write ``bench/results/NAME.json`` for the results page (see the module text).

    ``figures``: (label, value as printed) pairs, in the order the page shows them;
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


# --- staleness ---------------------------------------------------------------------------
def known_commit(commit: str) -> bool:
    return _git("cat-file", "-e", f"{commit}^{{commit}}").returncode == 0


def staleness(results: list[dict]) -> dict[str, list[str]]:
    """Result name -> the files it measures that changed between its commit and HEAD (only
    results with such files; a result whose commit is unknown is left out: see problems).
    Text pages inside the package (``*.md``, such as the quotes ``vocab info`` prints) are
    not code: their changes never make a figure stale."""
    out = {}
    for r in results:
        if not known_commit(r["commit"]):
            continue
        changed = [f for f in _git("diff", "--name-only", r["commit"], "HEAD", "--", *r["measures"]).stdout.split()
                   if not f.endswith(".md")]  # fmt: skip
        if changed:
            out[r["name"]] = changed
    return out


def mark(r: dict, stale: dict[str, list[str]]) -> str:
    """The inline mark of a stale result ("" when current)."""
    return f" **{STALE_WORDS} {r['commit']}**" if r["name"] in stale else ""


def normalise(text: str) -> str:
    """A page with its "code changed since" marks taken out."""
    return _MARK.sub("", _MARK_LINE.sub("", text))


# --- parsing the printed values ----------------------------------------------------------
def _parts(value: str) -> list[tuple[str, str]]:
    """(key, value) pieces of a printed value: 'tracked 160 of 160, resets 0' ->
    [('tracked', '160 of 160'), ('resets', '0')]; '28.6 frames/s' -> [('frames/s', '28.6 frames/s')]."""
    out = []
    m = re.match(r"^(\d+) (runs?): (.*)$", value)
    if m:
        out.append((m.group(2), m.group(1)))
        value = m.group(3)
    for part in re.split(r", (?![^\[(]*[\])])", value):
        part = part.strip()
        m = re.match(r"^(.*?[^\d\s.+-][^\s]*)\s+([-+]?\d.*)$", part)
        if m:
            out.append((m.group(1), m.group(2)))
            continue
        m = re.match(r"^[-+]?[\d.]+\s+(\S+)", part)
        out.append((m.group(1) if m else "", part))
    return out


def contrasts(value: str) -> list[tuple[str, ...]] | None:
    """'B0-A0 +0.022 [+0.002, +0.043] 13/7 Holm p 1; ...' -> [(contrast, difference, low,
    high, wins/losses, Holm p)], or None when the value is not such a list."""
    items = [s.strip() for s in value.split(";")]
    found = [_CONTRAST.match(s) for s in items]
    if not items or not all(found):
        return None
    return [tuple(g or "" for g in m.groups()) for m in found]


def _cell(s: str) -> str:
    return s.replace("|", "\\|")


# --- quoting a figure in the docs' prose -------------------------------------------------
_FIG = re.compile(r"<!--\s*fig\s(?P<spec>(?:(?!-->).)*?)-->(?P<value>(?:(?!<!--).)*?)<!--\s*/fig\s*-->", re.S)
_FIG_OPEN = re.compile(r"<!--\s*fig\s")


def _top_level(value: str) -> list[int]:
    """Bracket depth (of ``()`` and ``[]``) before each character of ``value``."""
    depth, out = 0, []
    for ch in value:
        if ch in ")]":
            depth = max(depth - 1, 0)
        out.append(depth)
        if ch in "([":
            depth += 1
    return out


def _pieces(value: str) -> list[str]:
    """``value`` cut at every "," and ";" outside brackets, each piece stripped."""
    depth, out, start = _top_level(value), [], 0
    for i, ch in enumerate(value):
        if ch in ",;" and depth[i] == 0:
            out.append(value[start:i].strip())
            start = i + 1
    return [*out, value[start:].strip()]


def quote(value: str, part: str | None = None) -> str | None:
    """The text a marker quotes from a figure's value: all of it without ``part``, else the
    part's text by the rule of the module text (None where the value has no such part)."""
    if not part:
        return value
    depth, n = _top_level(value), len(part)
    for i in range(len(value) - n + 1):
        if depth[i] or not value.startswith(part, i) or (i and value[i - 1] != " "):
            continue
        if value[i + n:i + n + 1] == " " or value[i + n:i + n + 2] == ": ":
            rest = value[i + n:]
            return _pieces(rest.removeprefix(":").strip())[0]
    for piece in _pieces(value):
        if piece.endswith(" " + part):
            return piece[:-n].strip()
    return None


def _spec(text: str) -> tuple[str, str, str | None] | None:
    fields = [" ".join(f.split()) for f in text.split("|")]
    if len(fields) not in (2, 3) or not all(fields):
        return None
    return fields[0], fields[1], fields[2] if len(fields) == 3 else None


def quotes(text: str, results: list[dict], where: str = "") -> tuple[str, list[str]]:
    """``text`` with every figure marker's VALUE filled from ``results``, and what is wrong with
    its markers as it stands ("WHERE:LINE: why"; empty when every VALUE is its quote)."""
    figs = {r["name"]: dict(r["figures"]) for r in results}
    found, out, pos, starts = [], [], 0, set()
    for m in _FIG.finditer(text):
        starts.add(m.start())
        at = f"{where}:{text.count(chr(10), 0, m.start()) + 1}"
        spec = _spec(m.group("spec"))
        want = None
        if spec is None:
            found.append(f"{at}: figure marker {m.group('spec').strip()!r} is not 'NAME | KEY' or 'NAME | KEY | PART'")
        elif spec[0] not in figs:
            found.append(f"{at}: figure marker names no result file: bench/results/{spec[0]}.json")
        elif spec[1] not in figs[spec[0]]:
            found.append(f"{at}: {spec[0]} has no figure {spec[1]!r}")
        else:
            want = quote(figs[spec[0]][spec[1]], spec[2])
            if want is None:
                found.append(f"{at}: {spec[0]}, {spec[1]!r} has no part {spec[2]!r}")
            elif " ".join(m.group("value").split()) != want:
                found.append(f"{at}: quotes {' '.join(m.group('value').split())!r} from {spec[0]}, {spec[1]!r}"
                             f"{'' if spec[2] is None else ', ' + repr(spec[2])}; the result file gives {want!r} "
                             "(python bench/figures.py --write)")
        value = m.group("value")
        if want is not None and " ".join(value.split()) != want:
            value = want
        out.append(text[pos:m.start("value")] + value)
        pos = m.end("value")
    out.append(text[pos:])
    for m in _FIG_OPEN.finditer(text):
        if m.start() not in starts:
            found.append(f"{where}:{text.count(chr(10), 0, m.start()) + 1}: figure marker without its <!-- /fig -->")
    return "".join(out), found


def doc_pages(folder: Path = DOCS) -> dict[str, str]:
    """The pages whose prose may quote figures: every docs/*.md but RESULTS.md, and the
    README (its prose outside the figures block), by path."""
    pages = [p for p in sorted(folder.glob("*.md")) if p.name != RESULTS_PAGE.name]
    if folder == DOCS:
        pages += [README, VOCAB_PAGE]
    return {str(p.relative_to(REPO)) if p.is_relative_to(REPO) else str(p): p.read_text() for p in pages}


# --- the results page --------------------------------------------------------------------
def _plot_names(results: list[dict]) -> dict[str, str]:
    """Plot file name -> what it shows, for the plots the results give."""
    out = {}
    if any(_ATE.search(f"{k} {v}") for r in results for k, v in r["figures"]):
        out["keyframe_ate.png"] = "keyframe ATE"
    for r in results:
        if any(contrasts(v) for _, v in r["figures"]):
            out[f"{r['name']}_contrasts.png"] = r["name"]
    return out


def _rows(label: str, value: str) -> list[str]:
    """One figure as table rows: a value longer than CELL cut after each top-level ";", a
    piece longer than fits wrapped; the label on the first row only."""
    depth, pieces, start = _top_level(value), [], 0
    for i, ch in enumerate(value):
        if ch == ";" and depth[i] == 0 and len(value) > CELL:
            pieces.append(value[start:i + 1].strip())
            start = i + 1
    pieces.append(value[start:].strip())
    lines = [w for piece in pieces if piece
             for w in textwrap.wrap(piece, MAX_LINE - 100, break_on_hyphens=False)]
    return [f"| {_cell(label) if i == 0 else ''} | {_cell(line)} |" for i, line in enumerate(lines or [""])]


def _table(r: dict) -> list[str]:
    """The result's figures that are not contrast lists: one row per key and one column per
    figure, or, past WIDE figures, one row per figure (see the module text)."""
    plain = [(k, v) for k, v in r["figures"] if contrasts(v) is None]
    if not plain:
        return []
    if len(plain) > WIDE:
        return ["| figure | value |", "|---|---|", *[row for k, v in plain for row in _rows(k, v)]]
    cols = [k for k, _ in plain]
    rows: dict[str, dict[str, str]] = {}
    for label, value in plain:
        for key, val in _parts(value):
            rows.setdefault(key, {})[label] = val
    if len(cols) == 1:
        return ["| | " + _cell(cols[0]) + " |", "|---|---|",
                *[f"| {_cell(k)} | {_cell(v.get(cols[0], ''))} |" for k, v in rows.items()]]
    out = ["| | " + " | ".join(_cell(c) for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for key, vals in rows.items():
        out.append(f"| {_cell(key)} | " + " | ".join(_cell(vals.get(c, "")) for c in cols) + " |")
    return out


def _contrast_table(r: dict) -> list[str]:
    rows = []
    for label, value in r["figures"]:
        for c in contrasts(value) or []:
            rows.append(f"| {_cell(label)} | {c[0]} | {c[1]} | [{c[2]}, {c[3]}] | {c[4]} | {c[5]} |")
    if not rows:
        return []
    return ["| figure | contrast | difference | 95% CI | wins/losses | Holm p |", "|---|---|---|---|---|---|", *rows]


def render_results(results: list[dict], stale: dict[str, list[str]]) -> str:
    """docs/RESULTS.md: an index, then per result its provenance, tables and plots."""
    plots = _plot_names(results)
    out = [
        "# Recorded results",
        "",
        "Written by `python bench/figures.py --write` from `bench/results/*.json`; do not edit by hand",
        "(`python bench/figures.py --check`, run by the test suite, fails when this page differs from",
        "the files). Each file is written by a bench's `--record NAME` with the command, the commit it",
        "ran on, the date, the machine and its 1-minute load average at the start and the end (about 1",
        f"while nothing runs beside the bench). A result marked **{STALE_WORDS} COMMIT** was measured",
        "on older code than this page's commit: a file it measures has changed since; run its command",
        "again and record it.",
        "",
        "| result | figures | commit | date | load |",
        "|---|---|---|---|---|",
    ]
    for r in results:
        out.append(f"| [{r['name']}](#{r['name']}) | {len(r['figures'])} | {r['commit']}{mark(r, stale)} "
                   f"| {r.get('date', '')} | {_load(r)} |")  # fmt: skip
    if "keyframe_ate.png" in plots:
        out += ["", "Keyframe ATE of every recorded run that prints one (Sim(3)-aligned, cm):", "",
                "![keyframe ATE](figures/keyframe_ate.png)"]
    for r in results:
        out += ["", f"## {r['name']}", "", r["title"] + ".", ""]
        if r["name"] in stale:
            files = stale[r["name"]]
            shown = ", ".join(f"`{f}`" for f in files[:3]) + (f" and {len(files) - 3} more" if len(files) > 3 else "")
            out += [f"**{STALE_WORDS} {r['commit']}**: {shown} changed since it was measured.", ""]
        out += ["| recorded | |", "|---|---|", f"| command | `{_cell(r['command'])}` |", *_temporary(r['command']),
                f"| commit | {r['commit']} |",
                f"| date | {r.get('date', '')} |", f"| machine | {_cell(r.get('machine', ''))} |",
                f"| load | {_load(r)} |", f"| measures | {', '.join(f'`{m}`' for m in r['measures'])} |"]
        if r.get("notes"):
            out.append(f"| notes | {_cell(r['notes'])} |")
        for block in (_table(r), _contrast_table(r)):
            if block:
                out += ["", *block]
        png = f"{r['name']}_contrasts.png"
        if png in plots:
            out += ["", f"![{r['name']} contrasts](figures/{png})"]
    return "\n".join(out) + "\n"


def _temporary(command: str) -> list[str]:
    """A note row where a recorded command names folders under /tmp."""
    folders = list(dict.fromkeys(re.findall(r"/tmp/[^/\s=,'\"]+", command)))
    if not folders:
        return []
    return [f"| note | {', '.join(f'`{f}`' for f in folders)}: temporary folder{'s' if len(folders) > 1 else ''} of "
            "the recording machine, not kept: to run the command again, make its inputs anew (docs/BENCHMARKS.md) |"]


def _load(r: dict) -> str:
    if r.get("load_start") is None:
        return "" if r.get("load_end") is None else f"end {r['load_end']:.2f}"
    return f"{r['load_start']:.2f}-{r['load_end']:.2f}"


# --- the README's key lines --------------------------------------------------------------
def render_key(results: list[dict], stale: dict[str, list[str]]) -> str:
    """The README block: a few key figures, each naming its result file and commit."""
    by_name = {r["name"]: r for r in results}
    lines = []
    for name, label, keep, words in KEY_LINES:
        r = by_name.get(name)
        value = dict(r["figures"]).get(label) if r else None
        if value is None:
            continue
        parts = [p.strip() for p in re.split(r", (?![^\[(]*[\])])", value)]
        if keep is not None:
            parts = [p for p in parts if p.startswith(keep)]
        text = f"- {words}: {', '.join(parts)} ([{name}](docs/RESULTS.md#{name}), {r['commit']})"
        lines += textwrap.wrap(text, 150, subsequent_indent="  ", break_on_hyphens=False)
        lines[-1] += mark(r, stale)
    lines.append("- Every recorded figure, with its command, commit, machine and load: [docs/RESULTS.md](docs/RESULTS.md).")
    return "\n".join(lines)


def readme_block(text: str) -> str:
    """The text between the markers of a README (ValueError where they are missing)."""
    if BEGIN not in text or END not in text:
        raise ValueError(f"README.md has no {BEGIN} ... {END} block")
    return text.split(BEGIN, 1)[1].split(END, 1)[0].strip()


# --- plots -------------------------------------------------------------------------------
def write_plots(results: list[dict], folder: Path = PLOTS) -> list[Path]:
    """The PNGs the results page shows (matplotlib, small)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    meta = {"Software": None}
    ates = [(f"{r['name']}: {k}", float(m.group(1))) for r in results for k, v in r["figures"]
            if (m := _ATE.search(f"{k} {v}"))]
    if ates:
        fig, ax = plt.subplots(figsize=(6.4, 0.35 * len(ates) + 0.9), dpi=80)
        ax.barh(range(len(ates)), [a for _, a in ates], color="#4a7bb7")
        ax.set_yticks(range(len(ates)), [n for n, _ in ates], fontsize=8)
        ax.invert_yaxis()
        for i, (_, a) in enumerate(ates):
            ax.text(a, i, f" {a:.2f}", va="center", fontsize=8)
        ax.set_xlabel("keyframe ATE (cm)")
        ax.set_xlim(0, max(a for _, a in ates) * 1.2)
        fig.tight_layout()
        written.append(folder / "keyframe_ate.png")
        fig.savefig(written[-1], metadata=meta)
        plt.close(fig)
    for r in results:
        groups = [(k, c) for k, v in r["figures"] if (c := contrasts(v))]
        if not groups:
            continue
        fig, axes = plt.subplots(1, len(groups), figsize=(3.3 * len(groups), 0.3 * max(len(c) for _, c in groups) + 1.2),
                                 dpi=80, squeeze=False)  # fmt: skip
        for ax, (label, cs) in zip(axes[0], groups):
            d = [float(c[1]) for c in cs]
            lo = [float(c[1]) - float(c[2]) for c in cs]
            hi = [float(c[3]) - float(c[1]) for c in cs]
            ax.errorbar(d, range(len(cs)), xerr=[lo, hi], fmt="o", color="#b7584a", capsize=3, markersize=4)
            ax.axvline(0, color="grey", lw=0.8)
            ax.set_yticks(range(len(cs)), [c[0] for c in cs], fontsize=8)
            ax.invert_yaxis()
            ax.set_title(label, fontsize=9)
            ax.tick_params(axis="x", labelsize=8)
            ax.set_xlabel("difference, 95% CI", fontsize=8)
        fig.tight_layout()
        written.append(folder / f"{r['name']}_contrasts.png")
        fig.savefig(written[-1], metadata=meta)
        plt.close(fig)
    return written


# --- the check ---------------------------------------------------------------------------
def problems(results: list[dict], readme_text: str, results_text: str, plots: Path = PLOTS,
             docs: dict[str, str] | None = None) -> list[str]:
    """Why the pages and the result files disagree (empty when they agree). The "code changed
    since" marks are left out of the comparison: a stale figure is a notice, not a problem.
    ``docs``: the pages whose figure markers are checked, path -> text (default: docs/*.md
    but RESULTS.md, read from disk)."""
    out = []
    for where, text in (doc_pages() if docs is None else docs).items():
        out += quotes(text, results, where)[1]
    stale = staleness(results)
    if normalise(readme_block(readme_text)) != normalise(render_key(results, stale)):
        out.append("the README's figures block differs from bench/results/*.json (python bench/figures.py --write)")
    if normalise(results_text) != normalise(render_results(results, stale)):
        out.append("docs/RESULTS.md differs from bench/results/*.json (python bench/figures.py --write)")
    for name in _plot_names(results):
        if not (plots / name).is_file():
            out.append(f"docs/figures/{name} is missing (python bench/figures.py --write)")
    for r in results:
        if not known_commit(r["commit"]):
            out.append(f"{r['name']}: commit {r['commit']} is not in this repository's history")
    return out


def notices(results: list[dict]) -> list[str]:
    """The results measured on older code than HEAD (no failure)."""
    return [f"{name}: {STALE_WORDS} {next(r['commit'] for r in results if r['name'] == name)} "
            f"({len(files)} file(s) it measures, e.g. {files[0]}): run its command again and record it"
            for name, files in staleness(results).items()]  # fmt: skip


def write_pages(results: list[dict]) -> None:
    stale = staleness(results)
    text = README.read_text()
    before, rest = text.split(BEGIN, 1)
    README.write_text(f"{before}{BEGIN}\n{render_key(results, stale)}\n{END}{rest.split(END, 1)[1]}")
    RESULTS_PAGE.parent.mkdir(parents=True, exist_ok=True)
    RESULTS_PAGE.write_text(render_results(results, stale))
    for where, text in doc_pages().items():
        filled = quotes(text, results, where)[0]
        if filled != text:
            (REPO / where).write_text(filled)
            print(f"{where}: figure markers filled from bench/results")
        for f in quotes(filled, results, where)[1]:  # what filling cannot mend
            print(f, file=sys.stderr)
    plots = write_plots(results)
    print(f"README.md, {RESULTS_PAGE.relative_to(REPO)}: {len(results)} result(s), {len(stale)} older than the code; "
          f"{len(plots)} plot(s) in {PLOTS.relative_to(REPO)}")  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--write", "--write-readme", "--write-results", dest="write", action="store_true",
                   help="render the result files into docs/RESULTS.md, docs/figures/ and README.md")
    g.add_argument("--check", action="store_true",
                   help="fail when the pages and the result files disagree; list figures older than the code")
    a = ap.parse_args()
    results = load_results()
    if a.write:
        write_pages(results)
        return 0
    for n in notices(results):
        print(f"notice: {n}")
    found = problems(results, README.read_text(), RESULTS_PAGE.read_text() if RESULTS_PAGE.exists() else "")
    for p in found:
        print(p, file=sys.stderr)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
