"""The recorded figures against the pages that show them (bench/figures.py): docs/RESULTS.md
and the README's key lines must be what bench/results/*.json give, every commit named must
be in the history, and a figure older than the code it measures is marked, not a failure."""

import importlib.util
import json
import subprocess
import sys
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


def test_the_pages_show_the_committed_bench_results():
    fig = _figures()
    results = fig.load_results()
    assert results, "bench/results holds no result file"
    page = (REPO / "docs" / "RESULTS.md").read_text()
    assert fig.problems(results, (REPO / "README.md").read_text(), page) == []
    # Every result file has its section on the page, with its command and commit.
    for r in results:
        assert f"\n## {r['name']}\n" in page and r["command"] in page and r["commit"] in page


def _result(commit: str, measures: list[str], value: str = "38.65 cm", name: str = "kitti") -> dict:
    return {"name": name, "title": "KITTI 00", "figures": [["keyframe ATE", value]], "command": "python bench/x.py",
            "commit": commit, "measures": measures, "date": "2026-01-01", "machine": "m, 2 CPUs",
            "load_start": 0.1, "load_end": 0.2, "notes": ""}


def _pages(fig, results, stale):
    readme = f"intro\n{fig.BEGIN}\n{fig.render_key(results, stale)}\n{fig.END}\nrest\n"
    return readme, fig.render_results(results, stale)


@pytest.fixture()
def commits():
    head = _git("rev-parse", "--short=7", "HEAD")
    first = _git("rev-list", "--max-parents=0", "HEAD").splitlines()[-1][:7]
    return head, first


def test_a_changed_figure_or_an_unknown_commit_fails_the_check(tmp_path, commits):
    fig = _figures()
    head, _ = commits
    good = _result(head, ["bench/figures.py"])
    (tmp_path / "keyframe_ate.png").write_bytes(b"png")
    readme, page = _pages(fig, [good], {})
    assert fig.problems([good], readme, page, tmp_path, docs={}) == []
    # A figure edited on the page but not in the result file.
    assert any("RESULTS.md differs" in p for p in fig.problems([good], readme, page.replace("38.65", "30.65"), tmp_path, docs={}))
    # A result file the page does not show yet.
    other = _result(head, ["bench/figures.py"], "12.00 cm", name="other")
    assert any("RESULTS.md differs" in p for p in fig.problems([good, other], readme, page, tmp_path, docs={}))
    # A plot the page shows that is not there.
    assert any("keyframe_ate.png is missing" in p for p in fig.problems([good], readme, page, tmp_path / "none", docs={}))
    missing = _result("0000000", ["orbslam_hgcn"])
    readme, page = _pages(fig, [missing], {})
    found = fig.problems([missing], readme, page, tmp_path, docs={})
    assert len(found) == 1 and "not in this repository's history" in found[0]
    with pytest.raises(ValueError):
        fig.readme_block("no markers here")


def test_the_readme_key_lines_are_checked_too(tmp_path, commits):
    fig = _figures()
    head, _ = commits
    r = _result(head, ["bench/figures.py"], "words 4.3 ms CPU (0.94x orb), keyframe ATE 43.86 cm", name="words_in_system")
    r["figures"] = [["kmeans", r["figures"][0][1]]]
    (tmp_path / "keyframe_ate.png").write_bytes(b"png")
    readme, page = _pages(fig, [r], {})
    assert "words 4.3 ms CPU (0.94x orb)" in readme
    assert fig.problems([r], readme, page, tmp_path, docs={}) == []
    found = fig.problems([r], readme.replace("4.3 ms", "3.3 ms"), page, tmp_path, docs={})
    assert len(found) == 1 and "README" in found[0]


def test_a_figure_older_than_its_code_is_marked_and_is_no_failure(tmp_path, commits):
    fig = _figures()
    head, first = commits
    # Measured at the first commit: the package has changed since.
    stale = _result(first, ["orbslam_hgcn"], name="words_in_system")
    stale["figures"] = [["kmeans", "keyframe ATE 38.65 cm"]]
    found = fig.staleness([stale])
    assert list(found) == ["words_in_system"] and found["words_in_system"]
    (tmp_path / "keyframe_ate.png").write_bytes(b"png")
    marked_readme, marked_page = _pages(fig, [stale], found)
    plain_readme, plain_page = _pages(fig, [stale], {})
    mark = f"**code changed since {first}**"
    assert mark in marked_page and mark in marked_readme
    assert mark not in plain_page and mark not in plain_readme
    # The page written before the code changed (no mark) and the one written after both pass.
    assert fig.problems([stale], marked_readme, marked_page, tmp_path, docs={}) == []
    assert fig.problems([stale], plain_readme, plain_page, tmp_path, docs={}) == []
    assert fig.normalise(marked_page) == plain_page and fig.normalise(marked_readme) == plain_readme
    notes = fig.notices([stale])
    assert len(notes) == 1 and f"code changed since {first}" in notes[0]
    # The mark does not hide an edited figure.
    assert fig.problems([stale], marked_readme, marked_page.replace("38.65", "30.65"), tmp_path, docs={})
    # Measured at HEAD on files that have not changed since: current, no notice.
    assert fig.staleness([_result(head, ["bench/figures.py"])]) == {}


def test_check_exits_0_with_notices_and_1_on_a_difference(tmp_path):
    out = subprocess.run([sys.executable, str(REPO / "bench" / "figures.py"), "--check"], cwd=REPO, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert all(line.startswith("notice: ") for line in out.stdout.splitlines())


def test_tables_and_contrasts_are_parsed_into_rows():
    fig = _figures()
    assert fig._parts("3 runs: tracked 160-160 of 160 frames, keyframe ATE 43.86 cm, 28.6 frames/s (1.3x orb)") == [
        ("runs", "3"), ("tracked", "160-160 of 160 frames"), ("keyframe ATE", "43.86 cm"),
        ("frames/s", "28.6 frames/s (1.3x orb)")]
    assert fig.contrasts("B0-A0 +0.022 [+0.002, +0.043] 13/7 Holm p 1; orb-A0 -0.176 [-0.205, -0.145] 1/19 Holm p 0.0001") == [
        ("B0-A0", "+0.022", "+0.002", "+0.043", "13/7", "1"), ("orb-A0", "-0.176", "-0.205", "-0.145", "1/19", "0.0001")]
    assert fig.contrasts("A0 0.776, A1 0.775") is None
    r = _result("abc1234", ["orbslam_hgcn"], "B0-A0 +0.022 [+0.002, +0.043] 13/7 Holm p 1", name="tw")
    r["figures"] = [["8000 words, AP", "A0 0.776, B0 0.798"], ["8000 words, AP contrasts", r["figures"][0][1]]]
    page = fig.render_results([r], {})
    assert "| A0 | 0.776 |" in page and "| 8000 words, AP contrasts | B0-A0 | +0.022 | [+0.002, +0.043] | 13/7 | 1 |" in page
    assert "figures/tw_contrasts.png" in page


def test_plots_are_written(tmp_path):
    pytest.importorskip("matplotlib")
    fig = _figures()
    r = _result("abc1234", ["orbslam_hgcn"], "keyframe ATE 43.86 cm", name="a")
    c = _result("abc1234", ["orbslam_hgcn"], "B0-A0 +0.022 [+0.002, +0.043] 13/7 Holm p 1", name="b")
    written = fig.write_plots([r, c], tmp_path)
    assert sorted(p.name for p in written) == ["b_contrasts.png", "keyframe_ate.png"]
    assert all(p.read_bytes()[:4] == b"\x89PNG" and p.stat().st_size < 100_000 for p in written)


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


OFFICE_AP = "A0 0.748, A1 0.739, B0 0.753, B1 0.719, C 0.759, C-att 0.764, orb 0.554"
OFFICE_CONTRASTS = ("B0-A0 +0.005 [-0.013, +0.026] 8/12 Holm p 1; B1-A0 -0.029 [-0.051, -0.006] 6/14 Holm p 0.38; "
                    "C-att-A0 +0.016 [+0.000, +0.032] 14/6 Holm p 0.99")


def _words(commit: str = "abc1234") -> dict:
    r = _result(commit, ["bench/figures.py"], name="tw")
    r["figures"] = [["8000 words, AP", OFFICE_AP], ["8000 words, AP contrasts", OFFICE_CONTRASTS],
                    ["kitti", "3 runs: tracked 160-160 of 160 frames, resets 0, keyframe ATE 37.16 cm"],
                    ["peer", "tracked 160, 80 keyframes, CPU 60.0 ms/frame"]]
    return r


def test_the_part_rule_quotes_a_label_up_to_the_next_comma_or_semicolon_outside_brackets():
    fig = _figures()
    assert fig.quote(OFFICE_AP, "B0") == "0.753"
    assert fig.quote(OFFICE_AP, "C") == "0.759" and fig.quote(OFFICE_AP, "C-att") == "0.764"
    assert fig.quote(OFFICE_AP, "orb") == "0.554"
    assert fig.quote(OFFICE_CONTRASTS, "B0-A0") == "+0.005 [-0.013, +0.026] 8/12 Holm p 1"
    assert fig.quote(OFFICE_CONTRASTS, "C-att-A0") == "+0.016 [+0.000, +0.032] 14/6 Holm p 0.99"
    # "A0" inside "B0-A0" is no label; a label inside brackets is not one either.
    assert fig.quote(OFFICE_CONTRASTS, "A0") is None
    assert fig.quote("words 5.2 ms CPU (0.65x orb), insert step 7.7 ms", "orb") is None
    assert fig.quote("words 5.2 ms CPU (0.65x orb), insert step 7.7 ms", "insert step") == "7.7 ms"
    # After "LABEL: ", and a count before its label.
    assert fig.quote("3 runs: tracked 160-160 of 160 frames, resets 0", "tracked") == "160-160 of 160 frames"
    assert fig.quote("tracked 160, 80 keyframes, keyframe ATE 37.16 cm", "keyframes") == "80"
    assert fig.quote("tracked 160, 80 keyframes, keyframe ATE 37.16 cm", "keyframe ATE") == "37.16 cm"
    assert fig.quote("both counted: 1.20x (1.21x, 1.19x); CPU 1.48x", "both counted") == "1.20x (1.21x, 1.19x)"
    assert fig.quote("46.5 frames/s (1.13x orb), tracked 100.0%", "frames/s") == "(1.13x orb)"
    assert fig.quote(OFFICE_AP) == OFFICE_AP and fig.quote(OFFICE_AP, "D") is None


def _plots(folder: Path) -> Path:
    for name in ("keyframe_ate.png", "tw_contrasts.png"):
        (folder / name).write_bytes(b"png")
    return folder


def test_write_fills_the_quotes_and_the_check_reports_a_hand_edited_one(tmp_path, commits):
    fig = _figures()
    r = _words(commits[0])
    text = ("Offices (`tw`): B0 <!-- fig tw | 8000 words, AP | B0 -->0.798<!-- /fig --> against A0\n"
            "<!-- fig tw | 8000 words, AP | A0 --><!-- /fig -->; B0-A0 <!-- fig tw | 8000 words,\n"
            "  AP contrasts | B0-A0 -->+0.022<!-- /fig -->, all: <!-- fig tw | kitti -->x<!-- /fig -->,\n"
            "<!-- fig tw | kitti | tracked -->160<!-- /fig --> frames, <!-- fig tw | peer | keyframes -->?<!-- /fig -->.\n")
    filled, found = fig.quotes(text, [r], "docs/X.md")
    assert len(found) == 6 and all("(python bench/figures.py --write)" in f for f in found)
    assert found[0].startswith("docs/X.md:1: ") and "'0.798'" in found[0] and "'0.753'" in found[0]
    assert found[1].startswith("docs/X.md:2: ") and found[2].startswith("docs/X.md:2: ")
    # The filled text gives back the record's values and nothing else changes.
    assert "B0 <!-- fig tw | 8000 words, AP | B0 -->0.753<!-- /fig --> against A0" in filled
    assert "<!-- fig tw | 8000 words, AP | A0 -->0.748<!-- /fig -->" in filled
    assert "AP contrasts | B0-A0 -->+0.005 [-0.013, +0.026] 8/12 Holm p 1<!-- /fig -->" in filled
    assert f"<!-- fig tw | kitti -->{r['figures'][2][1]}<!-- /fig -->" in filled
    assert "<!-- fig tw | kitti | tracked -->160-160 of 160 frames<!-- /fig -->" in filled
    assert "<!-- fig tw | peer | keyframes -->80<!-- /fig -->" in filled
    assert fig.quotes(filled, [r], "docs/X.md") == (filled, [])
    # Through problems(): the filled page passes, a quote edited by hand is reported with its line.
    readme, page = _pages(fig, [r], {})
    assert fig.problems([r], readme, page, _plots(tmp_path), docs={"docs/X.md": filled}) == []
    edited = filled.replace("-->0.748<", "-->0.776<")
    found = fig.problems([r], readme, page, tmp_path, docs={"docs/X.md": edited})
    assert len(found) == 1 and found[0].startswith("docs/X.md:2: ") and "'0.776'" in found[0]
    # A reflowed quote (white space only) is no difference.
    reflowed = filled.replace("+0.005 [-0.013, +0.026]", "+0.005\n  [-0.013, +0.026]")
    assert fig.quotes(reflowed, [r], "d")[1] == []


def test_a_marker_naming_an_unknown_result_key_or_part_is_reported(tmp_path, commits):
    fig = _figures()
    r = _words(commits[0])
    for marker, why in (("<!-- fig nothing | 8000 words, AP | A0 -->0.748<!-- /fig -->", "no result file"),
                        ("<!-- fig tw | 9000 words, AP | A0 -->0.748<!-- /fig -->", "no figure '9000 words, AP'"),
                        ("<!-- fig tw | 8000 words, AP | D0 -->0.748<!-- /fig -->", "no part 'D0'"),
                        ("<!-- fig tw | 8000 words, AP contrasts | A0 -->x<!-- /fig -->", "no part 'A0'"),
                        ("<!-- fig tw -->0.748<!-- /fig -->", "is not 'NAME | KEY'"),
                        ("<!-- fig tw | 8000 words, AP | A0 -->0.748", "without its <!-- /fig -->")):
        text = f"line one\nthe figure {marker} here\n"
        filled, found = fig.quotes(text, [r], "docs/Y.md")
        assert len(found) == 1 and found[0].startswith("docs/Y.md:2: ") and why in found[0], (marker, found)
        assert filled == text  # nothing to fill it with
        readme, page = _pages(fig, [r], {})
        assert fig.problems([r], readme, page, _plots(tmp_path), docs={"docs/Y.md": text}) == found


def test_the_docs_markers_are_read_from_every_docs_page_but_results():
    fig = _figures()
    pages = fig.doc_pages()
    assert "docs/BENCHMARKS.md" in pages and "docs/RESULTS.md" not in pages
    # The pages quote recorded figures through markers, and every one of them holds.
    results = fig.load_results()
    marked = [p for p, text in pages.items() if "<!-- fig " in text]
    assert "docs/BENCHMARKS.md" in marked and "docs/VOCABULARIES.md" in marked
    assert all(fig.quotes(pages[p], results, p)[1] == [] for p in marked)


def _peer(runs: int) -> dict:
    r = _result("abc1234", ["orbslam_hgcn"], name="peer")
    run = ("orbslam-hgcn tracked 160, 80 keyframes, keyframe ATE 37.16 cm, camera ATE 36.71 cm, 28.44 frames/s, start "
           "0.39 s, shutdown 0.04 s, CPU 59.3 ms/frame; ORB-SLAM3 tracked 127, 25 keyframes, keyframe ATE 25.35 cm, "
           "camera ATE 29.73 cm, 45.24 frames/s, start 3.75 s, shutdown 0.00 s, CPU 31.4 ms/frame; comparison void: "
           "ORB-SLAM3 tracked 127 of 160 frames (under 95% of 160); no ratio; " + "x" * 500)
    r["figures"] = [["vocabulary", "orb"], *[[f"run {i + 1}", run] for i in range(runs)]]
    r["command"] = "python bench/bench_peer.py --sequence /tmp/jpeg_office --json /tmp/rec/a.json --record peer"
    return r


def test_results_page_lines_stay_short_and_temporary_folders_are_noted():
    fig = _figures()
    page = (REPO / "docs" / "RESULTS.md").read_text()
    long = [(i + 1, len(line)) for i, line in enumerate(page.splitlines()) if len(line) > fig.MAX_LINE]
    assert long == [], f"docs/RESULTS.md lines over {fig.MAX_LINE} characters (line, length): {long}"
    r = _peer(10)
    made = fig.render_results([r], {})
    assert max(len(line) for line in made.splitlines()) <= fig.MAX_LINE
    assert "| run 1 | orbslam-hgcn tracked 160, 80 keyframes" in made
    assert "|  | ORB-SLAM3 tracked 127, 25 keyframes" in made and "|  | no ratio; |" in made
    # The command as recorded, then a note on its /tmp folders.
    assert f"| command | `{r['command']}` |" in made
    assert "| note | `/tmp/jpeg_office`, `/tmp/rec`: temporary folders" in made
    assert "| note |" not in fig.render_results([_result("abc1234", ["orbslam_hgcn"])], {})
    # A few figures stay one column each.
    assert "| | vocabulary | run 1 |" in fig.render_results([_peer(1)], {})
