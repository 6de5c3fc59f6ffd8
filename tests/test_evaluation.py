"""ATE/RPE evaluation: known Sim(3) moves and noise, association, reports, plots, the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from orbslam_hgcn.cli import main
from orbslam_hgcn.errors import OrbslamError
from orbslam_hgcn.evaluation.ate import EvaluationError, evaluate
from orbslam_hgcn.evaluation.plots import axis_label, box_plot, principal_axes
from orbslam_hgcn.evaluation.report import read_report, write_report
from orbslam_hgcn.geometry.se3 import inv_S
from orbslam_hgcn.trajectory import Trajectory, read_tum, write_tum

SCALE = 0.37  # estimate = SCALE * R0 * ground truth + t0 (a monocular run's arbitrary frame)
R0 = Rotation.from_rotvec([0.4, -0.9, 0.3]).as_matrix()
T0 = np.array([1.5, -0.7, 2.2])
SIGMA = 0.01  # metres per axis, in the ground-truth frame


def make_gt(n: int = 200, t0: float = 1000.0, rate: float = 30.0) -> Trajectory:
    """A smooth closed 3D curve (about 4 x 3 x 0.6 m) with the camera turning along it."""
    a = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    pos = np.stack([2.0 * np.cos(a), 1.5 * np.sin(2.0 * a), 1.0 + 0.3 * np.sin(3.0 * a)], axis=1)
    rot = Rotation.from_euler("zyx", np.stack([a, 0.2 * np.sin(2 * a), 0.1 * np.cos(a)], 1))
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = rot.as_matrix()
    poses[:, :3, 3] = pos
    return Trajectory(t0 + np.arange(n) / rate, poses)


def move(traj: Trajectory, s: float, R: np.ndarray, t: np.ndarray, noise: np.ndarray | None = None) -> Trajectory:
    """Apply S = [[s R, t], [0, 1]] to every T_wc (positions first perturbed by ``noise``)."""
    poses = traj.poses.copy()
    p = poses[:, :3, 3] + (0.0 if noise is None else noise)
    poses[:, :3, 3] = s * p @ R.T + t
    poses[:, :3, :3] = R @ poses[:, :3, :3]
    return Trajectory(traj.timestamps.copy(), poses)


def independent_alignment(x: np.ndarray, y: np.ndarray, with_scale: bool) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) with y ~ s R x + t, from scipy's Kabsch rotation (not evo's Umeyama code)."""
    xc, yc = x - x.mean(0), y - y.mean(0)
    rot, _ = Rotation.align_vectors(yc, xc)
    R = rot.as_matrix()
    s = float(np.sum(yc * (xc @ R.T)) / np.sum(xc**2)) if with_scale else 1.0
    return s, R, y.mean(0) - s * R @ x.mean(0)


@pytest.fixture
def gt() -> Trajectory:
    return make_gt()


@pytest.fixture
def noise(gt) -> np.ndarray:
    return np.random.default_rng(7).normal(0.0, SIGMA, size=(len(gt), 3))


def test_sim3_noise_free_recovers_the_inverse_similarity(gt):
    est = move(gt, SCALE, R0, T0)
    r = evaluate(gt, est)
    assert r.num_pairs == len(gt)
    # The alignment maps the estimate onto the ground truth: the inverse of the applied move.
    assert r.scale == pytest.approx(1.0 / SCALE, rel=1e-9)
    S_true = np.eye(4)
    S_true[:3, :3], S_true[:3, 3] = SCALE * R0, T0
    np.testing.assert_allclose(r.S_gt_est, inv_S(S_true), atol=1e-9)
    assert r.ate.rmse < 1e-6 and r.ate.max < 1e-6
    np.testing.assert_allclose(r.est_aligned.poses, gt.poses, atol=1e-9)
    assert r.rpe_trans.rmse < 1e-6 and r.rpe_rot_deg.rmse < 1e-6
    assert len(r.rpe_trans_errors) == len(gt) - 1


def test_sim3_with_noise_matches_expected_rmse_and_an_independent_alignment(gt, noise):
    est = move(gt, SCALE, R0, T0, noise)
    r = evaluate(gt, est, align="sim3")
    # Residual after a 7-dof fit of 200 points is the noise itself: E|n|^2 = 3 sigma^2.
    assert r.ate.rmse == pytest.approx(np.sqrt(3) * SIGMA, rel=0.15)
    assert r.scale == pytest.approx(1.0 / SCALE, rel=0.01)
    # Same alignment and errors computed without evo.
    s, R, t = independent_alignment(est.positions, gt.positions, with_scale=True)
    err = np.linalg.norm(gt.positions - (s * est.positions @ R.T + t), axis=1)
    assert r.scale == pytest.approx(s, rel=1e-6)
    np.testing.assert_allclose(r.ate_errors, err, atol=1e-6)
    assert r.ate.rmse == pytest.approx(np.sqrt(np.mean(err**2)), abs=1e-6)
    assert r.ate.median == pytest.approx(np.median(err), abs=1e-9)
    assert r.ate.max == pytest.approx(err.max(), abs=1e-9)
    # RPE over one frame: translation error |n_j - n_i| has E = 6 sigma^2; the relative
    # rotations are untouched by position noise and by any common rotation.
    assert r.rpe_trans.rmse == pytest.approx(np.sqrt(6) * SIGMA, rel=0.15)
    assert r.rpe_rot_deg.max < 1e-6


def test_rpe_in_metres_pairs_poses_by_ground_truth_path_length(gt, noise):
    est = move(gt, SCALE, R0, T0, noise)
    r = evaluate(gt, est, delta=1.0, delta_unit="meters")
    assert r.rpe_trans.rmse == pytest.approx(np.sqrt(6) * SIGMA, rel=0.2)
    # Each pair ends at the first pose where 1 m of ground-truth path has been covered since
    # the previous pair ended: at least 1 m, overshooting by less than one frame's motion.
    step = np.linalg.norm(np.diff(gt.positions, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(step)])
    covered = np.diff(cum[np.concatenate([[0], r.rpe_ids])])
    assert len(covered) > (cum[-1] - 1.0) / (1.0 + step.max())  # less than 1 m left over
    assert np.all(covered >= 1.0) and np.all(covered < 1.0 + step.max())


def test_se3_alignment_of_a_scaled_trajectory_leaves_a_large_error(gt):
    est = move(gt, SCALE, R0, T0)
    r = evaluate(gt, est, align="se3")
    assert r.scale == 1.0
    s, R, t = independent_alignment(est.positions, gt.positions, with_scale=False)
    err = np.linalg.norm(gt.positions - (est.positions @ R.T + t), axis=1)
    assert r.ate.rmse == pytest.approx(np.sqrt(np.mean(err**2)), abs=1e-6)
    np.testing.assert_allclose(r.S_gt_est[:3, :3], R, atol=1e-6)
    assert r.ate.rmse > 0.5  # 63 % of a ~2 m radius curve is missing
    assert evaluate(gt, est, align="sim3").ate.rmse < 1e-6


def test_no_alignment_reports_the_raw_offset(gt):
    d = np.array([0.1, -0.2, 0.05])
    est = move(gt, 1.0, np.eye(3), d)
    r = evaluate(gt, est, align="none")
    np.testing.assert_allclose(r.ate_errors, np.linalg.norm(d), atol=1e-12)
    np.testing.assert_array_equal(r.S_gt_est, np.eye(4))
    assert r.rpe_trans.max < 1e-9  # a constant offset does not change relative motion
    # A rigid move is undone by se3 alignment.
    assert evaluate(gt, move(gt, 1.0, R0, T0), align="se3").ate.rmse < 1e-6


def test_association_with_time_jitter_missing_poses_and_extra_poses(gt):
    rng = np.random.default_rng(3)
    keep = np.array([i for i in range(20, 180) if i % 4 != 0])
    est_full = move(gt, SCALE, R0, T0)
    stamps = gt.timestamps[keep] + rng.uniform(-0.012, 0.012, size=len(keep))  # frames 33 ms apart
    extra_t = gt.timestamps[-1] + 1.0 + np.arange(5) * 0.1  # after the ground truth ends
    est = Trajectory(
        np.concatenate([stamps, extra_t]),
        np.concatenate([est_full.poses[keep], np.tile(np.eye(4), (5, 1, 1))]),
    )
    r = evaluate(gt, est, max_diff=0.02)
    assert r.num_pairs == len(keep)
    np.testing.assert_array_equal(r.gt.timestamps, gt.timestamps[keep])
    np.testing.assert_array_equal(r.est_aligned.timestamps, stamps)
    assert r.ate.rmse < 1e-6  # a pose paired with a neighbour would be centimetres off
    assert r.scale == pytest.approx(1.0 / SCALE, rel=1e-9)
    # gt_span covers the associated time range at the ground truth's own rate.
    assert r.gt_span.timestamps[0] == gt.timestamps[keep[0]]
    assert r.gt_span.timestamps[-1] == gt.timestamps[keep[-1]]


def test_clock_offset_fails_without_and_works_with_time_offset(gt):
    est = move(gt, SCALE, R0, T0)
    est = Trajectory(est.timestamps + 5000.0, est.poses)
    with pytest.raises(OrbslamError) as info:
        evaluate(gt, est, gt_name="gt.txt", est_name="est.txt")
    msg = str(info.value)
    assert "0 pose pair" in msg
    assert "gt.txt covers t 1000.000 .. 1006.633 s, 200 poses" in msg
    assert "est.txt covers t 6000.000 .. 6006.633 s" in msg
    assert evaluate(gt, est, t_offset=-5000.0).ate.rmse < 1e-6


def test_fewer_than_three_pairs_is_an_error(gt):
    est = Trajectory(gt.timestamps[[10, 11]], gt.poses[[10, 11]])
    with pytest.raises(EvaluationError, match="only 2 pose pair"):
        evaluate(gt, est)
    with pytest.raises(EvaluationError, match="no poses"):
        evaluate(gt, Trajectory(np.zeros(0), np.zeros((0, 4, 4))))


def test_collinear_positions_cannot_be_aligned():
    n = 50
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.linspace(0.0, 3.0, n)
    line = Trajectory(np.arange(n) * 0.1, poses)
    with pytest.raises(EvaluationError, match="collinear"):
        evaluate(line, line, align="se3")


def test_bad_arguments_are_errors(gt):
    with pytest.raises(EvaluationError, match="alignment"):
        evaluate(gt, gt, align="sim2")
    with pytest.raises(EvaluationError, match="whole"):
        evaluate(gt, gt, delta=1.5, delta_unit="frames")
    with pytest.raises(EvaluationError, match="smaller delta"):
        evaluate(gt, gt, delta=500)


def test_report_json_round_trip_and_pngs(gt, noise, tmp_path):
    r = evaluate(gt, move(gt, SCALE, R0, T0, noise), gt_name="gt.txt", est_name="est.txt")
    paths = write_report(r, tmp_path / "out")
    data = read_report(paths["json"])
    assert data == json.loads(paths["json"].read_text())
    assert data["ate_m"] == r.ate.to_dict()
    assert data["ate_m"]["rmse"] == r.ate.rmse
    assert data["scale"] == r.scale
    assert data["num_pairs"] == 200 and data["align"] == "sim3"
    np.testing.assert_array_equal(np.array(data["S_gt_est"]), r.S_gt_est)
    assert data["rpe"]["trans_m"] == r.rpe_trans.to_dict()
    assert data["rpe"]["rot_deg"]["rmse"] == r.rpe_rot_deg.rmse
    np.testing.assert_array_equal(data["per_pose"]["ate_m"], r.ate_errors)
    assert data["gt"] == "gt.txt" and data["est"] == "est.txt"
    for key in ("top", "over_time"):
        assert paths[key].stat().st_size > 15_000
        with Image.open(paths[key]) as im:
            assert im.format == "PNG" and im.width >= 600 and im.height >= 350
            px = np.asarray(im.convert("L"), dtype=np.float64)
        assert px.std() > 10.0  # drawn content, not a blank canvas
    assert set(write_report(r, tmp_path / "np", plot=False)) == {"json"}
    assert sorted(p.name for p in (tmp_path / "np").iterdir()) == ["ate.json"]


def test_read_report_rejects_bad_files(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{\n  \"ate_m\": \n")
    with pytest.raises(OrbslamError, match="bad.json:"):
        read_report(bad)
    with pytest.raises(OrbslamError, match="not found"):
        read_report(tmp_path / "missing.json")


def test_box_plot_writes_an_image(tmp_path):
    path = box_plot({"ORB": [0.031, 0.042, 0.038], "HGCN": [0.027, 0.030, 0.036, 0.029]},
                    tmp_path / "box.png", ylabel="ATE RMSE [m]")
    with Image.open(path) as im:
        assert im.format == "PNG" and im.width > 300
        assert np.asarray(im.convert("L"), dtype=np.float64).std() > 10.0


def test_box_plot_axis_starts_at_zero_and_one_run_says_it_cannot_rank(tmp_path, monkeypatch):
    """1.79 mm against 1.91 mm, one run each (the demo's case): the axis starts at zero, and
    the plot says that one value per group shows no spread; with several runs, no such note."""
    import orbslam_hgcn.evaluation.plots as plots

    figs = []
    save = plots._save
    monkeypatch.setattr(plots, "_save", lambda fig, path: (figs.append(fig), save(fig, path))[1])
    box_plot({"hgcn": [1.79], "orb": [1.91]}, tmp_path / "one.png", ylabel="mm")
    box_plot({"hgcn": [1.79, 1.85], "orb": [1.91, 1.88]}, tmp_path / "two.png", ylabel="mm")
    (one,), (two,) = (f.axes for f in figs)
    for ax in (one, two):
        low, high = ax.get_ylim()
        assert low == 0.0 and 1.91 < high < 2.2
    assert any("cannot rank" in t.get_text() for t in one.texts)
    assert not any("cannot rank" in t.get_text() for t in two.texts)


def test_principal_axes_pick_the_plane_of_largest_extent():
    t = np.linspace(0, 2 * np.pi, 100)
    pts = np.stack([3.0 * np.cos(t), 0.05 * np.sin(5 * t), -1.0 * np.sin(t)], axis=1)
    axes = principal_axes(pts)
    np.testing.assert_allclose(np.abs(axes), [[1, 0, 0], [0, 0, 1]], atol=1e-3)
    assert [axis_label(a) for a in axes] == ["x", "z"]
    assert axis_label(np.array([0.6, 0.8, 0.0])) == "(0.60, 0.80, 0.00)"


def test_cli_eval_end_to_end(gt, noise, tmp_path, capsys):
    gt_file, est_file = tmp_path / "gt.txt", tmp_path / "run" / "est.txt"
    write_tum(gt_file, gt)
    write_tum(est_file, move(gt, SCALE, R0, T0, noise))
    assert main(["eval", "--gt", str(gt_file), "--est", str(est_file)]) == 0
    out = capsys.readouterr().out
    assert "ATE RMSE" in out and "scale 2.7" in out and "RPE rot RMSE" in out
    # Default output folder: the estimate's.
    data = json.loads((est_file.parent / "ate.json").read_text())
    assert (est_file.parent / "ate.png").is_file() and (est_file.parent / "ate_over_time.png").is_file()
    expected = evaluate(read_tum(gt_file), read_tum(est_file))
    assert data["ate_m"]["rmse"] == pytest.approx(expected.ate.rmse, abs=1e-12)
    assert data["ate_m"]["rmse"] == pytest.approx(np.sqrt(3) * SIGMA, rel=0.15)
    assert data["scale"] == pytest.approx(1.0 / SCALE, rel=0.01)

    out_dir = tmp_path / "se3"
    rc = main(["eval", "--gt", str(gt_file), "--est", str(est_file), "--align", "se3",
               "--max-diff", "0.01", "--out", str(out_dir), "--no-plot"])
    assert rc == 0
    assert sorted(p.name for p in out_dir.iterdir()) == ["ate.json"]
    assert json.loads((out_dir / "ate.json").read_text())["ate_m"]["rmse"] > 0.5


def test_cli_eval_user_errors_exit_2(gt, tmp_path, capsys):
    gt_file = tmp_path / "gt.txt"
    write_tum(gt_file, gt)
    missing = tmp_path / "nope.txt"
    assert main(["eval", "--gt", str(gt_file), "--est", str(missing)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(missing) in err and "not found" in err

    bad = tmp_path / "bad.txt"
    bad.write_text("# t x y z qx qy qz qw\n1000.0 0 0 0 0 0 0 1\n1000.1 0 0 zero 0 0 0 1\n")
    assert main(["eval", "--gt", str(gt_file), "--est", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{bad}:3" in err

    far = tmp_path / "far.txt"
    write_tum(far, Trajectory(gt.timestamps + 100.0, gt.poses))
    assert main(["eval", "--gt", str(gt_file), "--est", str(far), "--no-plot"]) == 2
    err = capsys.readouterr().err.strip()
    assert "0 pose pair" in err and "1100.000" in err
