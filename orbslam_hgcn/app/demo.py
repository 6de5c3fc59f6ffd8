"""The demo: the built-in synthetic loop, SLAM with the HGCN vocabulary, then the ORB baseline.

:func:`run_demo` renders the synthetic loop round a desk (``orbslam-hgcn synth`` with its
defaults: 30 s, 900 frames, TUM fr3 camera, exact ground truth) into a cache folder, kept
and reused afterwards (written atomically: a render interrupted on the first use is
simply made again on the next); runs the system with loop closing, first with the shipped HGCN
vocabulary and then with the shipped ORB tree, printing each run's ATE as it ends; and
prints the comparison (:mod:`orbslam_hgcn.app.compare`). The first run is recorded
for rerun (``OUT/demo.rrd`` by default).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path

from orbslam_hgcn.config import ThreadsConfig
from orbslam_hgcn.errors import ConfigError
from orbslam_hgcn.app.compare import Comparison, RunOutcome, describe_run, format_markdown, run_comparison
from orbslam_hgcn.outputs import cache_root, check_output_folder
from orbslam_hgcn.viz.sinks import parse_rerun_arg

log = logging.getLogger(__name__)

DEMO_VOCABS = ("hgcn", "orb")  # the paper's vocabulary first, then the baseline


def demo_sequence(
    cache: str | Path | None = None, frames: int | None = None, progress: bool = True, force: bool = False
) -> Path:
    """The demo sequence, rendered on first use: ``CACHE/loop_default`` (900 frames), or
    ``CACHE/loop_<N>frames`` for a loop of ``frames`` frames (300 or more make a full lap;
    fewer are the start of a 10 s lap). The folder is the demo's own: whatever else it
    holds (an older render, files of an interrupted one) is replaced; ``force`` renders it
    again even when it holds the sequence."""
    from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence

    if frames is not None and frames < 1:
        raise ConfigError(f"--frames must be at least 1, found {frames}")
    root = check_output_folder(Path(cache) if cache is not None else cache_root(), "--cache")
    folder = root / ("loop_default" if frames is None else f"loop_{frames}frames")
    reuse = (folder / "scene.json").is_file() and not force
    log.info("%s the demo sequence in %s", "checking" if reuse else "rendering (once)", folder)
    return render_sequence(folder, SynthOptions(frames=frames), force=force, progress=progress, cache=True)


def run_demo(
    out: str | Path = "demo_out",
    frames: int | None = None,
    runs: int = 1,
    cache: str | Path | None = None,
    rerun: Sequence[str] | None = None,
    progress: bool = True,
    sequential: bool = False,
    speed: float | None = None,
    echo: Callable[[str], None] = print,
    force: bool = False,
) -> Comparison:
    """Render (or reuse) the demo sequence, run HGCN then ORB ``runs`` times each, print
    every run's figures and the comparison through ``echo``; write everything under ``out``.

    rerun: ``--rerun`` tokens for the first run; None records ``OUT/demo.rrd``; an empty
    sequence records nothing. sequential: run the stages in order instead of in threads.
    speed: how fast threaded runs take frames, relative to the sequence's 30 Hz (None: 1).
    force: render the sequence again even when the cache holds it.
    """
    if runs < 1:
        raise ConfigError(f"--runs must be at least 1, found {runs}")
    if speed is not None:
        ThreadsConfig(speed=speed)  # a bad value is a ConfigError before the render
    out = check_output_folder(out)
    if rerun:
        parse_rerun_arg(rerun)
    seq = demo_sequence(cache, frames, progress, force)
    echo(f"sequence: {seq}")
    tokens = ["save", str(out / "demo.rrd")] if rerun is None else list(rerun)

    def report(r: RunOutcome) -> None:
        echo(describe_run(r))

    comp = run_comparison(seq, out, kind="tum", runs=runs, vocabs=DEMO_VOCABS, progress=progress,
                          rerun_first=tokens or None, sequential=sequential,
                          speed=speed, on_run=report)
    echo("")
    echo(format_markdown(comp))
    for path in comp.paths.values():
        echo(f"wrote {path}")
    if tokens and tokens[0] == "save" and Path(tokens[1]).is_file():
        echo(f"rerun recording: {tokens[1]} (open it with: rerun {tokens[1]})")
    return comp
