"""Absolute and relative trajectory error (ATE / RPE) through evo.

The metrics follow Sturm et al., "A Benchmark for the Evaluation of RGB-D SLAM Systems"
(IROS 2012): the estimate is associated with the ground truth by timestamp, aligned to it in
the least-squares sense, and the **absolute trajectory error** is the distance between
associated camera centres; the **relative pose error** compares the motion between poses
``delta`` apart, ``E_i = (Q_i^-1 Q_{i+delta})^-1 (P_i^-1 P_{i+delta})``, and reports its
translation (metres) and rotation angle (degrees).

The alignment is the closed form of Umeyama, "Least-squares estimation of transformation
parameters between two point patterns" (IEEE TPAMI 13(4), 1991): a similarity Sim(3) for
monocular runs, whose scale is unobservable (the default), a rigid SE(3) for metric runs, or
none. Association, alignment and both metrics are evo's (``evo.core.sync``,
``PoseTrajectory3D.align``, ``evo.core.metrics.APE`` / ``RPE``); our :class:`Trajectory` is
handed to evo in memory, not through files.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass, field

import numpy as np
from evo import EvoException
from evo.core import metrics, sync
from evo.core.trajectory import PoseTrajectory3D
from evo.core.units import Unit

from orbslam_hgcn.errors import OrbslamError
from orbslam_hgcn.trajectory import Trajectory

log = logging.getLogger(__name__)

ALIGN_MODES = ("sim3", "se3", "none")
DELTA_UNITS = ("frames", "meters")
MIN_PAIRS = 3  # Umeyama needs three non-collinear point pairs for a unique rotation


class EvaluationError(OrbslamError):
    """Two trajectories cannot be compared (no overlap in time, too few pairs, degenerate)."""


@dataclass(frozen=True)
class ErrorStats:
    """Summary statistics of a set of non-negative errors (one unit: metres or degrees)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float

    @classmethod
    def from_metric(cls, metric: metrics.PE) -> ErrorStats:
        """Read the statistics evo computed for a processed APE/RPE metric."""
        s = metric.get_all_statistics()
        return cls(**{k: float(s[k]) for k in ("rmse", "mean", "median", "std", "min", "max")})

    def to_dict(self) -> dict[str, float]:
        return {
            "rmse": self.rmse, "mean": self.mean, "median": self.median,
            "std": self.std, "min": self.min, "max": self.max,
        }


@dataclass
class EvalResult:
    """Everything one evaluation measured.

    ``S_gt_est`` (4, 4) is the alignment that maps estimate-world points into the
    ground-truth world, ``p_gt ~ S_gt_est @ p_est = scale * R p_est + t`` (identity for
    ``align="none"``, ``scale`` 1 for ``"se3"``). ``gt`` and ``est_aligned`` hold the
    associated pairs (M poses each, same order; ``est_aligned`` keeps the estimate's
    timestamps). ``ate_errors`` (M,) metres per pair; ``rpe_trans_errors`` /
    ``rpe_rot_errors`` (K,) metres / degrees per relative pair, ending at the poses
    ``rpe_ids`` (K,) of the associated sequence. ``gt_span`` is the ground truth over the
    associated time range at its own full rate (for plots).
    """

    align: str
    max_diff: float
    t_offset: float
    num_gt: int
    num_est: int
    num_pairs: int
    gt_time_range: tuple[float, float]
    est_time_range: tuple[float, float]
    scale: float
    S_gt_est: np.ndarray
    ate: ErrorStats
    rpe_delta: float
    rpe_delta_unit: str
    rpe_trans: ErrorStats
    rpe_rot_deg: ErrorStats
    gt: Trajectory
    est_aligned: Trajectory
    ate_errors: np.ndarray
    rpe_trans_errors: np.ndarray
    rpe_rot_errors: np.ndarray
    rpe_ids: np.ndarray
    gt_span: Trajectory
    names: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """All figures as plain JSON-serialisable values (per-pose errors included)."""
        return {
            "gt": self.names.get("gt", ""),
            "est": self.names.get("est", ""),
            "align": self.align,
            "max_diff_s": self.max_diff,
            "t_offset_s": self.t_offset,
            "num_gt_poses": self.num_gt,
            "num_est_poses": self.num_est,
            "num_pairs": self.num_pairs,
            "gt_time_range_s": list(self.gt_time_range),
            "est_time_range_s": list(self.est_time_range),
            "scale": self.scale,
            "S_gt_est": self.S_gt_est.tolist(),
            "ate_m": self.ate.to_dict(),
            "rpe": {
                "delta": self.rpe_delta,
                "delta_unit": self.rpe_delta_unit,
                "num_pairs": int(len(self.rpe_trans_errors)),
                "trans_m": self.rpe_trans.to_dict(),
                "rot_deg": self.rpe_rot_deg.to_dict(),
            },
            "per_pose": {
                "timestamps": self.est_aligned.timestamps.tolist(),
                "ate_m": self.ate_errors.tolist(),
            },
        }


def to_evo(traj: Trajectory, name: str = "") -> PoseTrajectory3D:
    """evo trajectory holding copies of ``traj``'s timestamps and (N, 4, 4) ``T_wc`` poses."""
    return PoseTrajectory3D(
        timestamps=traj.timestamps.copy(),
        poses_se3=[T.copy() for T in traj.poses],
        name=name or None,
    )


def from_evo(traj: PoseTrajectory3D) -> Trajectory:
    """Our :class:`Trajectory` from an evo trajectory (poses copied as an (N, 4, 4) array)."""
    return Trajectory(np.asarray(traj.timestamps, dtype=np.float64), np.array(traj.poses_se3))


def _span(traj: Trajectory) -> str:
    return f"t {traj.timestamps[0]:.3f} .. {traj.timestamps[-1]:.3f} s, {len(traj)} poses"


def _check_args(align: str, delta: float, delta_unit: str, max_diff: float) -> None:
    if align not in ALIGN_MODES:
        raise EvaluationError(f"alignment {align!r} unknown; choose one of {', '.join(ALIGN_MODES)}")
    if delta_unit not in DELTA_UNITS:
        raise EvaluationError(f"RPE delta unit {delta_unit!r} unknown; choose frames or meters")
    if not delta > 0 or (delta_unit == "frames" and float(delta) != int(delta)):
        raise EvaluationError(f"RPE delta {delta} must be positive (and whole for frames)")
    if not max_diff >= 0:
        raise EvaluationError(f"max_diff {max_diff} s must be >= 0")


def associate(
    gt: Trajectory, est: Trajectory, max_diff: float = 0.02, t_offset: float = 0.0,
    gt_name: str = "ground truth", est_name: str = "estimate",
) -> tuple[PoseTrajectory3D, PoseTrajectory3D]:
    """Pair poses by nearest timestamp (evo's ``associate_trajectories``).

    ``t_offset`` is added to the estimate's timestamps for matching only. Returns the two
    evo trajectories reduced to the M associated pairs, in the same order. Raises
    :class:`EvaluationError` naming both time ranges when fewer than three pairs match.
    """
    for traj, name in ((gt, gt_name), (est, est_name)):
        if len(traj) == 0:
            raise EvaluationError(f"{name}: trajectory has no poses")
    e_gt, e_est = to_evo(gt, gt_name), to_evo(est, est_name)
    try:
        a_gt, a_est = sync.associate_trajectories(e_gt, e_est, max_diff=max_diff, offset_2=t_offset)
        n = a_gt.num_poses
    except sync.SyncException:
        n = 0
    if n < MIN_PAIRS:
        raise EvaluationError(
            f"only {n} pose pair(s) associate within {max_diff} s (at least {MIN_PAIRS} needed): "
            f"{gt_name} covers {_span(gt)}; {est_name} covers {_span(est)}"
            + (f" (time offset {t_offset} s)" if t_offset else "")
            + "; do both use the same clock?"
        )
    return a_gt, a_est


def _align(a_est: PoseTrajectory3D, a_gt: PoseTrajectory3D, align: str, est_name: str) -> tuple[float, np.ndarray]:
    """Align ``a_est`` in place onto ``a_gt``; returns (scale, (4, 4) S_gt_est)."""
    S_gt_est = np.eye(4)
    if align == "none":
        return 1.0, S_gt_est
    try:
        R, t, s = a_est.align(a_gt, correct_scale=(align == "sim3"))
    except EvoException as exc:  # degenerate covariance: (nearly) collinear positions
        raise EvaluationError(
            f"{est_name}: cannot align {a_est.num_poses} associated positions to the ground "
            f"truth ({exc}); the camera centres are (nearly) collinear or identical"
        ) from None
    S_gt_est[:3, :3] = s * R
    S_gt_est[:3, 3] = t
    return float(s), S_gt_est


def evaluate(
    gt: Trajectory,
    est: Trajectory,
    align: str = "sim3",
    max_diff: float = 0.02,
    delta: float = 1.0,
    delta_unit: str = "frames",
    *,
    t_offset: float = 0.0,
    gt_name: str = "ground truth",
    est_name: str = "estimate",
) -> EvalResult:
    """ATE and RPE of ``est`` against ``gt`` (Sturm et al., IROS 2012), both ``T_wc`` trajectories.

    Steps: associate by timestamp within ``max_diff`` seconds (after adding ``t_offset``
    to the estimate's stamps); align the associated estimate positions to the ground truth
    with Umeyama's method (1991): ``"sim3"`` (scale too; the monocular default), ``"se3"`` or
    ``"none"``; ATE = evo ``APE`` of the translation part on the aligned pairs; RPE = evo
    ``RPE`` over pose pairs ``delta`` apart (``"frames"``: in index; ``"meters"``: in
    ground-truth path length), translation (m, after alignment, so in ground-truth scale)
    and rotation angle (degrees).

    Raises :class:`EvaluationError` (an :class:`OrbslamError`) when fewer than three poses
    associate, when the associated positions are degenerate for alignment, or when no
    relative pair fits ``delta``.
    """
    _check_args(align, delta, delta_unit, max_diff)
    a_gt, a_est = associate(gt, est, max_diff, t_offset, gt_name, est_name)
    m = a_gt.num_poses
    log.debug("%d of %d estimate poses associate with %s", m, len(est), gt_name)

    aligned = copy.deepcopy(a_est)
    scale, S_gt_est = _align(aligned, a_gt, align, est_name)

    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((a_gt, aligned))

    unit = Unit.frames if delta_unit == "frames" else Unit.meters
    d = int(delta) if delta_unit == "frames" else float(delta)
    rpe_t = metrics.RPE(metrics.PoseRelation.translation_part, d, unit, pairs_from_reference=True)
    rpe_r = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, d, unit, pairs_from_reference=True)
    try:
        rpe_t.process_data((a_gt, aligned))
        rpe_r.process_data((a_gt, aligned))
    except EvoException as exc:
        raise EvaluationError(
            f"RPE with delta {delta} {delta_unit} finds no pose pair among the {m} associated "
            f"poses ({exc}); use a smaller delta"
        ) from None

    t0, t1 = a_gt.timestamps[0] - max_diff, a_gt.timestamps[-1] + max_diff
    keep = (gt.timestamps >= t0) & (gt.timestamps <= t1)
    return EvalResult(
        align=align,
        max_diff=float(max_diff),
        t_offset=float(t_offset),
        num_gt=len(gt),
        num_est=len(est),
        num_pairs=m,
        gt_time_range=(float(gt.timestamps[0]), float(gt.timestamps[-1])),
        est_time_range=(float(est.timestamps[0]), float(est.timestamps[-1])),
        scale=scale,
        S_gt_est=S_gt_est,
        ate=ErrorStats.from_metric(ape),
        rpe_delta=float(delta),
        rpe_delta_unit=delta_unit,
        rpe_trans=ErrorStats.from_metric(rpe_t),
        rpe_rot_deg=ErrorStats.from_metric(rpe_r),
        gt=from_evo(a_gt),
        est_aligned=from_evo(aligned),
        ate_errors=np.asarray(ape.error, dtype=np.float64),
        rpe_trans_errors=np.asarray(rpe_t.error, dtype=np.float64),
        rpe_rot_errors=np.asarray(rpe_r.error, dtype=np.float64),
        rpe_ids=np.asarray(rpe_t.delta_ids, dtype=np.int64),
        gt_span=Trajectory(gt.timestamps[keep], gt.poses[keep]),
        names={"gt": gt_name, "est": est_name},
    )
