"""Headless plots of trajectory errors: top view, error over time, comparison box plot.

Every function draws on its own :class:`matplotlib.figure.Figure` attached to the Agg
canvas (chosen inside the function, so importing this module changes no global matplotlib
state and works without a display), writes a PNG and returns its path.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

_AXIS_NAMES = ("x", "y", "z")


def _figure(width: float, height: float):
    """A new figure on the Agg (file-only) canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    log.debug("wrote %s", path)
    return path


def error_unit(max_error_m: float) -> tuple[float, str]:
    """(factor, label) to show metre errors in cm below 0.5 m, in metres above."""
    return (100.0, "cm") if max_error_m < 0.5 else (1.0, "m")


def principal_axes(points: np.ndarray) -> np.ndarray:
    """(2, 3) unit directions of largest and second-largest extent of (N, 3) points.

    The plane they span is the one in which the trajectory moves most (PCA). Each axis is
    signed so that its largest component is positive, which keeps an axis that lies along
    a world axis reading like that world axis.
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(P) < 2:
        return np.eye(3)[:2]
    C = np.cov((P - P.mean(axis=0)).T)
    w, V = np.linalg.eigh(C)  # ascending eigenvalues
    axes = V[:, np.argsort(w)[::-1][:2]].T
    signs = np.sign(axes[np.arange(2), np.argmax(np.abs(axes), axis=1)])
    return axes * signs[:, None]


def axis_label(axis: np.ndarray, tol_deg: float = 5.0) -> str:
    """Name of a (3,) unit direction: ``x``/``-y``/... when within ``tol_deg`` of a world axis,
    otherwise its components, e.g. ``(0.71, 0.00, 0.71)``."""
    k = int(np.argmax(np.abs(axis)))
    if np.degrees(np.arccos(np.clip(abs(axis[k]), -1.0, 1.0))) <= tol_deg:
        return ("-" if axis[k] < 0 else "") + _AXIS_NAMES[k]
    return "(" + ", ".join(f"{c:.2f}" for c in axis) + ")"


def plot_top_view(
    gt_positions: np.ndarray,
    est_positions: np.ndarray,
    errors: np.ndarray,
    path: str | Path,
    title: str = "",
) -> Path:
    """Aligned estimate over the ground truth, seen along the ground truth's least extent.

    gt_positions: (N, 3) metres, drawn as a dashed grey line; est_positions: (M, 3) metres
    in the same world frame, drawn as a line and points coloured by ``errors`` (M,) metres
    (ATE per pose) with a colour bar. Both are projected onto the two principal axes of the
    ground truth (:func:`principal_axes`), with equal scale on both axes.
    """
    from matplotlib.collections import LineCollection

    gt = np.asarray(gt_positions, dtype=np.float64).reshape(-1, 3)
    est = np.asarray(est_positions, dtype=np.float64).reshape(-1, 3)
    err = np.asarray(errors, dtype=np.float64).reshape(-1)
    axes = principal_axes(gt if len(gt) >= 2 else est)
    g2, e2 = gt @ axes.T, est @ axes.T
    factor, unit = error_unit(float(err.max()) if err.size else 0.0)
    c = err * factor
    vmax = float(c.max()) if c.size and c.max() > 0 else 1.0

    fig = _figure(7.5, 6.0)
    ax = fig.add_subplot()
    cmap = "viridis"
    ax.plot(g2[:, 0], g2[:, 1], "--", color="0.45", lw=1.3, label="ground truth", zorder=1)
    if len(e2) >= 2:
        segs = np.stack([e2[:-1], e2[1:]], axis=1)
        lc = LineCollection(segs, cmap=cmap, linewidths=1.3, zorder=2)
        lc.set_array(0.5 * (c[:-1] + c[1:]))
        lc.set_clim(0.0, vmax)
        ax.add_collection(lc)
    # Dots mark the poses of sparse (e.g. keyframe) trajectories; dense ones read as a line.
    size = 10.0 if len(e2) <= 400 else 0.0
    sc = ax.scatter(e2[:, 0], e2[:, 1], c=c, cmap=cmap, vmin=0.0, vmax=vmax, s=size, zorder=3)
    fig.colorbar(sc, ax=ax, label=f"ATE [{unit}]")
    ax.plot([], [], "-", color=sc.cmap(0.5), lw=1.5, label="estimate (aligned), colour = ATE")
    ax.plot(g2[:1, 0], g2[:1, 1], "o", mfc="none", mec="k", ms=9, zorder=4, label="start")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel(f"along {axis_label(axes[0])} [m]")
    ax.set_ylabel(f"along {axis_label(axes[1])} [m]")
    ax.grid(True, color="0.9")
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path)


def plot_error_over_time(
    timestamps: np.ndarray,
    errors: np.ndarray,
    path: str | Path,
    title: str = "",
    ylabel: str = "ATE",
) -> Path:
    """Per-pose error (M,) metres against time (M,) seconds, from the first stamp; RMSE and
    median drawn as horizontal lines."""
    t = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    err = np.asarray(errors, dtype=np.float64).reshape(-1)
    factor, unit = error_unit(float(err.max()) if err.size else 0.0)
    e = err * factor
    fig = _figure(8.0, 3.6)
    ax = fig.add_subplot()
    t_rel = t - t[0] if t.size else t
    ax.plot(t_rel, e, "-", color="tab:blue", lw=1.2)
    if e.size:
        rmse = float(np.sqrt(np.mean(e**2)))
        ax.axhline(rmse, color="tab:red", lw=1.0, label=f"RMSE {rmse:.3g} {unit}")
        ax.axhline(float(np.median(e)), color="tab:green", lw=1.0, ls="--",
                   label=f"median {np.median(e):.3g} {unit}")
        ax.legend(loc="upper left", fontsize=8)
    ax.set_xlabel("time since first pose [s]")
    ax.set_ylabel(f"{ylabel} [{unit}]")
    ax.set_ylim(bottom=0.0)
    ax.grid(True, color="0.9")
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path)


def box_plot(
    groups: Mapping[str, Sequence[float]],
    path: str | Path,
    ylabel: str,
    title: str = "",
) -> Path:
    """One box per named group of values (e.g. ATE RMSE of several runs per vocabulary).

    groups: {label: values}, drawn left to right in the mapping's order; each box shows
    median and quartiles, whiskers at 1.5 IQR, and every value as a jittered dot (the
    jitter is seeded, so the image is reproducible). The value axis starts at zero when no
    value is negative, so that a small difference does not fill the picture; with at most
    one value per group the plot says that it shows no spread and cannot rank the groups.
    """
    labels = list(groups)
    data = [np.asarray(groups[k], dtype=np.float64).reshape(-1) for k in labels]
    fig = _figure(max(4.0, 1.2 * len(labels) + 2.0), 4.2)
    ax = fig.add_subplot()
    if labels:
        ax.boxplot(data, tick_labels=labels, showfliers=False, widths=0.5)
        rng = np.random.default_rng(0)
        for i, d in enumerate(data, start=1):
            ax.plot(i + rng.uniform(-0.12, 0.12, size=d.size), d, "o", ms=3.5,
                    color="tab:blue", alpha=0.7)
    values = np.concatenate(data) if data else np.zeros(0)
    values = values[np.isfinite(values)]
    if values.size and values.min() >= 0:
        ax.set_ylim(0.0, 1.1 * values.max() if values.max() > 0 else 1.0)
    if labels and max(d.size for d in data) < 2:
        ax.text(0.5, 0.03, "one value per group: no spread shown, so this cannot rank the groups",
                transform=ax.transAxes, ha="center", va="bottom", fontsize=8, color="0.3")
    ax.set_ylabel(ylabel)
    ax.grid(True, axis="y", color="0.9")
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path)
