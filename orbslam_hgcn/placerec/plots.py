"""Figures of a loop-closure comparison: confusion matrices, PR curves, and their JSON.

Matplotlib's Agg backend is selected inside each function (never at import time).
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_confusion(
    path: str | Path, scores: np.ndarray, gt: np.ndarray, title: str, min_gap: int = 1,
    *, log_scores: np.ndarray | None = None,
) -> Path:
    """PNG of a detector's (n, n) confusion matrix (lower triangle) beside the ground truth.

    log_scores: natural log of the scores where the detector has it (FAB-MAP): then
    ``log10`` is shown, floored at its 5th percentile, since posteriors span hundreds of
    decades and a linear scale shows only the few near 1.
    """
    plt = _pyplot()
    n = scores.shape[0]
    lower = np.tri(n, n, -max(1, min_gap), dtype=bool)
    shown = np.where(lower, scores, np.nan)
    if log_scores is not None:
        shown = np.where(lower, log_scores / np.log(10.0), np.nan)
        finite = shown[np.isfinite(shown)]
        vmin = float(np.percentile(finite, 5)) if finite.size else -12.0
        shown = np.clip(shown, vmin, 0.0)
        vmax, label = 0.0, "log10 score"
    else:
        vmin, vmax, label = 0.0, max(1e-12, float(np.nanmax(shown))) if lower.any() else 1.0, "score"
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.2))
    fig.subplots_adjust(left=0.06, right=0.98, wspace=0.25)
    im = axes[0].imshow(shown, cmap="viridis", vmin=vmin, vmax=vmax, interpolation="nearest")
    axes[0].set_title(f"{title}: {label} (query i, earlier image j)")
    fig.colorbar(im, ax=axes[0], shrink=0.8)
    axes[1].imshow(np.where(lower, gt, np.nan), cmap="gray_r", vmin=0, vmax=1, interpolation="nearest")
    axes[1].set_title("ground truth loops")
    for ax in axes:
        ax.set_xlabel("image j")
        ax.set_ylabel("query image i")
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_pr_curves(path: str | Path, curves: dict[str, tuple[np.ndarray, np.ndarray]], title: str = "") -> Path:
    """PNG of precision against recall for every method: ``{label: (recall, precision)}``."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 5.2))
    for label, (recall, precision) in curves.items():
        if len(recall):
            ax.step(np.r_[0.0, recall], np.r_[precision[0], precision], where="pre", label=label)
        else:
            ax.plot([], [], label=f"{label} (no match)")
    ax.set_xlim(0, 1.0)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision (accuracy)")
    ax.set_title(title or "loop-closure detection")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _clean(obj):
    """JSON-safe copy: arrays to lists, NaN/inf to None."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _clean(obj.tolist())
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    return obj


def write_json(path: str | Path, data: dict) -> Path:
    """Write ``data`` (arrays allowed; NaN written as null) as indented JSON."""
    path = Path(path)
    path.write_text(json.dumps(_clean(data), indent=1), encoding="utf-8")
    return path
