"""The README's "Where it stands" figures against the bench result files committed beside
them (bench/figures.py): the quoted block must be what the files give, and no figure may be
older than the code it measures."""

import importlib.util
import json
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _figures():
    spec = importlib.util.spec_from_file_location("bench_figures", REPO / "bench" / "figures.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()


def test_readme_quotes_the_committed_bench_results():
    fig = _figures()
    results = fig.load_results()
    assert results, "bench/results holds no result file"
    assert fig.problems(results, (REPO / "README.md").read_text()) == []


def _result(commit: str, measures: list[str], value: str = "38.65 cm") -> dict:
    return {"name": "kitti", "title": "KITTI 00", "figures": [["keyframe ATE", value]], "command": "python bench/x.py",
            "commit": commit, "measures": measures, "load_start": 0.1, "load_end": 0.2, "notes": ""}


def test_the_check_fails_on_a_changed_figure_a_stale_commit_and_an_unknown_commit():
    fig = _figures()
    head = _git("rev-parse", "--short=7", "HEAD")
    first = _git("rev-list", "--max-parents=0", "HEAD").splitlines()[-1][:7]
    good = _result(head, ["bench/figures.py"])
    readme = f"intro\n{fig.BEGIN}\n{fig.render([good])}\n{fig.END}\nrest\n"
    assert fig.problems([good], readme) == []
    # A figure edited in the README but not in the result file.
    assert any("differs" in p for p in fig.problems([good], readme.replace("38.65", "30.65")))
    # Measured at the first commit: the package has changed since.
    stale = _result(first, ["orbslam_hgcn"])
    found = fig.problems([stale], f"{fig.BEGIN}\n{fig.render([stale])}\n{fig.END}")
    assert len(found) == 1 and "changed since" in found[0]
    missing = _result("0000000", ["orbslam_hgcn"])
    found = fig.problems([missing], f"{fig.BEGIN}\n{fig.render([missing])}\n{fig.END}")
    assert len(found) == 1 and "not in this repository's history" in found[0]
    with pytest.raises(ValueError):
        fig.readme_block("no markers here")


def test_record_prints_the_results_path_inside_or_outside_the_repository(tmp_path, monkeypatch, capsys):
    fig = _figures()
    repo = tmp_path / "repo"
    monkeypatch.setattr(fig, "REPO", repo)
    # A clean tree at commit abc1234, whatever this checkout holds.
    monkeypatch.setattr(fig, "_git", lambda *args: subprocess.CompletedProcess(
        args, 0, "abc1234\n" if args[0] == "rev-parse" else "", ""))
    bench = str(repo / "bench" / "bench_x.py")
    for results, shown in ((repo / "bench" / "results", "bench/results/x.json"),
                           (tmp_path / "elsewhere", str((tmp_path / "elsewhere" / "x.json").resolve()))):
        monkeypatch.setattr(fig, "RESULTS", results)
        path = fig.record("x", "X", [("ATE", "1.00 cm")], bench_file=bench, load_start=0.5)
        assert path == results / "x.json"
        written = json.loads(path.read_text())
        assert written["figures"] == [["ATE", "1.00 cm"]] and written["commit"] == "abc1234"
        assert written["measures"] == ["bench/bench_x.py", "orbslam_hgcn"]
        assert capsys.readouterr().out == f"figures: recorded {shown} at abc1234\n"
