"""The sweep command: manifest checks naming the line, the same table with Ray (a local
instance) and without, the table equal to the run commands made one by one, resuming after
an interruption, and a killed run retried once, then recorded as failed."""

import json
import logging
import sys
import textwrap

import pytest
import ray
import yaml

from orbslam_hgcn.cli import main
from orbslam_hgcn.app import processes, sweep
from orbslam_hgcn.app.demo import demo_sequence


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    """Two short renders of the demo's loop (30 and 20 frames)."""
    root = tmp_path_factory.mktemp("sweep_cache")
    return demo_sequence(root, 30, progress=False), demo_sequence(root, 20, progress=False)


@pytest.fixture(scope="module")
def ray_local():
    """A local Ray instance for the module (the sweeps use it and leave it running)."""
    ray.init(num_cpus=2, include_dashboard=False, logging_level=logging.WARNING, log_to_driver=False)
    yield
    ray.shutdown()


# A stand-in for ``orbslam-hgcn run``: writes a stats.json whose ATE depends on the
# vocabulary, logs each start to starts.log beside the output folder (named out), and
# kills itself (SIGKILL) on every attempt for a sequence folder named "bad", on the first
# only for one named "flaky".
FAKE_RUN = textwrap.dedent("""\
    import json, os, signal, sys  # noqa: E401
    from pathlib import Path
    argv = sys.argv[1:]
    out = Path(argv[argv.index("--out") + 1])
    vocab = argv[argv.index("--vocab") + 1]
    log = next(p for p in out.parents if p.name == "out").parent / "starts.log"
    starts = log.read_text().splitlines() if log.exists() else []
    with open(log, "a") as f:
        f.write(str(out) + "\\n")
    seq = Path(argv[1]).name
    if seq == "bad" or (seq == "flaky" and str(out) not in starts):
        os.kill(os.getpid(), signal.SIGKILL)
    out.mkdir(parents=True, exist_ok=True)
    stats = {"complete": True, "frames": {"frames": 10, "tracked": 10, "lost": 0, "dropped": 0},
             "map_resets": 0, "wall_s": 1.0, "ate_sim3": {"keyframes": {"rmse_m": 0.001 * len(vocab)}},
             "loop_closing": {"loops": []}}
    (out / "stats.json").write_text(json.dumps(stats))
""")


@pytest.fixture
def fake_run(tmp_path, monkeypatch):
    """RUN_PROGRAM replaced by FAKE_RUN; returns the file listing each process started."""
    script = tmp_path / "fake_run.py"
    script.write_text(FAKE_RUN)
    monkeypatch.setattr(processes, "RUN_PROGRAM", [sys.executable, str(script)])
    return tmp_path / "starts.log"  # the sweeps write into tmp_path / "out"


def _write(path, text):
    path.write_text(textwrap.dedent(text))
    return path


def _comparable(sw_json, root):
    """The sweep's records without the timings (fps, wall time), with its output folder
    ``root`` written OUT in the run commands."""
    cells = [{k: v for k, v in c.items() if k != "fps"} for c in sw_json["cells"]]
    runs = [{k: v.replace(str(root), "OUT") if k == "command" else v for k, v in r.items()
             if k not in ("fps", "wall_s")} for r in sw_json["runs"]]
    return cells, runs


def _without_fps(md):
    """The Markdown tables with their fps column removed."""
    rows = []
    for ln in md.splitlines():
        if ln.startswith("| sequence |"):
            fps_col = [c.strip() for c in ln.strip("|").split("|")].index(
                next(c.strip() for c in ln.strip("|").split("|") if c.strip().startswith("fps")))
        if ln.startswith("|"):
            cells = [c.strip() for c in ln.strip("|").split("|")]
            rows.append(cells[:fps_col] + cells[fps_col + 1:])
        else:
            rows.append(ln)
    return rows


def test_manifest_errors_name_the_line(tmp_path, capsys):
    seq = tmp_path / "seq"
    seq.mkdir()
    cases = {
        "missing path": (f"""\
            sequences:
              - {{name: a, path: {seq}}}
              - {{name: b, path: no_such_folder}}
            vocabularies: [orb]
            """, 3, "sequence path not found"),
        "unknown vocabulary": (f"""\
            sequences:
              - {{name: a, path: {seq}}}
            vocabularies:
              - orb
              - no_such_vocabulary
            """, 5, "unknown vocabulary 'no_such_vocabulary'"),
        "bad override key": (f"""\
            sequences: [{{name: a, path: {seq}}}]
            vocabularies: [orb]
            overrides:
              orb.n_features: 800
              tracking.no_such_key: 3
            """, 5, "override 'tracking.no_such_key': unknown key"),
        "bad override section": (f"""\
            sequences: [{{name: a, path: {seq}}}]
            overrides: {{nosuch.key: 1}}
            """, 2, "override 'nosuch.key': expected section.key"),
        "bad override value": (f"""\
            sequences: [{{name: a, path: {seq}}}]
            params:
              - name: few
                overrides: {{orb.n_features: many}}
            """, 4, "override 'orb.n_features': expected int"),
    }
    for name, (text, line, message) in cases.items():
        m = _write(tmp_path / f"{name.replace(' ', '_')}.yaml", text)
        assert main(["sweep", str(m), "--out", str(tmp_path / "out"), "--no-ray"]) == 2, name
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"orbslam-hgcn sweep: error: {m}:{line}: "), (name, err)
        assert message in err[0], (name, err)
    assert not (tmp_path / "out").exists()  # nothing ran


def test_sweep_with_and_without_ray_and_run_by_run_give_the_same_table(renders, tmp_path, ray_local):
    a, b = renders
    m = _write(tmp_path / "sweep.yaml", f"""\
        sequences:
          - {{name: a, path: {a}, kind: tum}}
          - {{name: b, path: {b}}}
        vocabularies: [orb, hgcn]
        runs: 1
        sequential: true
        """)
    plain = sweep.run_sweep(m, tmp_path / "plain", use_ray=False, progress=False)
    on_ray = sweep.run_sweep(m, tmp_path / "ray", jobs=2, progress=False)
    assert plain.engine == "in order (no Ray)" and on_ray.engine.startswith("local Ray")
    assert len(plain.runs) == 4 and all(r.outcome.counts and r.attempts == 1 for r in plain.runs)
    j_plain = json.loads((tmp_path / "plain" / "sweep.json").read_text())
    j_ray = json.loads((tmp_path / "ray" / "sweep.json").read_text())
    assert _comparable(j_plain, tmp_path / "plain") == _comparable(j_ray, tmp_path / "ray")
    assert _without_fps((tmp_path / "plain" / "sweep.md").read_text()) == \
        _without_fps((tmp_path / "ray" / "sweep.md").read_text())
    for name in ("sweep_ate_a.png", "sweep_ate_b.png"):
        assert (tmp_path / "ray" / name).stat().st_size > 0
    # Every figure is the run's own stats.json, and the same run made on its own (the
    # command recorded, in this process) gives the same trajectory and ATE.
    for cell in j_plain["cells"]:
        stats = json.loads((tmp_path / "plain" / cell["sequence"] / cell["vocabulary"] / "default" / "run1" /
                            "stats.json").read_text())
        assert cell["ate_median_m"] == stats["ate_sim3"]["keyframes"]["rmse_m"] and cell["runs_ok"] == 1
        assert cell["tracked_share"] == stats["frames"]["tracked"] / stats["frames"]["frames"]
    first = j_plain["runs"][0]
    argv = first["command"].split()[1:]
    alone = tmp_path / "alone"
    argv[argv.index("--out") + 1] = str(alone)
    assert main(argv) == 0
    ours = json.loads((alone / "stats.json").read_text())["ate_sim3"]["keyframes"]["rmse_m"]
    assert ours == first["ate_rmse_m"]
    kf = "KeyFrameTrajectory.txt"
    assert (alone / kf).read_text() == (tmp_path / "plain" / first["out"] / kf).read_text()
    assert (tmp_path / "ray" / first["out"] / kf).read_text() == (alone / kf).read_text()


def test_resume_runs_only_the_missing_runs(tmp_path, fake_run, capsys):
    for s in ("s1", "s2"):
        (tmp_path / s).mkdir()
    m = _write(tmp_path / "sweep.yaml", f"""\
        sequences: [{{name: s1, path: {tmp_path / 's1'}}}, {{name: s2, path: {tmp_path / 's2'}}}]
        vocabularies: [orb, hgcn]
        runs: 2
        overrides: {{orb.n_features: 500}}
        """)
    out = tmp_path / "out"
    seen = []

    def stop_after_three(rec):
        seen.append(rec)
        if len(seen) == 3:
            raise KeyboardInterrupt

    first = sweep.run_sweep(m, out, use_ray=False, progress=False, on_run=stop_after_three)
    assert first.interrupted and len(first.runs) == 3 and len(first.executed) == 3
    assert json.loads((out / "sweep.json").read_text())["interrupted"] is True
    config = out / "s1" / "orb" / "default" / "config.yaml"
    assert yaml.safe_load(config.read_text()) == {"orb": {"n_features": 500}}
    assert f"--config {config}" in first.runs[0].command
    assert len(fake_run.read_text().splitlines()) == 3
    code = main(["sweep", str(m), "--out", str(out), "--no-ray", "--no-progress"])
    assert code == 0
    started = fake_run.read_text().splitlines()
    assert len(started) == 8 and len(set(started)) == 8  # each run made once: 3 before, 5 now
    data = json.loads((out / "sweep.json").read_text())
    assert data["interrupted"] is False and len(data["runs"]) == 8
    assert [r["attempts"] for r in data["runs"]].count(0) == 3  # read back, not run again
    assert [(c["sequence"], c["vocabulary"], c["runs_ok"]) for c in data["cells"]] == [
        ("s1", "orb", 2), ("s1", "hgcn", 2), ("s2", "orb", 2), ("s2", "hgcn", 2)]
    assert data["cells"][0]["ate_median_m"] == pytest.approx(0.003)
    assert "| s2 | hgcn | default | 2/2 | 4.00 | 4.00 | 4.00 | 100.0% | 0 |" in capsys.readouterr().out


def test_a_killed_run_is_retried_once_then_recorded_as_failed(tmp_path, fake_run, ray_local, capsys):
    for s in ("good", "flaky", "bad"):
        (tmp_path / s).mkdir()
    m = _write(tmp_path / "sweep.yaml", f"""\
        sequences:
          - {{name: good, path: {tmp_path / 'good'}}}
          - {{name: flaky, path: {tmp_path / 'flaky'}}}
          - {{name: bad, path: {tmp_path / 'bad'}}}
        vocabularies: [orb]
        runs: 1
        """)
    code = main(["sweep", str(m), "--out", str(tmp_path / "out"), "--jobs", "2", "--no-progress"])
    assert code == 1  # one run failed, the others went on
    data = json.loads((tmp_path / "out" / "sweep.json").read_text())
    assert data["engine"].startswith("local Ray")
    runs = {r["out"].split("/")[0]: r for r in data["runs"]}
    assert runs["good"]["ok"] and runs["good"]["attempts"] == 1
    assert runs["flaky"]["ok"] and runs["flaky"]["attempts"] == 2  # killed once, then ran
    bad = runs["bad"]
    assert not bad["ok"] and bad["attempts"] == 2 and "killed (SIGKILL, then SIGKILL)" in bad["error"]
    cells = {c["sequence"]: c for c in data["cells"]}
    assert cells["bad"]["failed_runs"] == 1 and cells["bad"]["ate_median_m"] is None
    assert cells["good"]["failed_runs"] == 0 and cells["good"]["ate_median_m"] == pytest.approx(0.003)
    printed = capsys.readouterr().out
    assert "| bad | orb | default | 1 | n/a | n/a | n/a | n/a | n/a | X failed: run process killed" in printed
    assert sum(1 for ln in fake_run.read_text().splitlines() if "/bad/" in ln) == 2


def test_vocab_train_extracts_in_shards_on_ray_and_trains_on_the_device_asked(renders, tmp_path, ray_local,
                                                                             monkeypatch):
    """Descriptor extraction in shards on Ray gives the descriptors extracted in order;
    HGCN training with --device cpu and auto gives the same vocabulary here (no GPU: auto
    is the CPU; with one, auto trains on it)."""
    import numpy as np
    import torch

    from orbslam_hgcn.cli import build_parser
    from orbslam_hgcn.config import HgcnTrainConfig
    from orbslam_hgcn.errors import ConfigError
    from orbslam_hgcn.engine import Engine
    from orbslam_hgcn.vocabulary.training import train
    from orbslam_hgcn.vocabulary.training.hgcn import training_device

    sources = [train.open_image_source(renders[1])]
    pairs = train.select_images(sources, 6)
    in_order = train.extract_descriptors(sources, pairs, 300, None, progress=False)
    monkeypatch.setattr(train, "CACHE_EVERY", 2)  # three shards of two images
    cache = tmp_path / "cache.npz"
    with Engine(jobs=2) as engine:
        sharded = train.extract_descriptors(sources, pairs, 300, cache, progress=False, images=[renders[1]],
                                            engine=engine)
    for name in ("desc", "uv", "image_ids", "groups"):
        assert np.array_equal(getattr(in_order, name), getattr(sharded, name)), name
    assert cache.is_file()

    args = build_parser().parse_args(["vocab", "train", "--kind", "hgcn", "--images", "x", "--out", "v.npz"])
    assert (args.device, args.jobs, args.address) == ("auto", 1, None)
    cfg = HgcnTrainConfig(epochs=4, hidden_dim=16, n_coarse=8)
    vocabs = {}
    for device in ("cpu", "auto"):
        v = train.train_vocabulary("hgcn", in_order.desc, in_order.image_ids, words=30, hgcn=cfg, device=device,
                                   progress=False)
        v.save(tmp_path / f"{device}.npz")
        vocabs[device] = (v, np.load(tmp_path / f"{device}.npz"))
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert vocabs["cpu"][0].metadata.stats["hgcn_device"] == "cpu"
    assert vocabs["auto"][0].metadata.stats["hgcn_device"] == expected
    if expected == "cpu":
        a, b = vocabs["cpu"][1], vocabs["auto"][1]
        assert sorted(a.files) == sorted(b.files)
        for k in a.files:
            if k != "_metadata":
                assert np.array_equal(a[k], b[k]), k
    with pytest.raises(ConfigError, match="--device"):
        training_device("no_such_device")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="sees no CUDA GPU"):
            training_device("cuda")


def test_compare_with_jobs_is_a_one_sequence_sweep(tmp_path, fake_run, ray_local, capsys):
    seq = tmp_path / "flaky"
    seq.mkdir()
    out = tmp_path / "out"
    code = main(["compare", str(seq), "--dataset", "tum", "--runs", "2", "--vocabs", "orb", "hgcn", "--out", str(out),
                 "--jobs", "2", "--no-progress"])  # an empty folder: the fake run reads nothing
    assert code == 0
    data = json.loads((out / "compare.json").read_text())
    assert [(r["vocab"], r["run"], r["ok"]) for r in data["runs"]] == [
        ("orb", 1, True), ("orb", 2, True), ("hgcn", 1, True), ("hgcn", 2, True)]
    assert data["summary"]["hgcn"]["ate_rmse_m"]["median"] == pytest.approx(0.004)
    assert (out / "orb" / "run2" / "stats.json").is_file() and (out / "compare_ate.png").is_file()
    assert len(fake_run.read_text().splitlines()) == 8  # every run killed once, then made again
    assert "| hgcn | 2/2 | 4.00 | 4.00 | 4.00 |" in capsys.readouterr().out
