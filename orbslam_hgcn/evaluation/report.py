"""Write an evaluation to disk (JSON of all figures + PNG plots) and format it as a table."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from orbslam_hgcn.errors import DatasetError
from orbslam_hgcn.evaluation.ate import EvalResult
from orbslam_hgcn.evaluation.plots import plot_error_over_time, plot_top_view

log = logging.getLogger(__name__)

REPORT_VERSION = 1


def _title(result: EvalResult) -> str:
    scale = f", scale {result.scale:.4g}" if result.align == "sim3" else ""
    return (
        f"ATE RMSE {100 * result.ate.rmse:.2f} cm ({result.ate.rmse:.4f} m), "
        f"{result.align} alignment{scale}, {result.num_pairs} pairs"
    )


def write_report(result: EvalResult, out_dir: str | Path, plot: bool = True, stem: str = "ate") -> dict[str, Path]:
    """Write ``<stem>.json`` (every figure of :meth:`EvalResult.to_dict`) into ``out_dir``
    and, when ``plot``, ``<stem>.png`` (top view of the aligned estimate over the ground
    truth, coloured by ATE) and ``<stem>_over_time.png``. Returns {kind: path}."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = {"report_version": REPORT_VERSION, **result.to_dict()}
    paths = {"json": out / f"{stem}.json"}
    paths["json"].write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    if plot:
        title = _title(result)
        paths["top"] = plot_top_view(
            result.gt_span.positions, result.est_aligned.positions, result.ate_errors,
            out / f"{stem}.png", title=title,
        )
        paths["over_time"] = plot_error_over_time(
            result.est_aligned.timestamps, result.ate_errors, out / f"{stem}_over_time.png",
            title=title, ylabel="ATE",
        )
    log.debug("wrote %s", ", ".join(str(p) for p in paths.values()))
    return paths


def read_report(path: str | Path) -> dict:
    """Load a JSON written by :func:`write_report`; errors name the file."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DatasetError(f"{path}: evaluation report not found") from None
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}:{exc.lineno}: not valid JSON ({exc.msg})") from None
    if not isinstance(data, dict) or "ate_m" not in data:
        raise DatasetError(f"{path}: not an evaluation report (no 'ate_m')")
    return data


def format_table(result: EvalResult) -> str:
    """A small plain-text table of the main figures."""
    a, rt, rr = result.ate, result.rpe_trans, result.rpe_rot_deg
    unit = "frames" if result.rpe_delta_unit == "frames" else "m"
    delta = f"{result.rpe_delta:g} {unit}"
    rows = [
        ("pairs", f"{result.num_pairs} (of {result.num_est} estimate, {result.num_gt} ground-truth poses)"),
        ("alignment", result.align + (f", scale {result.scale:.6g}" if result.align == "sim3" else "")),
        ("ATE RMSE", f"{100 * a.rmse:9.3f} cm  {a.rmse:10.5f} m"),
        ("ATE mean", f"{100 * a.mean:9.3f} cm  {a.mean:10.5f} m"),
        ("ATE median", f"{100 * a.median:9.3f} cm  {a.median:10.5f} m"),
        ("ATE max", f"{100 * a.max:9.3f} cm  {a.max:10.5f} m"),
        (f"RPE trans RMSE ({delta})", f"{100 * rt.rmse:9.3f} cm  {rt.rmse:10.5f} m"),
        (f"RPE trans mean ({delta})", f"{100 * rt.mean:9.3f} cm  {rt.mean:10.5f} m"),
        (f"RPE rot RMSE ({delta})", f"{rr.rmse:9.3f} deg"),
        (f"RPE rot mean ({delta})", f"{rr.mean:9.3f} deg"),
    ]
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
