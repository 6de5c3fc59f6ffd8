"""The track-words ablation bench's arithmetic on hand-made inputs with known answers:
Holm's adjustment, the paired contrast, the per-sequence scores, the causal track members,
ORB-SLAM's distinctive descriptor, the track-mean words and the mechanism figures."""

import math
from pathlib import Path

import numpy as np
import pytest
from conftest import load_bench, real_photo_folder

from orbslam_hgcn.vocabulary.bow import BowVector


@pytest.fixture(scope="module")
def tw():
    return load_bench("bench_track_words")


def test_holm_steps_down_monotone_and_caps(tw):
    # sorted 0.01 x4 = 0.04, 0.03 x3 = 0.09, 0.04 x2 = 0.08 -> 0.09 (monotone), 0.5 x1 = 0.5
    assert tw.holm([0.01, 0.04, 0.03, 0.5]) == pytest.approx([0.04, 0.09, 0.09, 0.5])
    assert tw.holm([0.3, 0.6]) == pytest.approx([0.6, 0.6])
    assert tw.holm([0.4, 0.9, 0.8]) == pytest.approx([1.0, 1.0, 1.0])


def test_contrast_mean_ci_and_exact_wilcoxon(tw):
    rng = np.random.default_rng(0)
    c = tw.contrast(np.array([1.0, 2, 3, 4, 5]), np.zeros(5), rng)
    assert c["mean"] == pytest.approx(3.0)
    assert 1.0 <= c["ci95"][0] < 3.0 < c["ci95"][1] <= 5.0
    assert c["wilcoxon_p"] == pytest.approx(2 / 32)  # all five signs positive, two-sided exact
    assert (c["wins"], c["losses"], c["units"]) == (5, 0, 5)
    tie = tw.contrast(np.ones(4), np.ones(4), rng)
    assert tie["mean"] == 0.0 and tie["wilcoxon_p"] == 1.0 and tie["ci95"] == [0.0, 0.0]


def _bow(d):
    return BowVector.from_dict(d)


@pytest.mark.parametrize("true_first", [True, False])
def test_scores_of_a_hand_made_sequence(tw, true_first):
    # Keyframes 0..3 at frames 0..3, min gap 2: keyframe 2 may match 0, keyframe 3 may match 0 or 1.
    # Keyframe 2's best match is 0 (true); keyframe 3's best is 1 (false: its loop is 0).
    strong, weak = (0.9, 0.6) if true_first else (0.6, 0.9)
    bows = [_bow({0: 1.0}), _bow({1: 1.0}),
            _bow({0: strong, 9: 1 - strong}), _bow({1: weak, 9: 1 - weak})]
    gt = np.zeros((4, 4), bool)
    gt[2, 0] = gt[0, 2] = gt[3, 0] = gt[0, 3] = True
    r = tw.scores(bows, np.arange(4), gt, 2)
    assert (r["queries"], r["with_loop"]) == (2, 2)
    assert r["recall@1"] == pytest.approx(0.5)
    # true detection ranked first: precision 1 at recall 0.5; ranked second: 0.5 at recall 0.5
    assert r["AP"] == pytest.approx(0.5 if true_first else 0.25)
    assert r["recall@P100"] == pytest.approx(0.5 if true_first else 0.0)


def test_causal_members_stay_in_the_window(tw):
    # track 5: kf0 f0, kf1 f2, kf2 f1; track 7: kf1 f0, kf2 f0
    tracks = [np.array([5, -1, -1]), np.array([7, -1, 5]), np.array([7, 5, -1])]
    out = tw.causal_members(tracks, window=2)
    rows, off, kf, ix = out[0]
    assert len(rows) == 0
    rows, off, kf, ix = out[1]  # track 5 has kf0 and kf1; track 7 only kf1
    assert rows.tolist() == [2] and kf.tolist() == [0, 1] and ix.tolist() == [0, 2]
    rows, off, kf, ix = out[2]  # window 2: kf0 is out of reach
    assert rows.tolist() == [0, 1]
    assert [kf[off[r]:off[r + 1]].tolist() for r in range(2)] == [[1, 2], [1, 2]]
    assert [ix[off[r]:off[r + 1]].tolist() for r in range(2)] == [[0, 0], [2, 1]]


def test_distinctive_is_the_least_median_member(tw):
    centre = np.zeros(32, np.uint8)
    others = []
    for k in range(4):  # each 8 bits from the centre, 16 from each other
        d = centre.copy()
        d[k] = 0xFF
        others.append(d)
    desc = np.stack([others[0], centre, *others[1:]])
    assert tw.distinctive(desc) == 1
    assert tw.distinctive(desc[[0, 2]]) == 0  # two members: a tie, to the oldest


class _LineVocab:
    """Words = nearest of centres 0, 1, 2, ... on the line of the first byte's value / 100."""

    def project(self, desc):
        return desc[:, :1].astype(np.float32) / 100.0

    def words_of_points(self, x):
        return np.rint(x[:, 0]).astype(np.int32)

    def transform_words(self, desc):
        return self.words_of_points(self.project(desc))


def _kfs(tw, desc, tracks, window):
    n = len(desc)
    return tw.Keyframes("t", np.arange(n), desc, [np.zeros((len(d), 2)) for d in desc], tracks, window,
                        np.zeros((n, n), bool), np.zeros((n, 3)), [np.zeros((len(d), 3)) for d in desc])


def test_track_mean_and_distinctive_words(tw):
    d = lambda *v: np.array([[x] + [0] * 31 for x in v], np.uint8)  # noqa: E731
    desc = [d(40, 250), d(80, 10), d(90, 120)]  # lone words 0, 2 / 1, 0 / 1, 1
    tracks = [np.array([3, -1]), np.array([3, -1]), np.array([3, -1])]
    kfs = _kfs(tw, desc, tracks, window=3)
    mean = tw.track_mean_words(_LineVocab(), kfs)
    # means: kf1 (40 + 80) / 2 = 60 -> 1; kf2 (40 + 80 + 90) / 3 = 70 -> 1; kf0 alone keeps 0
    assert [w.tolist() for w in mean] == [[0, 2], [1, 0], [1, 1]]
    dist = tw.distinctive_words(_LineVocab(), _kfs(tw, desc, tracks, window=2))
    # window 2: kf1's members (40, 80) tie -> 40 (word 0); kf2's (80, 90) tie -> 80 (word 1)
    assert [w.tolist() for w in dist] == [[0, 2], [0, 0], [1, 1]]


def test_effective_size_and_repeatability(tw):
    assert tw.effective_size([np.array([0, 1]), np.array([2, 3])]) == pytest.approx(4.0)
    p = np.array([0.75, 0.25])
    assert tw.effective_size([np.array([5, 5, 5, 9])]) == pytest.approx(math.exp(-(p * np.log(p)).sum()))
    words = [np.array([1, 2, 3]), np.array([1, 7, 3])]
    pairs = [(1, 0, np.array([0, 1]), np.array([0, 1])), (1, 0, np.array([2]), np.array([2]))]
    assert tw.repeatability(words, pairs) == pytest.approx(2 / 3)
    assert math.isnan(tw.repeatability(words, []))


def test_same_points_mutual_within_tolerance(tw):
    nan = np.nan
    kfs = _kfs(tw, [np.zeros((3, 32), np.uint8)] * 2, [np.full(3, -1)] * 2, 1)
    kfs.frames = np.array([0, 10])
    kfs.gt = np.array([[False, True], [True, False]])
    kfs.points = [np.array([[1.005, 0, 0], [0, 0, 0.02], [5, 5, 5]]),
                  np.array([[0, 0, 0], [1, 0, 0], [nan, nan, nan]])]
    (i, j, a, b), = tw.same_points(kfs, min_gap=5, tol=0.01)
    assert (i, j) == (1, 0)
    assert a.tolist() == [1] and b.tolist() == [0]  # (1, 0, 0) ~ (1.005, 0, 0); (0, 0, 0.02) too far
    assert tw.same_points(kfs, min_gap=11, tol=0.01) == []  # no older keyframe


def test_summary_leaves_out_contrasts_of_missing_arms(tw):
    rng = np.random.default_rng(1)
    per_seq = {}
    for n in range(6):
        per_seq[f"s{n}"] = {f"8000 {a}": {"AP": rng.random(), "recall@1": rng.random(), "recall@P100": 0.1,
                                          "repeatability": 0.2, "effective_words": 10.0} for a in ("A0", "B0")}
    means, table = tw.summarise(per_seq, {8000: ["A0", "B0"]})
    assert set(table) == {"8000 B0-A0 AP", "8000 B0-A0 recall@1"}
    d = [per_seq[n]["8000 B0"]["AP"] - per_seq[n]["8000 A0"]["AP"] for n in per_seq]
    assert table["8000 B0-A0 AP"]["mean"] == pytest.approx(np.mean(d))
    ps = [c["wilcoxon_p"] for c in table.values()]
    assert [c["holm_p"] for c in table.values()] == pytest.approx(tw.holm(ps))
    assert means["8000 A0"]["AP"] == pytest.approx(np.mean([per_seq[n]["8000 A0"]["AP"] for n in per_seq]))


def test_scores_agree_with_the_keyframe_database(tw):
    from orbslam_hgcn.map.database import KeyframeDatabase

    rng = np.random.default_rng(4)
    bows = []
    for _ in range(40):
        words = np.unique(rng.integers(0, 60, rng.integers(1, 12)))
        w = rng.random(len(words))
        bows.append(BowVector(words, w / w.sum()))
    frames = np.arange(40) * 3
    gt = rng.random((40, 40)) < 0.3
    got = tw.scores(bows, frames, gt, 30)
    # reference: the database's own query, keyframe by keyframe
    db, added, s, correct, eligible = KeyframeDatabase(), 0, [], [], []
    for i in range(40):
        while frames[added] <= frames[i] - 30:
            db.add(added, bows[added])
            added += 1
        if added == 0:
            continue
        res = db.query(bows[i], max_results=1)
        s.append(res[0][1] if res else 0.0)
        correct.append(bool(res) and bool(gt[i, res[0][0]]))
        eligible.append(bool(gt[i, :added].any()))
    assert got["queries"] == len(s) and got["with_loop"] == sum(eligible)
    assert got["recall@1"] == pytest.approx(sum(correct) / sum(eligible))
    assert 0 < got["recall@1"] < 1


def test_recorded_figures(tw, monkeypatch):
    got = {}
    monkeypatch.setattr(tw.figures, "record", lambda name, title, figs, **kw: got.update(name=name, figs=figs, **kw))
    arm = {"recall@P100": 0.25, "repeatability": 0.07, "effective_words": 7275.4}
    means = {"8000 A0": {"AP": 0.8123, "recall@1": 0.9, **arm}, "8000 B0": {"AP": 0.79, "recall@1": 0.88, **arm},
             "1000 A0": {"AP": 0.5, "recall@1": 0.6, **arm}}
    table = {"8000 B0-A0 AP": {"mean": -0.0212, "ci95": [-0.04, 0.001], "wins": 3, "losses": 9, "holm_p": 0.0312},
             "8000 B0-A0 recall@1": {"mean": 0.01, "ci95": [0.0, 0.02], "wins": 5, "losses": 1, "holm_p": 1.0}}
    tw.record_figures("track_words", means, table, 12, 1.5)
    assert got["name"] == "track_words" and got["load_start"] == 1.5
    assert got["figs"] == [("8000 words, AP", "A0 0.812, B0 0.790"),
                           ("8000 words, recall@1", "A0 0.900, B0 0.880"),
                           ("8000 words, AP contrasts", "B0-A0 -0.021 [-0.040, +0.001] 3/9 Holm p 0.031"),
                           ("1000 words, AP", "A0 0.500"),
                           ("1000 words, recall@1", "A0 0.600")]
    assert got["bench_file"].endswith("bench_track_words.py")


def test_recorded_kitti_figures(tw, monkeypatch):
    got = {}
    monkeypatch.setattr(tw.figures, "record", lambda name, title, figs, **kw: got.update(figs=figs))
    c = {"queries": 44, "threshold": 0.15, "max_score": 0.2}
    check = {"8000 A0": {**c, "false_positives": 3}, "8000 orb": {**c, "false_positives": 5},
             "1000 A0": {**c, "false_positives": 0}}
    tw.record_kitti("track_words_kitti", check, 3, 1.0)
    assert got["figs"] == [("8000 words, false positives of 44 queries", "A0 3, orb 5"),
                           ("1000 words, false positives of 44 queries", "A0 0")]


def test_threshold_at_precision(tw):
    s = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.4])
    c = np.array([True, True, False, True, False, False])
    # precision from the top: 1, 1, 2/3, 3/4, 3/5, 1/2
    assert tw.threshold_at_precision(s, c, 0.9) == 0.8
    assert tw.threshold_at_precision(s, c, 0.7) == 0.6
    assert tw.threshold_at_precision(s, c, 0.5) == 0.4
    assert tw.threshold_at_precision(s[::-1], c[::-1], 0.9) == 0.8  # order of the input does not matter
    # tied scores are kept or dropped together: 0.5 keeps both (2/3), so only 0.9 reaches 90%
    assert tw.threshold_at_precision(np.array([0.9, 0.5, 0.5]), np.array([True, True, False]), 0.9) == 0.9
    assert tw.threshold_at_precision(np.array([0.9, 0.5]), np.array([False, True]), 0.9) == math.inf


def test_false_positive_check(tw):
    r = tw.false_positive_check(np.array([0.1, 0.3, 0.25]), 0.25)
    assert (r["queries"], r["false_positives"]) == (3, 2)
    assert r["max_score"] == 0.3 and r["max_over_threshold"] == pytest.approx(1.2)
    none = tw.false_positive_check(np.array([0.1, 0.3]), math.inf)
    assert none["false_positives"] == 0 and none["max_over_threshold"] == 0.0


def test_kitti_check_thresholds_from_the_pooled_offices(tw):
    # Arm X: pooled office detections 0.9 T, 0.6 T, 0.5 F (from two offices) -> 90% threshold 0.6;
    # KITTI detections 0.7, 0.55, 0.6 -> 0.7 and 0.6 are false positives.
    offices = [{"8000 X": {"top1": [0.9, 0.5], "top1_true": [True, False]}},
               {"8000 X": {"top1": [0.6], "top1_true": [True]}}]
    kitti = {"8000 X": {"top1": [0.7, 0.55, 0.6]}}
    r = tw.kitti_check(kitti, offices, {8000: ["X"]})["8000 X"]
    assert r["threshold"] == 0.6 and r["false_positives"] == 2 and r["max_score"] == 0.7


def test_family_settings_and_units(tw):
    args = tw.argparse.Namespace(family="kitti", scene_seeds=None, calib_seeds=[0, 1], fps=None, kf_every=None,
                                 min_gap=50, dist=None, angle=None)
    assert tw.units(args) == [("kitti", 0), ("office", 0), ("office", 1)]
    k, o = tw.family_args(args, "kitti"), tw.family_args(args, "office")
    assert (k.min_gap, k.dist, k.kf_every) == (50, 4.0, 3)  # the option given overrides the family's own
    assert (o.min_gap, o.dist) == (100, 0.5)  # the calibration offices keep the frozen office settings
    args.family, args.scene_seeds = "street", [5, 6]
    assert tw.units(args) == [("street", 5), ("street", 6)]


def test_street_passes_revisit_the_route(tw):
    # Two 12 s passes at 10/3 Hz (40 keyframes each): the second drives 1 m left of the first's
    # path and 0.2 m lower, so at 4 m every second-pass keyframe has a loop in the first pass,
    # and no keyframe has one in its own pass at the database gap.
    opts, scene, first, second, times = tw.street_passes(3, 12.0, 10 / 3)
    assert len(times) == 40 and opts.width == 1241
    a, b = first(times), second(times)
    dense = first(np.arange(0.0, 14.0, 0.005))[:, :3, 3]
    near = dense[np.argmin(np.linalg.norm(dense[None, :, :2] - b[:, None, :2, 3], axis=2), axis=1)]
    assert np.allclose(np.linalg.norm(near[:, :2] - b[:, :2, 3], axis=1), 1.0, atol=0.05)
    assert np.allclose(b[:, 2, 3] - near[:, 2], -0.2, atol=0.05)
    assert np.linalg.norm(np.diff(a[:, :3, 3], axis=0), axis=1).min() > 1.0  # it drives
    gt = tw.loop_truth(np.concatenate([a, b]), 4.0, 30.0)
    frames = np.arange(80) * 3
    far = frames[:, None] - frames[None, :] >= 100
    cross = np.zeros((80, 80), bool)
    cross[40:, :40] = True
    assert not (gt & far & ~cross).any()
    assert gt[40:, :40].any(1).all()


def test_kitti_stretch_has_no_loop_at_the_gap(tw):
    from orbslam_hgcn.datasets.kitti import read_kitti_poses

    poses = read_kitti_poses(tw.KITTI_DIR.parents[1] / "poses" / "00.txt")[:160:3]
    f = tw.FAMILIES["kitti"]
    frames = np.arange(len(poses)) * f["kf_every"]
    gt = tw.loop_truth(poses, f["dist"], f["angle"])
    assert not (gt & (frames[:, None] - frames[None, :] >= f["min_gap"])).any()
    assert gt[np.arange(1, len(poses)), np.arange(len(poses) - 1)].all()  # consecutive keyframes are near


def test_depth_points_back_project(tw):
    from orbslam_hgcn.geometry.camera import PinholeCamera

    cam = PinholeCamera(100.0, 100.0, 50.0, 40.0, 100, 80)
    inv = np.full((80, 100), 0.5, np.float32)  # 2 m everywhere ...
    inv[10, 70] = 0.0  # ... but one pixel without depth
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    p = tw.depth_points(np.array([[50.0, 40.0], [60.0, 40.0], [70.0, 10.0]]), inv, cam, T)
    assert np.allclose(p[0], [1.0, 2.0, 5.0]) and np.allclose(p[1], [1.2, 2.0, 5.0])
    assert np.isnan(p[2]).all()


def test_map_window_keeps_members_inside_the_gap(tw):
    # keyframes every 30 frames, gap 100: 120 reaches back to 30 (4 keyframes), never to 0
    assert tw.map_window(np.array([0, 30, 60, 90, 120, 150, 180]), 100) == 4
    # a dense stretch does not widen it: 200 has no other keyframe within 100 frames
    assert tw.map_window(np.array([0, 10, 20, 50, 200, 210, 320]), 100) == 1
    frames = np.sort(np.random.default_rng(1).choice(2000, 300, replace=False))
    w = tw.map_window(frames, 100)
    k = np.arange(w - 1, len(frames))
    assert np.all(frames[k] - frames[k - w + 1] < 100)  # every window is inside the gap ...
    later = np.flatnonzero(frames - 100 >= frames[0])
    lo = np.searchsorted(frames, frames[later] - 100, side="right")
    assert np.any(later - lo + 1 == w)  # ... and one more keyframe would leave it somewhere


def test_settings_of_the_map_family_write_as_json(tw):
    import json

    pairs = [(Path("/m/office0.npz"), Path("/d/office0")), (Path("/m/office1.npz"), Path("/d/office1"))]
    settings = {"maps": pairs, "cache_dir": Path("/c"), "sizes": [8000, 1000], "family": "map"}
    back = json.loads(json.dumps({k: tw._plain(v) for k, v in settings.items()}))
    assert back["maps"] == [["/m/office0.npz", "/d/office0"], ["/m/office1.npz", "/d/office1"]]
    assert back["cache_dir"] == "/c" and back["sizes"] == [8000, 1000]


def test_photo_units_are_held_out_images_only(tw):
    from orbslam_hgcn.vocabulary.training.photos import HOLDOUT, photo_files

    folder = real_photo_folder()
    units = tw.photo_units(folder)
    held = {f for fs in photo_files(folder, "heldout").values() for f in fs}
    train = {f for fs in photo_files(folder, "train").values() for f in fs}
    used = [f for _, files in units for f in files]
    assert len(used) == len(set(used)) and set(used) <= held and not set(used) & train
    # every held-out CamVid image, in order, in blocks of about PHOTO_UNIT consecutive images
    camvid = photo_files(folder, "heldout")["camvid"]
    assert used == camvid and int(camvid[0].stem.split("_")[1]) == HOLDOUT["camvid"]
    assert len(units) == round(len(camvid) / tw.PHOTO_UNIT)
    assert all(abs(len(files) - tw.PHOTO_UNIT) <= 1 for _, files in units)
    assert units[0][0] == f"camvid_{HOLDOUT['camvid']:04d}-{units[0][1][-1].stem.split('_')[1]}"


def test_photo_truth_is_geometric_verification(tw):
    from orbslam_hgcn.datasets.base import read_image
    from orbslam_hgcn.features.orb import ORBExtractor

    folder = real_photo_folder()
    ex = ORBExtractor()
    # two consecutive held-out CamVid frames (the same street) and an unrelated ImageNet photo
    kps = [ex.extract(read_image(folder / f)) for f in ("camvid_0620.jpg", "camvid_0621.jpg",
                                                        "imagenet_sample_0000.jpg")]
    n = tw.photo_inliers([k.desc for k in kps], [np.asarray(k.uv, np.float32) for k in kps])
    assert (n == n.T).all() and (np.diag(n) == 0).all()
    assert n[0, 1] >= 4 * tw.PHOTO_MIN_INLIERS  # 456 inliers: the same place, far above the bar
    assert n[0, 2] < tw.PHOTO_MIN_INLIERS / 2 and n[1, 2] < tw.PHOTO_MIN_INLIERS / 2  # 8: chance
