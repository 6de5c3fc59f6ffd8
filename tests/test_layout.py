"""The package's layout: every module imports on its own, no import cycles (counting imports
inside functions), and imports flow one way between the layers that docs/ARCHITECTURE.md
states in its tables (checked to be the LAYERS and AGAINST_THE_FLOW below):
geometry -> features -> match -> map -> vocabulary/backend -> stages -> runtime -> app -> cli."""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "orbslam_hgcn"

ARCHITECTURE = ROOT / "docs" / "ARCHITECTURE.md"

# Layers of the one-way flow; an import may go to a lower layer or stay in its own package.
LAYERS = {
    "geometry": 0,
    "features": 1,
    "match": 2,
    "map": 3,
    "vocabulary": 4,
    "backend": 4,
    "tracking": 5,
    "mapping": 5,
    "loop": 5,
    "runtime": 6,
    "app": 7,
    "cli": 8,
}
STAGES = ("tracking", "mapping", "loop")
# Imports against the flow, each with its reason. The keyframe database sits beside the map
# (ARCHITECTURE.md) and indexes the vocabulary's BoW vectors.
AGAINST_THE_FLOW = {
    ("orbslam_hgcn.map.database", "orbslam_hgcn.vocabulary"),
    ("orbslam_hgcn.map.database", "orbslam_hgcn.vocabulary.bow"),
}


def doc_tables(text: str) -> dict[str, list[list[str]]]:
    """The markdown tables of a page, by their header row ("layer | packages"): the rows'
    cells, without the header and the rule."""
    tables: dict[str, list[list[str]]] = {}
    lines = text.splitlines()
    for i, line in enumerate(lines[:-1]):
        if line.startswith("|") and re.fullmatch(r"\|(\s*:?-+:?\s*\|)+", lines[i + 1].strip()):
            head = " | ".join(c.strip() for c in line.strip().strip("|").split("|"))
            rows = []
            for row in lines[i + 2:]:
                if not row.startswith("|"):
                    break
                rows.append([c.strip().strip("`") for c in row.strip().strip("|").split("|")])
            tables[head] = rows
    return tables


def documented_layers(text: str) -> tuple[dict[str, int], set[tuple[str, str]]]:
    """The layers ("layer | packages" table) and the imports against the flow ("importer |
    imported" table) that docs/ARCHITECTURE.md states."""
    tables = doc_tables(text)
    if "layer | packages" not in tables or "importer | imported" not in tables:
        raise ValueError("docs/ARCHITECTURE.md has no 'layer | packages' or 'importer | imported' table")
    layers = {p.strip(): int(n) for n, packages in tables["layer | packages"] for p in packages.split(",")}
    return layers, {(a, b) for a, b in tables["importer | imported"]}


def package_modules() -> dict[str, tuple[Path, bool]]:
    """Dotted name -> (file, is a package) for every module of the package."""
    mods = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        if is_pkg:
            parts = parts[:-1]
        mods[".".join(parts)] = (path, is_pkg)
    return mods


def _ancestors(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def import_graph(mods: dict[str, tuple[Path, bool]]) -> dict[str, dict[str, int]]:
    """module -> {imported module of the package: line}, from every import statement of
    the module (at the top, in functions, in classes). Importing ``a.b.c`` also runs the
    packages ``a`` and ``a.b`` unless the importer is inside them already, so those count."""

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, dict[str, int]] = {}
    for mod, (path, is_pkg) in mods.items():
        here = mod if is_pkg else mod.rpartition(".")[0]
        targets: dict[str, int] = {}
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            found: list[str] = []
            if isinstance(node, ast.Import):
                found = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = here.split(".")[: len(here.split(".")) - node.level + 1]
                    src = ".".join(base + ([node.module] if node.module else []))
                else:
                    src = node.module or ""
                # "from pkg import sub" imports the submodule; "from mod import name" the module.
                found = [f"{src}.{a.name}" if f"{src}.{a.name}" in mods else src for a in node.names]
            for name in found:
                if not name.startswith("orbslam_hgcn"):
                    continue
                target = resolve(name)
                if target is None:
                    continue
                own = set(_ancestors(mod)) | {mod}
                for t in [*_ancestors(target), target]:
                    if t not in own and t != "orbslam_hgcn":
                        targets.setdefault(t, node.lineno)
        graph[mod] = targets
    return graph


def cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _layer(mod: str) -> str:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else ""


@pytest.fixture(scope="module")
def graph():
    return import_graph(package_modules())


def test_graph_sees_imports_inside_functions_and_packages(graph):
    # A known import inside a function (cli imports the run command when it runs) and the
    # package a submodule import runs (app.run imports datasets, whose __init__ runs).
    assert "orbslam_hgcn.app.run" in graph["orbslam_hgcn.cli"]
    assert "orbslam_hgcn.datasets" in graph["orbslam_hgcn.app.run"]
    assert cycles({"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}, "d": {"a": 1}}) == [["a", "b", "c"]]


def test_no_import_cycles(graph):
    assert cycles(graph) == []


def test_imports_flow_one_way(graph):
    against = []
    for mod, targets in graph.items():
        a = _layer(mod)
        for target, line in targets.items():
            b = _layer(target)
            if a in LAYERS and b in LAYERS and a != b and LAYERS[b] >= LAYERS[a]:
                if (mod, target) not in AGAINST_THE_FLOW:
                    against.append(f"{mod}:{line} imports {target}")
    assert against == []


def test_the_layers_are_those_architecture_md_states():
    layers, against = documented_layers(ARCHITECTURE.read_text())
    assert layers == LAYERS
    assert against == AGAINST_THE_FLOW
    # The stages are one layer, as test_stages_meet_only_in_the_runtime assumes.
    assert {LAYERS[s] for s in STAGES} == {max(LAYERS[s] for s in STAGES)}


def test_documented_layers_read_a_changed_table():
    text = ARCHITECTURE.read_text()
    moved = text.replace("| 4 | vocabulary, backend |", "| 4 | vocabulary |\n| 5 | backend |", 1)
    assert moved != text
    assert documented_layers(moved)[0]["backend"] == 5
    with pytest.raises(ValueError):
        documented_layers("# no tables")


def test_stages_meet_only_in_the_runtime(graph):
    bad = [
        f"{mod} imports {target}"
        for mod, targets in graph.items()
        for target in targets
        if (_layer(mod) in STAGES and _layer(target) in (*STAGES, "runtime", "app", "cli") and _layer(target) != _layer(mod))
        or (_layer(mod) == "map" and _layer(target) in STAGES)
    ]
    assert bad == []


def test_every_module_imports_in_a_fresh_interpreter():
    names = [m for m in package_modules() if m != "orbslam_hgcn.__main__"]  # __main__ runs the CLI
    code = (
        "import importlib, json, sys, traceback\n"
        "failed = {}\n"
        "for name in json.loads(sys.argv[1]):\n"
        "    try:\n"
        "        importlib.import_module(name)\n"
        "    except Exception:\n"
        "        failed[name] = traceback.format_exc(limit=3)\n"
        "print(json.dumps(failed))\n"
    )
    out = subprocess.run([sys.executable, "-c", code, json.dumps(names)], cwd=ROOT, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    failed = json.loads(out.stdout.strip().splitlines()[-1])
    assert failed == {}, "\n".join(f"{k}:\n{v}" for k, v in failed.items())
    assert len(names) > 100


BENCH_SCRIPTS = sorted(p.name for p in (ROOT / "bench").glob("*.py"))


@pytest.mark.parametrize("script", BENCH_SCRIPTS)
def test_every_bench_prints_its_help(script):
    # argparse formats every help string with %: a stray one crashes --help only.
    out = subprocess.run([sys.executable, str(ROOT / "bench" / script), "--help"], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("usage:")


MAX_MODULE_LINES = 700


def test_no_module_is_longer_than_a_reader_can_hold():
    # A module a reader can hold: past this the file is split by concern (runtime/system.py
    # into feed, handover, map_switch and report; config.py into config_files and tool_config).
    long = {str(p.relative_to(ROOT)): n for p in PACKAGE.rglob("*.py")
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES}
    assert long == {}
