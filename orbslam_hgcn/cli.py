"""The ``orbslam-hgcn`` command: one entry point, one subcommand per user task.

Each subcommand has a ``_add_<name>(sub)`` function that declares its arguments and binds
a handler; the handler parses nothing itself and calls a typed function in the package.
User errors (:class:`OrbslamError`) print one line on stderr and exit with status 2, found
before any work (arguments, inputs, the output folder); a stage that failed
(:class:`StageError`: a worker thread, a child process) with status 4; Ctrl-C exits with
status 130 and SIGTERM with 143, for every command, keeping the results made so far where
the command has results. ``run`` has its own statuses for each way a run can end
(``orbslam-hgcn run --help``), and writes its results whichever it is; ``compare``,
``demo`` and ``sweep`` exit with 1 when a run failed.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from collections.abc import Callable, Sequence

from orbslam_hgcn import __version__
from orbslam_hgcn.childprocess import set_stopping
from orbslam_hgcn.errors import OrbslamError, StageError, Terminated

log = logging.getLogger("orbslam_hgcn")

# Subcommand registrars, in the order ``--help`` lists them.
_REGISTRARS: list[Callable[[argparse._SubParsersAction], None]] = []


def subcommand(fn: Callable[[argparse._SubParsersAction], None]) -> Callable:
    """Decorator: register a function that adds one subparser (with ``set_defaults(func=...)``)."""
    _REGISTRARS.append(fn)
    return fn


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="orbslam-hgcn",
        description="Monocular ORB-SLAM-style visual SLAM with an HGCN visual vocabulary.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for registrar in _REGISTRARS:
        registrar(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # Other libraries (faiss, matplotlib, ...) log only warnings; the package logs info.
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    log.setLevel(logging.DEBUG if args.verbose else logging.INFO)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    # SIGTERM ends every command as Ctrl-C does (run, compare, sweep, demo keep their results).
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        return int(args.func(args) or 0)
    except StageError as exc:  # its message may carry a child process's traceback: one line
        lines = str(exc).strip().splitlines() or [type(exc).__name__]
        print(f"orbslam-hgcn {args.command}: error: {exc.stage} failed: {lines[0]}", file=sys.stderr)
        return 4
    except OrbslamError as exc:
        print(f"orbslam-hgcn {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except Terminated:
        print(f"orbslam-hgcn {args.command}: terminated (SIGTERM)", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print(f"orbslam-hgcn {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped to a reader that stopped (| head): stop quietly, as cat does
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except OSError:
            pass
        return 141
    finally:
        signal.signal(signal.SIGTERM, previous)
        set_stopping(False)


def _terminate(signum: int, frame: object) -> None:
    # The child processes got the signal too when it was sent to the process group: they
    # outlive it while the command stops them (orbslam_hgcn.childprocess); none starts again.
    set_stopping(True)
    raise Terminated()


def _interrupted_status(terminated: bool) -> int:
    """Exit status of a command that stopped on a signal and kept its results."""
    return 143 if terminated else 130


# --- Subcommands ------------------------------------------------------------------------
# Each block below adds one subcommand; handlers import their stage lazily so that
# ``orbslam-hgcn --help`` stays fast.


@subcommand
def _add_eval(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "eval",
        help="ATE/RPE of an estimated trajectory against ground truth (TUM files)",
        description="Associate by timestamp, align (Umeyama), print ATE/RPE, write ate.json "
        "and plots.",
    )
    p.add_argument("--gt", required=True, help="ground-truth trajectory, TUM format")
    p.add_argument("--est", required=True, help="estimated trajectory, TUM format")
    p.add_argument("--align", choices=("sim3", "se3", "none"), default="sim3",
                   help="alignment before ATE (default sim3: monocular scale unknown)")
    p.add_argument("--max-diff", type=float, default=0.02,
                   help="largest timestamp gap for a pose pair, seconds (default 0.02)")
    p.add_argument("--t-offset", type=float, default=0.0,
                   help="seconds added to the estimate's timestamps when associating")
    p.add_argument("--delta", type=float, default=1.0, help="RPE step (default 1)")
    p.add_argument("--delta-unit", choices=("frames", "meters"), default="frames",
                   help="unit of --delta (default frames)")
    p.add_argument("--out", default=None, help="output folder (default: the folder of --est)")
    p.add_argument("--no-plot", action="store_true", help="write ate.json only, no PNGs")
    p.set_defaults(func=_run_eval)


def _run_eval(args: argparse.Namespace) -> int:
    from pathlib import Path

    from orbslam_hgcn.evaluation.ate import evaluate
    from orbslam_hgcn.evaluation.report import format_table, write_report
    from orbslam_hgcn.outputs import check_output_folder
    from orbslam_hgcn.trajectory import read_tum

    gt_path, est_path = Path(args.gt), Path(args.est)
    out = check_output_folder(args.out if args.out else est_path.resolve().parent)
    result = evaluate(
        read_tum(gt_path), read_tum(est_path), align=args.align, max_diff=args.max_diff,
        delta=args.delta, delta_unit=args.delta_unit, t_offset=args.t_offset,
        gt_name=str(gt_path), est_name=str(est_path),
    )
    paths = write_report(result, out, plot=not args.no_plot)
    print(format_table(result))
    for path in paths.values():
        print(f"wrote {path}")
    return 0


@subcommand
def _add_lcd(sub: argparse._SubParsersAction) -> None:
    from orbslam_hgcn.cli_lcd import add_lcd  # its many arguments live beside its handler

    add_lcd(sub)


@subcommand
def _add_viz_demo(sub: argparse._SubParsersAction) -> None:
    from orbslam_hgcn.viz.sinks import add_rerun_argument

    p = sub.add_parser(
        "viz-demo",
        help="log a synthetic SLAM run to rerun (checks the viewer set-up)",
        description="A camera circling random map points, closing one loop; logged as a SLAM "
        "run would be. Without a display, spawn saves to an .rrd instead.",
    )
    add_rerun_argument(p)
    p.add_argument("--frames", type=int, default=120, help="frames to log (default 120)")
    p.set_defaults(func=_run_viz_demo)


def _run_viz_demo(args: argparse.Namespace) -> int:
    from orbslam_hgcn.errors import ConfigError
    from orbslam_hgcn.viz.demo import demo_camera, fake_run, replay
    from orbslam_hgcn.viz.rerun_logger import RerunLogger
    from orbslam_hgcn.viz.sinks import parse_rerun_arg

    if args.frames < 1:
        raise ConfigError(f"--frames: must be at least 1, found {args.frames}")
    mode, target = parse_rerun_arg(args.rerun or ["spawn"])
    with RerunLogger(demo_camera(), mode, target, recording_name="viz-demo") as logger:
        replay(logger, fake_run(args.frames, n_points=5000, n_keypoints=500, loop_at=(args.frames * 2) // 3 or None))
    print(f"rerun {logger.mode}: {logger.target}")
    return 0


_SYNTH_DESCRIPTION = """\
Render a synthetic sequence with exact ground truth into OUT: an office (a loop round a desk,
or a replayed TUM trajectory) or a KITTI-like street drive, in the TUM RGB-D layout (rgb/,
rgb.txt, groundtruth.txt) or the KITTI odometry layout (sequences/NN/image_0/, times.txt,
calib.txt, poses/NN.txt), with camera.yaml and scene.json (loop_gt.npy, depth on request);
frames as PNG files, or JPEG files with --image-format jpg.

presets (--preset NAME; options given beside a preset override its values):
  office_loop      the demo's 30 s office loop, clean, with loop_gt.npy
  fr3_replay_hard  the fr3 long-office camera path replayed (2,613 frames at 30 Hz; --gt to
                   replay another), blurred along the image motion over 16 ms exposures,
                   auto-exposure steps of 30-50 % every 2-6 s settling over 6 frames,
                   vignetting (corners at 70 %), noise 2, exposure drift 0.1, JPEG quality 75
  street           a 60 s street drive with KITTI 00's camera (1241x376, 10 Hz) in the KITTI
                   layout, the same degradations with 5 ms exposures, auto-exposure settling
                   over 3 frames, noise 1.5, JPEG quality 80
"""


@subcommand
def _add_synth(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "synth",
        help="render a synthetic sequence (office or street; TUM or KITTI layout) with exact ground truth",
        description=_SYNTH_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--preset", choices=("office_loop", "fr3_replay_hard", "street"),
                   help="a named option set (see above)")
    p.add_argument("--scene", choices=("office", "street"),
                   help="office room (default) or street drive (KITTI 00's camera, 45 s by default)")
    p.add_argument("--layout", choices=("tum", "kitti"), help="output layout (default tum)")
    p.add_argument("--sequence", type=int, help="sequence number NN of the KITTI layout (default 0)")
    p.add_argument("--trajectory", choices=("loop", "replay"),
                   help="office: generated loop round the desk (default) or a replayed TUM ground truth")
    p.add_argument("--gt", help="TUM ground-truth file to replay (with --trajectory replay)")
    n = p.add_mutually_exclusive_group()
    n.add_argument("--frames", type=int, help="number of frames (default: 30 s of loop, or the whole replay)")
    n.add_argument("--duration", type=float, help="length in seconds")
    p.add_argument("--fps", type=float, help="frame rate (default 30; street 10)")
    p.add_argument("--noise", type=float, help="Gaussian sensor noise sigma in grey levels (default 0)")
    p.add_argument("--exposure-drift", type=float,
                   help="slow relative gain swing, e.g. 0.2 for +-20%% (default 0)")
    p.add_argument("--motion-blur", nargs="?", const="subframes", choices=("subframes", "flow"),
                   help="motion blur over the shutter time: the average of sub-frame renders (exact; the "
                   "default mode), or 'flow': each pixel blurred along its own image motion, from its depth "
                   "and the camera poses (faster, any blur length)")
    p.add_argument("--shutter", type=float, help="exposure time as a fraction of the frame interval (default 0.5)")
    p.add_argument("--vignetting", type=float, help="darkening of the image corners, e.g. 0.3 (default 0)")
    p.add_argument("--exposure-steps", type=float,
                   help="sudden auto-exposure steps of +-(0.75-1.25) x this, e.g. 0.4 for 30-50%% (default 0)")
    p.add_argument("--exposure-step-interval", type=float, help="mean seconds between exposure steps (default 4)")
    p.add_argument("--exposure-settle", type=int,
                   help="frames the auto-exposure takes to undo a step, to 5%% (default 4)")
    p.add_argument("--jpeg-quality", type=int,
                   help="JPEG encode/decode at this quality, 1-100 (default 0: none); with --image-format jpg, "
                   "the quality of the JPEG files (default 90)")
    p.add_argument("--image-format", choices=("png", "jpg"),
                   help="frame files: png (default) or jpg, written at --jpeg-quality (the one compression: "
                   "no JPEG round trip before writing); beside a preset, changes only the format")
    p.add_argument("--fog", type=float,
                   help="stretches of fog and flat light (one per 25 s, 3-6 s long): the contrast lost at the "
                   "scene's typical depth, e.g. 0.7 (default 0)")
    p.add_argument("--seed", type=int, help="seed of noise, exposure drift and steps, fog (default 0)")
    p.add_argument("--scene-seed", type=int,
                   help="seed of the layout and the camera path's wobble (and of the textures) (default 0)")
    p.add_argument("--texture-seed", type=int, help="seed of the surface textures (default: the scene seed)")
    p.add_argument("--repeated-texture", action="store_true", default=None,
                   help="one texture patch repeated on every surface (a false-loop test)")
    p.add_argument("--texel-scale", type=float, help="texel sizes times this (coarser, faster) (default 1)")
    p.add_argument("--draw-distance", type=float, metavar="M",
                   help="leave surface tiles farther than M metres (along the view) to the background; bounds the "
                   "render time of long straight streets (default 0: draw everything)")
    p.add_argument("--loop-gt", action="store_true", default=None,
                   help="write loop_gt.npy (frame pairs that revisit a place)")
    p.add_argument("--laps", type=int, help="office loop: times round the desk, each lap beside the others (default 1)")
    p.add_argument("--depth", action="store_true", default=None,
                   help="also write depth images (TUM: 5000 per metre; KITTI layout: 256 per metre)")
    p.add_argument("--force", action="store_true", help="overwrite a non-empty output folder")
    p.set_defaults(func=_run_synth)


def _run_synth(args: argparse.Namespace) -> int:
    from orbslam_hgcn.synth.sequence import render_sequence, synth_options

    given = {
        "scene": args.scene, "layout": args.layout, "kitti_sequence": args.sequence, "trajectory": args.trajectory,
        "gt": args.gt, "frames": args.frames, "duration": args.duration, "fps": args.fps, "noise": args.noise,
        "exposure_drift": args.exposure_drift, "motion_blur": None if args.motion_blur is None else True,
        "motion_blur_mode": args.motion_blur, "shutter": args.shutter, "vignetting": args.vignetting,
        "exposure_steps": args.exposure_steps, "exposure_step_interval": args.exposure_step_interval,
        "exposure_settle": args.exposure_settle, "jpeg_quality": args.jpeg_quality, "fog": args.fog,
        "seed": args.seed, "scene_seed": args.scene_seed, "texture_seed": args.texture_seed,
        "repeated_texture": args.repeated_texture, "texel_scale": args.texel_scale, "loop_gt": args.loop_gt,
        "depth": args.depth, "laps": args.laps, "image_format": args.image_format,
        "draw_distance": args.draw_distance,
    }
    from orbslam_hgcn.outputs import check_output_folder

    options = synth_options(args.preset, **{k: v for k, v in given.items() if v is not None})
    out = render_sequence(check_output_folder(args.out), options, force=args.force)
    print(out)
    return 0


def _add_sequence_arguments(p: argparse.ArgumentParser) -> None:
    """The dataset path and --dataset kind (run, compare)."""
    p.add_argument("path", help="dataset folder, video file, or (run) a live source: cam:N for camera device N, "
                   "or a stream URL (rtsp://, http://, ...) with --config giving its camera")
    p.add_argument("--dataset", choices=("tum", "euroc", "kitti", "folder", "video"), default=None,
                   help="dataset kind (default: detected from the folder)")


def _add_sequential_argument(p: argparse.ArgumentParser) -> None:
    """--sequential and --speed (run, compare, demo)."""
    p.add_argument("--sequential", action="store_true",
                   help="run local mapping and loop closing in order after each frame (reproducible), "
                   "instead of in worker threads")
    p.add_argument("--speed", type=float, default=None, metavar="X",
                   help="threaded runs: take frames no faster than X times the rate of their timestamps, as "
                   "a camera delivers them (default 1, or threads.speed of --config; 0: as fast as they are "
                   "processed, which leaves local mapping less time per frame and so fewer keyframes)")


@subcommand
def _add_run(sub: argparse._SubParsersAction) -> None:
    from orbslam_hgcn.app.ending import exit_status_help

    p = sub.add_parser(
        "run",
        help="run monocular SLAM over a dataset; write trajectories and stats",
        description="Track and map a sequence (local mapping and loop closing in worker threads, or in "
        "order with --sequential) and write "
        "KeyFrameTrajectory.txt, CameraTrajectory.txt (TUM format) and stats.json; prints the "
        "ATE after Sim(3) alignment when the dataset has ground truth. Whatever ends the run, the results "
        "of the frames processed are written; stats.json says \"complete\": false and why when it ended early.",
        epilog=exit_status_help(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_sequence_arguments(p)
    p.add_argument("--config", default=None,
                   help="YAML with the camera and/or stage sections (orb, initializer, tracking, "
                   "local_mapping, backend, map, system); a shipped camera name such as tum_fr3")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--no-loop", action="store_true", help="run without loop closing")
    p.add_argument("--vocab", default=None, metavar="orb|hgcn|kmeans|orb10k|FILE|none",
                   help="visual vocabulary: a shipped one (orb, hgcn, kmeans, orb10k, hgcn_graph, hgcn_graph_mean), "
                   "a vocabulary file, or none "
                   "(default kmeans, the arm that won the vocabulary ablation; needed for loop closing and relocalisation)")
    p.add_argument("--max-frames", type=int, default=None, help="process at most this many frames")
    p.add_argument("--on-bad-frame", choices=("skip", "stop"), default="skip",
                   help="a frame whose image cannot be read (missing, empty, truncated, corrupt, wrong size): "
                   "skip it with a warning and count it (default), or stop the run there (exit status 3)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    from orbslam_hgcn.viz.sinks import add_rerun_argument

    add_rerun_argument(p)
    p.add_argument("--save-map", default=None, metavar="FILE", help="write the map at the end (.npz)")
    p.add_argument("--load-map", default=None, metavar="FILE",
                   help="start from a saved map (relocalise on it first); the vocabulary defaults to the map's")
    p.add_argument("--localization", action="store_true",
                   help="with --load-map: track against the map without changing it (no new keyframes)")
    _add_sequential_argument(p)
    p.add_argument("--drop-late", action="store_true", default=None,
                   help="paced threaded runs: drop a frame that waits longer than threads.frame_buffer_s (0.5 s), "
                   "as a live camera's driver does, and count it; by default every frame of a recorded sequence "
                   "is processed and a slow run falls behind the clock (stats.json: real_time); a live source "
                   "drops late frames unless --keep-late")
    p.add_argument("--keep-late", action="store_true",
                   help="a live source: process every frame it delivers, falling behind the camera if need be")
    p.add_argument("--export-ply", default=None, metavar="FILE.ply",
                   help="write the map's points (coloured from the images; by observation count for a live "
                   "source) and keyframe poses (FILE_keyframes.ply) as PLY for MeshLab, Open3D, CloudCompare")
    p.set_defaults(func=_run_run)


def _drop_late(args: argparse.Namespace) -> bool | None:
    if args.keep_late and args.drop_late:
        raise OrbslamError("--drop-late and --keep-late: choose one")
    return False if args.keep_late else args.drop_late


def _run_run(args: argparse.Namespace) -> int:
    from orbslam_hgcn.app.run import format_report, run_dataset

    # A flag not given is None: the config decides (orbslam_hgcn.app.settings).
    report = run_dataset(
        args.path, args.out, kind=args.dataset, config=args.config, max_frames=args.max_frames,
        loop_closing=False if args.no_loop else None, progress=not args.no_progress, vocab=args.vocab,
        rerun=args.rerun, load_map=args.load_map, save_map=args.save_map, localization=args.localization,
        sequential=args.sequential or None, speed=args.speed, on_bad_frame=args.on_bad_frame,
        drop_late=_drop_late(args), export_ply=args.export_ply,
    )
    for line in format_report(report):
        print(line)
    for path in report.paths.values():
        print(f"wrote {path}")
    if not report.complete:
        print(f"orbslam-hgcn run: {report.end.kind.replace('_', ' ')}: {report.end.reason}; the results of the "
              f"frames processed are in {args.out}", file=sys.stderr)  # fmt: skip
    return report.exit_status


@subcommand
def _add_vocab(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("vocab", help="train, inspect or export a visual vocabulary (HGCN, k-means or DBoW2-style ORB tree)")
    vsub = p.add_subparsers(dest="vocab_command", metavar="ACTION", required=True)
    t = vsub.add_parser("train", help="train a vocabulary from images")
    t.add_argument("--kind", choices=("hgcn", "orb", "kmeans"), required=True,
                   help="vocabulary kind (kmeans: the HGCN vocabulary's PCA and seed k-means without the network)")
    t.add_argument("--images", nargs="+", required=True,
                   help="image sources: TUM/EuRoC/KITTI sequence folders, image folders or image files")
    t.add_argument("--words", type=int, default=None,
                   help="word count (hgcn, kmeans: exactly, default 8000; orb: sets the depth L = round(log_k words))")
    t.add_argument("--out", required=True, help="output vocabulary file (.npz)")
    t.add_argument("--max-images", type=int, default=None, help="use at most this many images, evenly spread")
    t.add_argument("--n-features", "--features", dest="n_features", type=int, default=1000,
                   help="ORB features per image (default 1000; --features is the former name)")
    t.add_argument("--levels", type=int, default=None, help="orb: tree depth L (default 6, as ORB-SLAM's ORBvoc)")
    t.add_argument("--branching", type=int, default=None, help="orb: children per node k (default 10)")
    t.add_argument("--label-fraction", type=float, default=None, help="hgcn: fraction of seeded nodes (0.1)")
    t.add_argument("--epochs", type=int, default=None,
                   help="hgcn: full-batch epochs at most (60; training stops earlier on held-out seeds)")
    t.add_argument("--config", default=None,
                   help="YAML with 'hgcn:' / 'vocab_tree:' sections overriding training parameters")
    t.add_argument("--trained-on", default=None, help="description of the imagery kept in the metadata")
    t.add_argument("--no-tracks", action="store_true",
                   help="hgcn: do not share seed labels along feature tracks matched between consecutive "
                        "images of a sequence (shared by default)")
    t.add_argument("--keep-cache", action="store_true", help="keep the descriptor cache <out>.descriptors.npz")
    t.add_argument("--device", default="auto",
                   help="hgcn: torch device to train on: auto (default: a CUDA GPU when torch sees one, else the "
                   "CPU), cpu, cuda, cuda:N")
    t.add_argument("--jobs", type=int, default=1,
                   help="extract the descriptors in shards on a local Ray instance with this many jobs (default 1: "
                   "in this process)")
    t.add_argument("--address", default=None, help="extract the descriptors on the Ray cluster at this address")
    t.set_defaults(func=_run_vocab_train)
    i = vsub.add_parser("info", help="print a vocabulary's metadata")
    i.add_argument("file", help="vocabulary file, or a shipped one: 'orb', 'hgcn', 'kmeans', 'orb10k', "
                   "'hgcn_graph', 'hgcn_graph_mean'")
    i.set_defaults(func=_run_vocab_info)
    e = vsub.add_parser("export", help="write an ORB-tree vocabulary as a DBoW2 text file (ORB-SLAM2/3's ORBvoc.txt)")
    e.add_argument("file", help="ORB-tree vocabulary file, or 'orb' for the shipped default")
    e.add_argument("--format", choices=("dbow2",), default="dbow2",
                   help="dbow2: DBoW2's text format, as TemplatedVocabulary::loadFromTextFile reads it")
    e.add_argument("--out", required=True, help="output file (e.g. ORBvoc.txt)")
    e.set_defaults(func=_run_vocab_export)


def _run_vocab_train(args: argparse.Namespace) -> int:
    import dataclasses

    from orbslam_hgcn.config import HgcnTrainConfig, TreeTrainConfig, load_yaml, section_from_yaml
    from orbslam_hgcn.vocabulary.training.train import train_from_images

    data = load_yaml(args.config) if args.config else {}
    tree = section_from_yaml(TreeTrainConfig, data, args.config or "", "vocab_tree")
    hgcn = section_from_yaml(HgcnTrainConfig, data, args.config or "", "hgcn")
    if args.levels is not None:
        tree = dataclasses.replace(tree, levels=args.levels)
    if args.branching is not None:
        tree = dataclasses.replace(tree, k=args.branching)
    if args.label_fraction is not None:
        hgcn = dataclasses.replace(hgcn, label_fraction=args.label_fraction)
    if args.epochs is not None:
        hgcn = dataclasses.replace(hgcn, epochs=args.epochs)
    words = args.words if (args.kind != "orb" or args.levels is None) else None
    vocab = train_from_images(
        args.kind, args.images, args.out, words=words, max_images=args.max_images, n_features=args.n_features,
        tree=tree, hgcn=hgcn, trained_on=args.trained_on, tracks=not args.no_tracks, keep_cache=args.keep_cache,
        device=args.device, jobs=args.jobs, address=args.address,
    )
    print(vocab.metadata.describe())
    print(f"wrote {args.out}")
    return 0


def _run_vocab_info(args: argparse.Namespace) -> int:
    from orbslam_hgcn.vocabulary import load_vocabulary
    from orbslam_hgcn.vocabulary.loading import which_vocabulary

    vocab = load_vocabulary(args.file)
    print(vocab.metadata.describe())
    print()
    print(which_vocabulary())
    return 0


def _run_vocab_export(args: argparse.Namespace) -> int:
    from orbslam_hgcn.outputs import check_output_file
    from orbslam_hgcn.vocabulary import load_vocabulary
    from orbslam_hgcn.vocabulary.dbow2 import write_dbow2_text

    out = check_output_file(args.out, "--out")
    vocab = load_vocabulary(args.file)
    out = write_dbow2_text(vocab, out)
    print(f"wrote {out} ({args.format}: {vocab.n_words} words, {len(vocab.parent)} nodes)")
    return 0


@subcommand
def _add_compare(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "compare",
        help="run SLAM N times per vocabulary (ORB baseline, HGCN) and compare ATE, loops, fps",
        description="Run the whole system (loop closing on) --runs times with each vocabulary and "
        "summarise keyframe ATE after Sim(3) alignment (median/min/max), loops closed, frames lost "
        "and fps per vocabulary; write compare.md, compare.json and compare_ate.png into --out.",
    )
    _add_sequence_arguments(p)
    p.add_argument("--config", default=None, help="camera/stage YAML or a shipped camera name, as for run")
    p.add_argument("--runs", type=int, default=5, help="runs per vocabulary (default 5)")
    p.add_argument("--vocabs", nargs="+", default=["orb", "hgcn"], metavar="VOCAB",
                   help="vocabularies to compare: orb, hgcn, kmeans, orb10k or files (default: orb hgcn)")
    p.add_argument("--out", required=True, help="output folder (one sub-folder per run)")
    p.add_argument("--max-frames", type=int, default=None, help="process at most this many frames per run")
    _add_sequential_argument(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--jobs", type=int, default=None,
                   help="make each run an 'orbslam-hgcn run' process, this many at a time on a local Ray instance "
                   "(in order without Ray), as a one-sequence sweep (default: the runs in this process, in order)")
    p.add_argument("--address", default=None, help="make the runs as processes on the Ray cluster at this address")
    p.set_defaults(func=_run_compare)


def _run_compare(args: argparse.Namespace) -> int:
    from orbslam_hgcn.app.compare import describe_run, format_markdown, run_comparison

    comp = run_comparison(
        args.path, args.out, kind=args.dataset, config=args.config, runs=args.runs, vocabs=args.vocabs,
        max_frames=args.max_frames, progress=not args.no_progress, sequential=args.sequential,
        speed=args.speed, jobs=args.jobs, address=args.address,
        on_run=lambda r: print(describe_run(r)),
    )
    print(format_markdown(comp))
    for path in comp.paths.values():
        print(f"wrote {path}")
    if comp.interrupted:
        return _interrupted_status(comp.terminated)
    return 1 if any(not r.counts for r in comp.runs) else 0


@subcommand
def _add_demo(sub: argparse._SubParsersAction) -> None:
    from orbslam_hgcn.viz.sinks import add_rerun_argument

    p = sub.add_parser(
        "demo",
        help="render the synthetic loop (cached), run SLAM with the HGCN vocabulary, then the ORB baseline",
        description="Render the built-in synthetic loop sequence once into a cache folder, run SLAM with "
        "the shipped HGCN vocabulary and print its ATE, run the ORB-tree baseline on the same sequence and "
        "print the comparison. The first run is recorded for rerun in OUT/demo.rrd.",
    )
    p.add_argument("--out", default="demo_out", help="output folder (default ./demo_out)")
    p.add_argument("--frames", type=int, default=None,
                   help="a shorter loop of N frames (default 900; 300 or more make a full lap)")
    p.add_argument("--runs", type=int, default=1, help="runs per vocabulary (default 1)")
    p.add_argument("--cache", default=None,
                   help="cache folder of rendered sequences (default $ORBSLAM_HGCN_CACHE or ~/.cache/orbslam_hgcn)")
    p.add_argument("--force", action="store_true", help="render the sequence again even when the cache holds it")
    add_rerun_argument(p)
    p.add_argument("--no-rerun", action="store_true", help="record no rerun visualisation")
    _add_sequential_argument(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_run_demo)


def _run_demo(args: argparse.Namespace) -> int:
    from orbslam_hgcn.app.demo import run_demo

    rerun = [] if args.no_rerun else args.rerun
    comp = run_demo(out=args.out, frames=args.frames, runs=args.runs, cache=args.cache, rerun=rerun,
                    progress=not args.no_progress, sequential=args.sequential,
                    speed=args.speed, force=args.force)
    if comp.interrupted:
        return _interrupted_status(comp.terminated)
    return 1 if any(not r.counts for r in comp.runs) else 0


@subcommand
def _add_sweep(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sweep",
        help="run a manifest of sequences x vocabularies x runs (x parameter sets), each run in its own process",
        description="Run every cell of MANIFEST.yaml (sequences, vocabularies, runs, sequential, overrides, params; "
        "see the README) as 'orbslam-hgcn run' processes, on a local Ray instance with --jobs runs at a time, on "
        "the Ray cluster at --address, or, without Ray, in order. Results in OUT/<sequence>/<vocabulary>/<params>/"
        "run<k>/; the table in OUT/sweep.md and OUT/sweep.json, a box plot of the ATE per sequence. Runs already "
        "finished (their stats.json) are not run again. Exit status 0 when every run counts, 1 when some failed, "
        "2 on a bad manifest, 130 when interrupted.",
    )
    p.add_argument("manifest", help="sweep manifest (YAML)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--jobs", type=int, default=1, help="runs at a time on the local Ray instance (default 1)")
    p.add_argument("--address", default=None, help="address of an existing Ray cluster (e.g. ray://HOST:10001 or auto)")
    p.add_argument("--no-ray", action="store_true", help="run the cells in order in this process's children, without Ray")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run_sweep)


def _run_sweep(args: argparse.Namespace) -> int:
    from orbslam_hgcn.app.sweep import run_sweep

    sw = run_sweep(args.manifest, args.out, jobs=args.jobs, address=args.address,
                   use_ray=False if args.no_ray else None, progress=not args.no_progress)
    print(sw.paths["markdown"].read_text(encoding="utf-8"))
    for path in sw.paths.values():
        print(f"wrote {path}")
    if sw.interrupted:
        return _interrupted_status(sw.terminated)
    return 1 if any(not r.outcome.counts for r in sw.runs) else 0


@subcommand
def _add_map(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("map", help="work with a saved map (.npz): export it for other tools")
    msub = p.add_subparsers(dest="map_command", metavar="ACTION", required=True)
    e = msub.add_parser(
        "export-ply",
        help="write a saved map's points and keyframes as PLY files (MeshLab, Open3D, CloudCompare)",
        description="Write the active map of MAP (a file of 'orbslam-hgcn run --save-map') as OUT.ply: its points "
        "(x, y, z, colour, observations: the keyframes observing each), and OUT_keyframes.ply beside it: the "
        "keyframes' camera centres with their optical axes as normals and their frame index. Binary little-endian "
        "PLY 1.0, in the map's units (monocular: arbitrary scale). Points are coloured by observation count "
        "(dark: 2, bright: 15 or more), or with --colour-from by the pixel at their keypoint in a keyframe's image.",
    )
    e.add_argument("map", metavar="MAP.npz", help="saved map file")
    e.add_argument("out", metavar="OUT.ply", help="output points file; the keyframes go to OUT_keyframes.ply")
    e.add_argument("--colour-from", default=None, metavar="DATASET_PATH",
                   help="the dataset the map was made from: colour the points from its images")
    e.set_defaults(func=_run_map_export_ply)


def _run_map_export_ply(args: argparse.Namespace) -> int:
    from orbslam_hgcn.app.export import export_ply

    result = export_ply(args.map, args.out, colour_from=args.colour_from)
    for note in result.notes:
        print(note)
    print(f"wrote {result.paths['points']} ({result.n_points} points)")
    print(f"wrote {result.paths['keyframes']} ({result.n_keyframes} keyframes)")
    return 0
