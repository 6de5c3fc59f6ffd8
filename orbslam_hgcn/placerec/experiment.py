"""One sequence of a loop-closure experiment: the images used, the loops scored, the window.

:func:`prepare_sequence` opens a sequence, samples it (:func:`~orbslam_hgcn.placerec.window.sample_indices`),
loads its loop ground truth over the images kept, keeps the revisit pairs as the loops to
score, and chooses its exclusion window (:func:`~orbslam_hgcn.placerec.window.choose_window`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


def ground_truth_for(gt_path: Path, source, name: str = "test", gt: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The (n, n) loop matrix of the selected images, and its revisit pairs (n, n).

    A matrix over every image of the sequence is cut down to the selected ones, its revisits
    (:func:`~orbslam_hgcn.placerec.window.revisit_pairs`) found on the whole matrix first; a
    matrix over the selected images is taken as it is; any other size is a DatasetError
    naming the file. gt: the matrix already loaded from ``gt_path``.
    """
    from orbslam_hgcn.errors import DatasetError
    from orbslam_hgcn.placerec.data import load_ground_truth
    from orbslam_hgcn.placerec.window import revisit_pairs

    if gt is None:
        gt = load_ground_truth(gt_path)
    n = len(source)
    idx = source.indices
    if gt.shape[0] == source.total:
        return gt[np.ix_(idx, idx)], revisit_pairs(gt)[np.ix_(idx, idx)]
    if gt.shape[0] == n:
        return gt, revisit_pairs(gt)
    raise DatasetError(
        f"{gt_path}: ground truth is {gt.shape[0]}x{gt.shape[1]} but the {name} sequence has "
        f"{n} selected images ({source.total} in all)"
    )


@dataclass(frozen=True, eq=False)
class Prepared:
    """One sequence of the experiment: its images as used, how they were chosen, its loops
    over them (the revisit pairs of its ground truth, (n, n) bool; None without ground truth),
    how many true pairs of the ground truth were left out as one continuous visit, and its
    exclusion window (None for a training sequence without ground truth: it needs none)."""

    source: object  # ImageSource
    sampling: object  # window.Sampling
    gt: np.ndarray | None
    visit_pairs: int
    window: object  # window.Window


def prepare_sequence(
    path: str | Path, gt_path: Path | None, *, stride: int | None, every_s: float | None, limit: int | None,
    min_gap: int | None, window_s: float | None, name: str = "test",
) -> Prepared:
    """Open a sequence, choose its images (:func:`~orbslam_hgcn.placerec.window.sample_for_loops`),
    load its ground truth over them and choose its exclusion window.

    The loops scored are the ground truth's revisits
    (:func:`~orbslam_hgcn.placerec.window.revisit_pairs`): a pair of images of one continuous
    visit of a place (joined to the diagonal through true pairs) is no loop closure. A ground
    truth over every frame is read before the images are chosen, so that a spacing which
    leaves too few revisits is made denser; the window is then chosen on the images used.
    When too few images revisit even so, ``sampling.warning`` says so; when the ground truth
    covers only the images sampled, they are counted and warned about all the same.
    """
    from orbslam_hgcn.placerec.data import ImageSource, load_ground_truth
    from orbslam_hgcn.placerec.window import (
        MIN_REVISITS,
        Sampling,
        choose_window,
        revisit_pairs,
        revisiting_images,
        sample_for_loops,
        with_revisit_warning,
    )

    whole = ImageSource(path)
    poses = whole.all_poses if stride is None and every_s is None else None
    gt_all = load_ground_truth(gt_path) if gt_path is not None else None
    revisits_all = revisit_pairs(gt_all) if gt_all is not None and gt_all.shape[0] == whole.total else None
    sampling = sample_for_loops(whole.total, whole.all_timestamps, poses, revisits_all, stride=stride,
                                every_s=every_s, limit=limit, min_gap=min_gap, window_s=window_s, name=name)
    src = whole.select(sampling.indices, limit)
    revisits, visit_pairs = None, 0
    if gt_path is not None:
        gt, revisits = ground_truth_for(gt_path, src, name, gt_all)
        visit_pairs = int(np.count_nonzero(np.tril(gt, -1) & ~revisits))
    window = None
    if revisits is not None or name == "test":  # a training sequence needs one only to fit thresholds
        gap = sampling.min_gap if sampling.min_gap is not None else min_gap  # set only for a --min-gap
        window = choose_window(revisits, src.timestamps, min_gap=gap, window_s=window_s, given_gap=min_gap)
    if revisits is not None and sampling.revisiting is None and revisits.any():
        # a ground truth over the sampled images only: nothing to densify with
        sampling = with_revisit_warning(
            Sampling(sampling.indices, sampling.how, revisiting_images(revisits, window.gap)), name, MIN_REVISITS,
            "and the ground truth covers only the images sampled, so no denser sampling can be chosen")
    return Prepared(src, sampling, revisits, visit_pairs, window)


def warn_hidden_loops(name: str, prep: Prepared) -> str | None:
    """A warning when ground-truth revisits fall inside the window (no detector may report them)."""
    from orbslam_hgcn.placerec.window import hidden_revisits

    if prep.gt is None or prep.window is None:
        return None
    lost, pairs = hidden_revisits(prep.gt, prep.window.gap)
    if pairs == 0:
        return None
    return (f"{name}: {pairs} ground-truth loop pairs lie inside the exclusion window of {prep.window.gap} images; "
            f"{lost} images have no loop outside it, and no detector may report them")


def write_image_list(path: Path, prep: Prepared) -> Path:
    t = prep.source.timestamps
    with open(path, "w", encoding="utf-8") as f:
        f.write(f"# {prep.source.path}: {len(prep.source)} of {prep.source.total} images, {prep.sampling.how}\n")
        f.write("# position frame timestamp name\n")
        for k, (i, name) in enumerate(zip(prep.source.indices, prep.source.names())):
            stamp = f"{t[k]:.6f}" if t is not None else "-"
            f.write(f"{k} {int(i)} {stamp} {name}\n")
    return path
