"""ORB extraction: level budget, quadtree spreading, orientation, descriptors, undistortion."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from orbslam_hgcn.config import ORBConfig, load_camera
from orbslam_hgcn.features.distribute import cell_ids, distribute_quadtree, features_per_level, quadtree_keys
from orbslam_hgcn.features.orb import ORBExtractor, circular_patch_offsets, ic_angles
from orbslam_hgcn.features.pyramid import PyramidMaps, build_pyramid
from orbslam_hgcn.features.rbrief import opencv_rbrief

TUM_FRAME = "rgb/1341847980.722988.png"


def _tum_image(folder):
    """TUM_FRAME of the real sample, or the sixth frame of the rendered stand-in."""
    path = folder / TUM_FRAME if (folder / TUM_FRAME).is_file() else sorted((folder / "rgb").glob("*.png"))[5]
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert img is not None
    return img


@pytest.fixture(scope="module")
def extractor():
    return ORBExtractor(ORBConfig())


def test_features_per_level_is_orbslam_series():
    n = features_per_level(1000, 1.2, 8)
    assert n.sum() == 1000
    assert n.tolist()[:3] == [217, 181, 151]
    np.testing.assert_allclose(n[1:7] / n[:6], 1 / 1.2, atol=0.02)


def _reference_octree(x, y, resp, n_wanted, bounds):
    """Plain port of ORB-SLAM's DistributeOctTree (nodes split at their float midpoints)."""
    min_x, max_x, min_y, max_y = bounds
    n_ini = max(int(round((max_x - min_x) / (max_y - min_y))), 1)
    hx = (max_x - min_x) / n_ini
    idx = np.arange(len(x))

    def children(node):
        x0, x1, y0, y1, ids = node
        xm, ym = (x0 + x1) / 2, (y0 + y1) / 2
        out = []
        for a0, a1, b0, b1 in ((x0, xm, y0, ym), (xm, x1, y0, ym), (x0, xm, ym, y1), (xm, x1, ym, y1)):
            sel = ids[(x[ids] >= a0) & (x[ids] < a1) & (y[ids] >= b0) & (y[ids] < b1)]
            if len(sel):
                out.append((a0, a1, b0, b1, sel))
        return out

    nodes = []
    for i in range(n_ini):
        ids = idx[(x >= min_x + i * hx) & (x < min_x + (i + 1) * hx)]
        if len(ids):
            nodes.append((min_x + i * hx, min_x + (i + 1) * hx, min_y, max_y, ids))
    while True:
        prev = len(nodes)
        new, expandable = [], []
        for nd in nodes:
            if len(nd[4]) == 1:
                new.append(nd)
                continue
            for ch in children(nd):
                new.append(ch)
                if len(ch[4]) > 1:
                    expandable.append(ch)
        nodes = new
        if len(nodes) >= n_wanted or len(nodes) == prev:
            break
        if len(nodes) + 3 * len(expandable) > n_wanted:
            while True:
                prev = len(nodes)
                todo = sorted(expandable, key=lambda nd: len(nd[4]))
                expandable = []
                for nd in reversed(todo):
                    nodes = [m for m in nodes if m is not nd]
                    for ch in children(nd):
                        nodes.append(ch)
                        if len(ch[4]) > 1:
                            expandable.append(ch)
                    if len(nodes) >= n_wanted:
                        break
                if len(nodes) >= n_wanted or len(nodes) == prev:
                    break
            break
    return {int(nd[4][np.argmax(resp[nd[4]])]) for nd in nodes}


def test_quadtree_matches_orbslam_reference():
    rng = np.random.default_rng(2)
    bounds = (16.0, 624.0, 16.0, 464.0)
    # Clustered corners: a dense blob plus a sparse background, as on real images.
    x = np.concatenate([rng.normal(200, 30, 1500), rng.uniform(16, 624, 500)])
    y = np.concatenate([rng.normal(150, 25, 1500), rng.uniform(16, 464, 500)])
    keep = (x >= 16) & (x < 624) & (y >= 16) & (y < 464)
    x, y = np.round(x[keep]), np.round(y[keep])
    _, first = np.unique(x * 1000 + y, return_index=True)
    x, y = x[first], y[first]
    resp = rng.uniform(7, 100, len(x))
    for n_wanted in (50, 217, 400):
        keys = quadtree_keys(x, y, np.zeros(len(x), int), np.array([bounds]))
        ours = distribute_quadtree(keys, resp, np.array([n_wanted]))
        ref = _reference_octree(x, y, resp, n_wanted, bounds)
        assert len(ours) == n_wanted
        assert n_wanted <= len(ref) <= n_wanted + 3
        assert len(set(ours.tolist()) & ref) >= 0.9 * n_wanted


def test_quadtree_over_levels_keeps_the_wanted_count_and_the_strongest_of_a_node():
    # Two levels in one call, in any input order: each keeps min(N, wanted) corners; a
    # level with fewer corners than wanted keeps them all; a lone strong corner in its own
    # quadrant survives; of two corners at the same position the stronger one is kept.
    rng = np.random.default_rng(7)
    bounds = np.array([(16.0, 624.0, 16.0, 464.0), (16.0, 517.0, 16.0, 384.0)])
    x = np.concatenate([rng.uniform(16, 300, 800), [600.0, 100.0, 100.0], rng.uniform(16, 500, 30)])
    y = np.concatenate([rng.uniform(16, 200, 800), [450.0, 300.0, 300.0], rng.uniform(16, 380, 30)])
    group = np.concatenate([np.zeros(803, int), np.ones(30, int)])
    resp = np.concatenate([rng.uniform(7, 50, 800), [60.0, 30.0, 40.0], rng.uniform(7, 50, 30)])
    keys = quadtree_keys(x, y, group, bounds)
    perm = rng.permutation(len(x))
    kept = perm[distribute_quadtree(keys[perm], resp[perm], np.array([100, 40]))]
    assert np.sum(group[kept] == 0) == 100 and np.sum(group[kept] == 1) == 30
    assert 800 in kept  # alone in the bottom-right quadrant
    assert 802 in kept and 801 not in kept  # same position: the stronger one
    with pytest.raises(ValueError, match="quadtree keys"):
        distribute_quadtree(np.array([-1, 5]), np.ones(2), np.array([1]))
    with pytest.raises(ValueError, match="quadtree keys"):
        distribute_quadtree(keys, resp, np.array([100]))  # level 1 has no entry


@pytest.mark.parametrize("size", [(1241, 376, 1.2, 8, 30.0), (752, 480, 1.2, 8, 35.0), (60, 45, 1.5, 4, 20.0)])
def test_pyramid_tables_equal_the_cell_and_key_of_every_pixel(size):
    # The tables are filled from one row and one column of each level; they must hold
    # cell_ids and quadtree_keys of every pixel, -1 outside the detection area, and each
    # cell's box must be the bounding box of its pixels.
    width, height, scale, levels, cell = size
    maps = PyramidMaps.create(width, height, scale, levels, 19, cell)
    lo = 19 - 3
    for level, (w, h) in enumerate(maps.sizes):
        yy, xx = np.mgrid[0:h, 0:w]
        inside = (xx >= lo) & (xx < w - lo) & (yy >= lo) & (yy < h - lo)
        x, y = xx[inside].astype(np.float64), yy[inside].astype(np.float64)
        g = np.full(len(x), level)
        assert (maps.cell_maps[level][~inside] == -1).all() and (maps.key_maps[level][~inside] == -1).all()
        np.testing.assert_array_equal(maps.cell_maps[level][inside], cell_ids(x, y, g, maps.bounds, cell))
        np.testing.assert_array_equal(maps.key_maps[level][inside], quadtree_keys(x, y, g, maps.bounds))
        cells = maps.cell_maps[level][inside]
        for c in np.unique(cells)[:: max(1, len(np.unique(cells)) // 25)]:
            px, py = xx[inside][cells == c], yy[inside][cells == c]
            assert tuple(maps.cell_boxes[c]) == (px.min(), px.max() + 1, py.min(), py.max() + 1)
        if len(cells):  # the smallest levels have no detection area
            assert maps.level_cells[level] <= cells.min() and cells.max() < maps.level_cells[level + 1]


def test_weak_corners_only_where_a_cell_has_no_strong_one(extractor):
    # Left half: high-contrast blobs (many FAST scores above 20); right half: the same
    # pattern at 60 grey levels of contrast (scores between 7 and 20 only). ORB-SLAM's cells
    # keep their strong corners only, and fall back to the weak ones where none is strong.
    rng = np.random.default_rng(3)
    pattern = cv2.resize(rng.random((60, 80)).astype(np.float32), (640, 480), interpolation=cv2.INTER_CUBIC)
    img = np.where(np.arange(640)[None, :] < 320, 30 + 200 * pattern, 60 + 60 * pattern)
    img = np.clip(img, 0, 255).astype(np.uint8)
    maps = extractor.maps(*img.shape)
    levels = build_pyramid(img, 1.2, 8)
    x, y, level, score, cell, _ = extractor._detect(levels, maps)
    lvl0 = level == 0
    window = levels[0][16:464, 16:624]  # level 0 inside ORB-SLAM's border (edge 19 - 3)

    def fast_cells(threshold):
        pts = np.asarray(cv2.KeyPoint_convert(cv2.FastFeatureDetector_create(threshold, True).detect(window)))
        pts = pts.astype(int) + 16
        return pts, maps.cell_maps[0][pts[:, 1], pts[:, 0]]

    strong_pts, strong_cells = fast_cells(20)
    weak_pts, weak_cells = fast_cells(7)
    weak = lvl0 & (score < 20)
    assert len(strong_pts) > 500 and weak.sum() > 200
    # Every strong corner is kept; weak ones only in cells without a strong one, and those
    # lie in the low-contrast half; every such cell was searched.
    found = set(zip(x[lvl0].tolist(), y[lvl0].tolist()))
    assert set(map(tuple, strong_pts.tolist())) <= found
    assert not np.isin(cell[weak], strong_cells).any()
    assert score[weak].min() >= 7 and np.all(x[weak] >= 320 - 19)
    assert set(weak_cells.tolist()) - set(strong_cells.tolist()) <= set(cell[weak].tolist())
    kps = extractor.extract(img)
    assert abs(len(kps) - 1000) <= 50 and np.any(kps.uv_raw[:, 0] > 400)


def _opencv_cell_fast(img, level, maps, hi=20, lo_th=7, edge=19):
    """ORB-SLAM's per-cell FAST with cv2.FAST: the level window (edge - 3 inside) at the
    high threshold, then each cell without a corner on its own window (the cell plus 3 px)
    at the low threshold, keeping the corners inside the cell."""
    lo = edge - 3
    h, w = img.shape

    def fast(threshold, r0, r1, c0, c1):
        if r1 - r0 <= 6 or c1 - c0 <= 6:
            return []
        kps = cv2.FastFeatureDetector_create(threshold, True).detect(img[r0:r1, c0:c1])
        return [(int(k.pt[0]) + c0, int(k.pt[1]) + r0, k.response) for k in kps]

    cells = maps.cell_maps[level]
    found = [(x, y, r, cells[y, x]) for x, y, r in fast(hi, lo, h - lo, lo, w - lo)]
    covered = {c for *_, c in found}
    for cell in range(maps.level_cells[level], maps.level_cells[level + 1]):
        if cell in covered:
            continue
        x0, x1, y0, y1 = maps.cell_boxes[cell].tolist()
        for x, y, r in fast(lo_th, max(y0 - 3, lo), min(y1 + 3, h - lo), max(x0 - 3, lo), min(x1 + 3, w - lo)):
            if cells[y, x] == cell:
                found.append((x, y, r, cell))
    return found


@pytest.mark.parametrize("which", ["tum", "euroc", "blobs"])
def test_compiled_fast_equals_opencv_on_orbslam_windows(which, request, extractor):
    # The compiled detector must find cv2.FAST's corners, scores and order on the same
    # windows, on every level: a real TUM frame (many cells fall back to the low
    # threshold), a EuRoC frame (752 px wide) and a synthetic image with both contrasts.
    if which == "tum":
        img = _tum_image(request.getfixturevalue("tum_sample"))
    elif which == "euroc":
        euroc_sample = request.getfixturevalue("euroc_sample")
        img = cv2.imread(str(sorted((euroc_sample / "mav0" / "cam0" / "data").glob("*.png"))[40]), 0)
    else:
        rng = np.random.default_rng(5)
        pattern = cv2.resize(rng.random((60, 80)).astype(np.float32), (640, 480), interpolation=cv2.INTER_CUBIC)
        img = np.clip(np.where(np.arange(640)[None, :] < 320, 30 + 200 * pattern, 60 + 60 * pattern), 0, 255)
        img = img.astype(np.uint8)
    maps = extractor.maps(*img.shape)
    weak = 0
    for level, level_img in enumerate(build_pyramid(img, 1.2, 8)):
        x, y, _, score, cell, _ = extractor._detect_level(level, level_img, maps)
        ref = _opencv_cell_fast(level_img, level, maps)
        assert len(ref) > 20
        assert list(zip(x.tolist(), y.tolist(), score.tolist(), cell.tolist())) == [
            (a, b, float(r), c) for a, b, r, c in ref
        ]
        weak += int((score < 20).sum())
    assert weak > 50  # the low-threshold pass was exercised


def test_extractor_rejects_fast_thresholds_outside_a_byte():
    with pytest.raises(ValueError, match="FAST thresholds"):
        ORBExtractor(ORBConfig(ini_th_fast=300))
    with pytest.raises(ValueError, match="FAST thresholds"):
        ORBExtractor(ORBConfig(min_th_fast=25, ini_th_fast=20))


def _grid_stats(uv, width, height, gx=8, gy=6):
    cx = np.clip((uv[:, 0] * gx / width).astype(int), 0, gx - 1)
    cy = np.clip((uv[:, 1] * gy / height).astype(int), 0, gy - 1)
    counts = np.bincount(cy * gx + cx, minlength=gx * gy)
    return (counts > 0).mean(), counts.std() / counts.mean()


def test_orb_on_tum_image_count_spread_octaves(tum_sample, extractor):
    img = _tum_image(tum_sample)
    cam = load_camera("tum_fr3")
    kps = extractor.extract(img, cam)
    assert abs(len(kps) - 1000) <= 50
    assert kps.desc.shape == (len(kps), 32) and kps.desc.dtype == np.uint8
    assert set(np.unique(kps.octave).tolist()) == set(range(8))
    np.testing.assert_allclose(kps.scale_factors, 1.2 ** np.arange(8), rtol=1e-6)
    # Every keypoint lies at least the edge threshold inside its level.
    lvl_xy = kps.uv_raw / kps.scale_factors[kps.octave][:, None]
    sizes = np.array([[np.round(640 / s), np.round(480 / s)] for s in kps.scale_factors])[kps.octave]
    assert np.all(lvl_xy >= 19 - 1e-3) and np.all(lvl_xy < sizes - 19 + 1e-3)
    occ, cv = _grid_stats(kps.uv, 640, 480)
    plain = cv2.KeyPoint_convert(cv2.ORB_create(1000).detect(img, None))
    occ_cv2, cv_cv2 = _grid_stats(plain, 640, 480)
    assert occ >= 0.8
    assert occ >= occ_cv2 + 0.2
    assert cv < 0.6 * cv_cv2


def test_level_threads_give_the_same_keypoints(tum_layout):
    # The pyramid levels may be searched and described on several threads; the result must
    # be that of one thread, element for element.
    img = _tum_image(tum_layout)
    cam = load_camera("tum_fr3")
    one = ORBExtractor(ORBConfig(threads=1)).extract(img, cam)
    three = ORBExtractor(ORBConfig(threads=3)).extract(img, cam)
    assert len(one) > 900
    for name in ("uv_raw", "uv", "octave", "angle", "response", "desc"):
        np.testing.assert_array_equal(getattr(three, name), getattr(one, name))


def test_orb_descriptors_equal_opencv_for_same_keypoints(tum_layout, extractor):
    img = _tum_image(tum_layout)
    kps = extractor.extract(img)
    levels = build_pyramid(img, 1.2, 8)
    orb = cv2.ORB_create(nfeatures=1000, scaleFactor=1.2, nlevels=1, edgeThreshold=19, patchSize=31)
    for lvl, level_img in enumerate(levels):
        idx = np.flatnonzero(kps.octave == lvl)
        xy = kps.uv_raw[idx] / np.float32(kps.scale_factors[lvl])
        cv_kps = [cv2.KeyPoint(float(u), float(v), 31.0, float(a)) for (u, v), a in zip(xy, kps.angle[idx])]
        out, desc = orb.compute(level_img, cv_kps)
        assert len(out) == len(idx)
        np.testing.assert_array_equal(desc, kps.desc[idx])
    # Level 0 also equals OpenCV's own multi-scale ORB given the same keypoints.
    idx = np.flatnonzero(kps.octave == 0)
    cv_kps = [
        cv2.KeyPoint(float(u), float(v), 31.0, float(a), 0.0, 0) for (u, v), a in zip(kps.uv_raw[idx], kps.angle[idx])
    ]
    orb8 = cv2.ORB_create(nfeatures=1000, scaleFactor=1.2, nlevels=8, edgeThreshold=19, patchSize=31)
    _, desc0 = orb8.compute(img, cv_kps)
    np.testing.assert_array_equal(desc0, kps.desc[idx])


def test_orientation_equals_loop_reference(tum_layout):
    img = _tum_image(tum_layout)
    rng = np.random.default_rng(3)
    x = rng.integers(20, 620, 25)
    y = rng.integers(20, 460, 25)
    du, dv = circular_patch_offsets(15)
    ref = []
    for xi, yi in zip(x, y):
        m10 = m01 = 0.0
        for a, b in zip(du, dv):
            val = float(img[yi + b, xi + a])
            m10 += a * val
            m01 += b * val
        ref.append(np.degrees(np.arctan2(m01, m10)) % 360.0)
    got = ic_angles(img, x, y, 15)
    diff = np.abs((got - np.array(ref) + 180.0) % 360.0 - 180.0)
    assert diff.max() < 1e-3
    # The patch is ORB-SLAM's symmetric disc of radius 15.
    assert len(du) == len(set(zip(du.tolist(), dv.tolist())))
    assert np.all(du**2 + dv**2 <= 15**2 + 15)


def test_euroc_keypoints_are_undistorted(euroc_layout, extractor):
    cam = load_camera("euroc_cam0")
    path = sorted((euroc_layout / "mav0" / "cam0" / "data").glob("*.png"))[0]
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    kps = extractor.extract(img, cam)
    assert abs(len(kps) - 1000) <= 50
    np.testing.assert_allclose(kps.uv, cam.undistort_points(kps.uv_raw), atol=1e-9)
    assert np.max(np.linalg.norm(kps.uv - kps.uv_raw, axis=1)) > 5.0


def test_compiled_rbrief_equals_opencv_at_any_orientation(tum_layout):
    # The test pattern is read off OpenCV, and the compiled descriptor must then equal
    # cv2.ORB.compute bit for bit: random keypoints, random orientations, real images.
    compiled = opencv_rbrief(31, 19)
    assert compiled is not None, "the extractor would fall back to cv2.ORB.compute"
    pattern = np.stack([compiled.px, compiled.py], axis=1)
    assert pattern.shape == (512, 2)
    assert np.all(np.abs(pattern) <= 15) and len({tuple(p) for p in pattern.reshape(256, 4).tolist()}) == 256
    orb = cv2.ORB_create(nfeatures=1000, nlevels=1, edgeThreshold=19, patchSize=31)
    rng = np.random.default_rng(7)
    for path in sorted((tum_layout / "rgb").glob("*.png"))[:6]:
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        x = rng.integers(19, img.shape[1] - 19, 400)
        y = rng.integers(19, img.shape[0] - 19, 400)
        angle = rng.uniform(0.0, 360.0, 400).astype(np.float32)
        kps = [cv2.KeyPoint(float(u), float(v), 31.0, float(a)) for u, v, a in zip(x, y, angle)]
        out, want = orb.compute(img, kps)
        assert len(out) == 400
        np.testing.assert_array_equal(compiled.describe(img, x, y, angle), want)
    with pytest.raises(ValueError, match="border"):
        compiled.describe(img, np.array([compiled.reach - 1]), np.array([100]), np.zeros(1, np.float32))


def test_the_pattern_kept_between_runs_is_checked_before_use(tmp_path, monkeypatch):
    # The pattern read off OpenCV is kept in the user's cache; a later process uses it only
    # after the same check against cv2.ORB.compute, so a wrong or damaged file is read
    # again from OpenCV and replaced.
    from orbslam_hgcn.features import rbrief as rb

    monkeypatch.setenv("ORBSLAM_HGCN_CACHE", str(tmp_path))
    probe = rb.opencv_rbrief.__wrapped__
    fresh = probe(31, 19)
    kept = rb._pattern_file(31, 19)
    assert fresh is not None and kept.is_file() and kept.is_relative_to(tmp_path)
    pattern = np.load(kept)
    np.testing.assert_array_equal(pattern.reshape(-1, 2), np.stack([fresh.px, fresh.py], axis=1))
    real_probe = rb.probe_pattern

    def not_probed(*args):
        raise AssertionError("OpenCV probed although the kept pattern is good")

    monkeypatch.setattr(rb, "probe_pattern", not_probed)
    assert np.array_equal(probe(31, 19).px, fresh.px)  # from the file
    monkeypatch.setattr(rb, "probe_pattern", real_probe)
    np.save(kept, pattern[::-1])  # the pairs in the wrong order: fails the check
    assert np.array_equal(probe(31, 19).px, fresh.px)
    np.testing.assert_array_equal(np.load(kept), pattern)  # read again and replaced
    kept.write_bytes(b"not a pattern")
    assert np.array_equal(probe(31, 19).px, fresh.px)
    np.testing.assert_array_equal(np.load(kept), pattern)


def test_extractor_falls_back_to_opencv_descriptors(tum_layout, extractor, monkeypatch):
    # Where the pattern cannot be read off OpenCV, cv2.ORB.compute describes, with the same result.
    monkeypatch.setattr("orbslam_hgcn.features.orb.opencv_rbrief", lambda *args: None)
    fallback = ORBExtractor()
    assert fallback._rbrief is None and extractor._rbrief is not None
    img = _tum_image(tum_layout)
    a, b = fallback.extract(img), extractor.extract(img)
    for name in ("uv_raw", "octave", "angle", "desc"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
