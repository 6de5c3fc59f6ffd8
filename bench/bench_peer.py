"""ORB-SLAM3 (monocular) and orbslam-hgcn side by side on one sequence.

Each run starts both systems in turn, each in a subprocess of its own, on the same frames:

- ours as a user runs it: ``orbslam-hgcn run PATH --out DIR`` (plus ``--ours-args``), read
  back from its ``stats.json`` and ``KeyFrameTrajectory.txt``;
- ORB-SLAM3 through the optional extra ``peer`` (the ``pyorbslam3`` bindings), with a DBoW2
  text vocabulary (below) and a settings file in ORB-SLAM3 v1.0's format written from the
  dataset's camera. The images are decoded here, by OpenCV as ORB-SLAM3's example programs
  decode them (``cv2.imread``, grey; not by orbslam_hgcn's faster PNG decoder, which is
  ours, not ORB-SLAM3's), and piped to the ORB-SLAM3 process, which hands frame i to
  ORB-SLAM3 no earlier than its timestamp says the camera delivered it (as ORB-SLAM3's
  example programs pace their input; like ``orbslam-hgcn run``, a gap of more than 1 s in
  the timestamps is waited 1 s). It records every frame's tracking state and, after
  ``Shutdown``, the keyframe trajectory. A crash or an ``exit`` inside ORB-SLAM3 ends that
  process only; the bench reports it and goes on.

ORB-SLAM3's vocabulary. By default the project's shipped ORB tree (``orb``: k = 10, L = 6,
trained on real photographs, no benchmark frame among them), exported to DBoW2 text with
``orbslam-hgcn vocab export`` into ``~/.cache/orbslam_hgcn/peer/`` since ORB-SLAM3 reads
text; it passes the gate below (159 of the 160 KITTI 00 frames tracked in each of 3 runs).
``--peer-vocab FILE`` takes any DBoW2 text vocabulary (``.txt`` or ``.txt.gz``, gunzipped
into the same cache) or another orbslam_hgcn ORB-tree vocabulary (a ``.npz`` file or a
shipped name); ``../shared/peer/ORBvoc_real_k10L6.txt.gz`` beside the repository is a
tree made independently of the project (see the README there), for a comparison that does
not lean on the project's own training. The shipped tree of earlier versions (trained
mostly on renders) let ORB-SLAM3 track only about 28 of the 160 KITTI 00 frames: a
comparison against a peer that loses its frames compares nothing.

A comparison counts only when both systems track at least 95% of the frames given
(``VALID_SHARE``): ours, frames with a pose in the final map; ORB-SLAM3, frames in state
OK. A run where either falls short prints which system failed, how many frames it tracked,
and that the comparison of that run is void; it gives no throughput ratio, and the median
ratio is taken over the valid runs only.

Timing, the same for both systems, all on the machine's monotonic clock:

- **frames/s**: frames given / the span from the first image handed in to the last pose
  out. Ours: from the start of the first frame's extraction (the image read and decoded,
  as ORB-SLAM3's first image has been decoded by the bench) to the last frame's pose,
  computed from ``stats.json`` ``real_time`` (``frames_wall_s`` starts at that
  extraction; ``real_time_factor`` is camera seconds per wall second over the same span,
  so the span is the camera time from the first to the last frame / that factor).
  ORB-SLAM3: from its first ``TrackMonocular`` call to the return of its last.
- **start s** (not in frames/s): from the bench starting the system's process to the
  first image handed in: interpreter, imports, configuration, vocabulary loading and, for
  ours, its extraction and local BA processes (ours: the bench notes when ``orbslam-hgcn
  run`` logs "N frames, camera ...", just before ``System.run``, and adds
  ``real_time.startup_s``, from there to the first extraction; ORB-SLAM3: its child
  notes the clock at its first ``TrackMonocular``).
- **shut s** (not in frames/s): from the last pose out to the system stopped. Ours, its
  stages drained at the end of ``System.run`` (``frames_wall_s`` minus the span above);
  ORB-SLAM3, ``Shutdown()`` returned. Writing trajectories afterwards counts in neither.
- **CPU ms/frame**: the CPU time (user + system, all threads) of the system's process tree
  from the first image handed in to the system stopped (start s to start s + span s + shut
  s), over the frames given. The bench samples each tree's CPU every 20 ms from /proc
  (Linux; ``TreeCpu``) and interpolates at those two moments. It counts what each system
  spends on the frames whatever the pace, so it compares them even where neither is pushed
  to its limit (``--speed 1``). Ours counts the decoding of its images; ORB-SLAM3's are
  decoded by the bench, outside its tree (a KITTI PNG takes about 5 ms with ``cv2.imread``).
  ``CPU s`` is the whole tree's CPU time, start-up and shutdown included.

ORB-SLAM3 groups features for BoW matching (tracking against the reference keyframe,
triangulation in local mapping, relocalisation) at the vocabulary's depth minus 4: level 2
(100 nodes) of a 6-level tree such as the default one, but level 1 (10 nodes) of
orbslam_hgcn's 5-level ORB trees, where each search compares many more descriptor pairs.
``--peer-bow-level 2`` hands it a copy of the vocabulary whose header makes that level 2.

Both systems' trajectories are scored the same way: ATE after Sim(3) alignment against the
dataset's ground truth, through :func:`orbslam_hgcn.app.run.trajectory_ate`, of the
keyframes (``KeyFrameTrajectory.txt``) and of every frame with a pose (the camera
trajectory: ours ``CameraTrajectory.txt``; ORB-SLAM3's ``SaveTrajectoryEuRoC``, each frame
against its optimised reference keyframe, rewritten in TUM's layout, since its
``SaveTrajectoryTUM`` refuses a monocular camera).

Printed per run and system: frames given, frames tracked, frames lost, maps started,
keyframes, keyframe and camera ATE, frames/s, the median time from an image to its pose (ours from the
start of its extraction, which an unpaced run starts up to ``threads.prefetch_frames`` frames
ahead of the tracker; ORB-SLAM3's ``TrackMonocular`` call), the span frames/s counts,
start-up, shutdown and CPU time (the process tree, start-up included); then each run's
verdict (ratio, or void), the medians over the runs and the median ratio over the valid
runs. Each valid run also gives two ratios with start-up counted: ours from its process's
start to its last pose (start s + span s) against ORB-SLAM3's span alone (the stricter one:
its start-up apart), and against ORB-SLAM3's start s + span s (both counted); frames are the
same on both sides, so each ratio is a ratio of times; and the CPU per frame, ORB-SLAM3's over
ours' (above 1: ours spent less). ``--record NAME`` writes these figures through ``bench/figures.py``.

``--gate`` checks a vocabulary: it runs ORB-SLAM3 alone (``--runs`` times) with
``--peer-vocab`` (default: the shared file above) and prints the frames tracked of those
given, run by run. Exit status 0 when the median run tracks at least 98% of them
(``GATE_SHARE``), else 1. The check a vocabulary for ORB-SLAM3 must pass: it lets ORB-SLAM3
track at least 98% of KITTI 00 frames 0-159.

The ORB-SLAM3 process needs ``pyorbslam3`` and the OpenGL/X11 runtime libraries its wheel
links against; when they are missing the bench says what to install and exits with status 2.

    python bench/bench_peer.py --sequence ../shared/data/kitti00_first160/sequences/00 \\
        --dataset kitti --speed 0 --runs 3
    python bench/bench_peer.py --sequence ../shared/data/kitti00_first160/sequences/00 \\
        --dataset kitti --gate --runs 3 --peer-vocab my_vocab.npz
"""

from __future__ import annotations

import argparse
import bisect
import json
import os
import re
import resource
import shlex
import shutil
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from bench_long import process_tree, proc_supported  # noqa: E402 - a sibling script
from bench_real import start_load, stop_load  # noqa: E402 - a sibling script

PEER_REQUIREMENT = "pyorbslam3==0.1.1"
# Debian/Ubuntu packages of the shared libraries pyorbslam3 0.1.1's wheel needs from the
# host (found with ldd on its extension module); the rest it carries inside the wheel.
APT_PACKAGES = {
    "libOpenGL.so.0": "libopengl0",
    "libGLX.so.0": "libglx0",
    "libGL.so.1": "libgl1",
    "libGLdispatch.so.0": "libglvnd0",
    "libEGL.so.1": "libegl1",
    "libX11.so.6": "libx11-6",
    "libXext.so.6": "libxext6",
    "libSM.so.6": "libsm6",
    "libICE.so.6": "libice6",
    "libxcb.so.1": "libxcb1",
    "libXau.so.6": "libxau6",
    "libXdmcp.so.6": "libxdmcp6",
    "libuuid.so.1": "libuuid1",
    "libbsd.so.0": "libbsd0",
    "libz.so.1": "zlib1g",
}
APT_LINE = "apt-get install libopengl0 libgl1 libglx0 libegl1 libsm6 libice6 libx11-6 libxext6"
# ORB features per image as ORB-SLAM's own settings files give them for each dataset.
PEER_FEATURES = {"kitti": 2000, "tum": 1000, "euroc": 1000}
MAX_WAIT_S = 1.0  # a longer wait is a gap in the timestamps: wait this long, restart the clock
FRAME_HEADER = struct.Struct("<dIII")  # timestamp (s), height, width, channels; height 0 ends
LOST_STATES = ("RECENTLY_LOST", "LOST")
VALID_SHARE = 0.95  # a comparison counts only when both systems track this share of the frames given
GATE_SHARE = 0.98  # --gate: a vocabulary passes when ORB-SLAM3's median run tracks this share
REPO = Path(__file__).resolve().parent.parent
DEFAULT_PEER_VOCAB = REPO.parent / "shared" / "peer" / "ORBvoc_real_k10L6.txt.gz"
# ORB-SLAM3's vocabulary unless --peer-vocab says otherwise: the project's shipped ORB tree,
# trained on real photographs, which passes the gate (>= 98% of KITTI 00 frames 0-159 tracked).
DEFAULT_PEER_SPEC = "orb"
CACHE = Path.home() / ".cache" / "orbslam_hgcn" / "peer"


# --- the ORB-SLAM3 side: runs in the interpreter given by --peer-python ------------------
# Nothing here imports orbslam_hgcn or OpenCV: that interpreter needs numpy and pyorbslam3.


def peer_check() -> int:
    """Print ``ok VERSION`` when pyorbslam3 loads here, else one line saying what to install
    (exit status 2)."""
    import importlib
    import importlib.metadata
    import importlib.util

    if importlib.util.find_spec("numpy") is None:
        print(f"numpy is missing in {sys.executable}: {sys.executable} -m pip install numpy '{PEER_REQUIREMENT}'")
        return 2
    spec = importlib.util.find_spec("pyorbslam3")
    if spec is None:
        print(f"pyorbslam3 is not installed in {sys.executable}: "
              f"{sys.executable} -m pip install '{PEER_REQUIREMENT}' (or pip install -e '.[peer]')")
        return 2
    try:
        importlib.import_module("pyorbslam3")
    except ImportError as exc:
        missing = re.findall(r"(lib[\w.+-]*\.so[\w.]*)", str(exc))
        missing += ldd_not_found(spec.submodule_search_locations or [])
        missing = sorted(set(missing))
        named = sorted({APT_PACKAGES[m] for m in missing if m in APT_PACKAGES})
        what = ", ".join(missing) or str(exc)
        pkgs = f" (Debian/Ubuntu: {' '.join(named)})" if named else ""
        print(f"pyorbslam3 cannot load {what}{pkgs}; install the OpenGL/X11 runtime libraries it links "
              f"against: {APT_LINE}")
        return 2
    print("ok", importlib.metadata.version("pyorbslam3"))
    return 0


def ldd_not_found(package_dirs: list[str]) -> list[str]:
    """Libraries that ``ldd`` reports as not found for pyorbslam3's extension modules."""
    if shutil.which("ldd") is None:
        return []
    out = []
    for d in package_dirs:
        for so in Path(d).glob("_core*.so"):
            try:
                text = subprocess.run(["ldd", str(so)], capture_output=True, text=True, timeout=30).stdout
            except (OSError, subprocess.SubprocessError):
                continue
            out += re.findall(r"^\s*(\S+) => not found", text, flags=re.M)
    return out


def euroc_to_tum(src: Path, dst: Path) -> int:
    """Rewrite ORB-SLAM3's ``SaveTrajectoryEuRoC`` file (``t_ns tx ty tz qx qy qz qw`` a
    line) in TUM's layout (``t_s tx ty tz qx qy qz qw``); returns the poses written (0, and
    no file, when there is none)."""
    lines = []
    if src.is_file():
        for ln in src.read_text().splitlines():
            f = ln.split()
            if len(f) == 8 and not ln.lstrip().startswith("#"):
                lines.append(f"{float(f[0]) * 1e-9:.9f} " + " ".join(f[1:]))
    if lines:
        dst.write_text("\n".join(lines) + "\n")
    return len(lines)


def read_exact(stream: Any, n: int) -> bytes | None:
    data = stream.read(n)
    return data if len(data) == n else None


def peer_child(vocab: str, settings: str, out: str, speed: float) -> int:
    """Run ORB-SLAM3 monocular over the frames piped to stdin (FRAME_HEADER then the pixels),
    pacing them by their timestamps; write frames.tsv, KeyFrameTrajectory.txt and result.json
    into ``out``."""
    import numpy as np
    import pyorbslam3

    out_dir = Path(out)
    t0 = time.perf_counter()
    slam = pyorbslam3.Slam(vocab, settings, pyorbslam3.Sensor.MONOCULAR, use_viewer=False)
    load_s = time.perf_counter() - t0
    stdin = sys.stdin.buffer
    anchor: tuple[float, float] | None = None  # (perf_counter, timestamp) of the clock's start
    first = last = first_mono = None
    n = 0
    with (out_dir / "frames.tsv").open("w") as tsv:
        tsv.write("index\ttimestamp\tstate\tpoints\ttrack_ms\tlate_ms\n")
        while True:
            head = read_exact(stdin, FRAME_HEADER.size)
            if head is None:
                break
            ts, h, w, c = FRAME_HEADER.unpack(head)
            if h == 0:
                break
            data = read_exact(stdin, h * w * c)
            if data is None:
                break
            image = np.frombuffer(data, np.uint8).reshape((h, w, c) if c > 1 else (h, w))
            now = time.perf_counter()
            if anchor is None:
                anchor = (now, ts)
            elif speed > 0:
                wait = anchor[0] + (ts - anchor[1]) / speed - now
                if wait > MAX_WAIT_S:
                    time.sleep(MAX_WAIT_S)
                    anchor = (time.perf_counter(), ts)
                elif wait > 0:
                    time.sleep(wait)
            ta = time.perf_counter()
            due = anchor[0] + (ts - anchor[1]) / speed if speed > 0 else ta
            if first is None:
                first, first_mono = ta, time.monotonic()  # the bench's clock: start-up from its spawn
            result = slam.track_monocular(image, ts)
            last = time.perf_counter()
            tsv.write(f"{n}\t{ts:.9f}\t{result.state.name}\t{result.num_tracked_points}\t"
                      f"{1000 * (last - ta):.3f}\t{1000 * max(0.0, ta - due):.3f}\n")
            tsv.flush()
            n += 1
    ts0 = time.perf_counter()
    slam.shutdown()
    shutdown_s = time.perf_counter() - ts0
    slam.save_keyframe_trajectory_tum(str(out_dir / "KeyFrameTrajectory.txt"))
    # Every tracked frame's pose against its optimised reference keyframe (ORB-SLAM3 writes
    # this file for a monocular camera only in EuRoC's layout: nanoseconds), as TUM.
    euroc = out_dir / "CameraTrajectory_euroc.txt"
    slam.save_trajectory_euroc(str(euroc))
    euroc_to_tum(euroc, out_dir / "CameraTrajectory.txt")
    summary = {
        "frames": n, "load_s": load_s, "shutdown_s": shutdown_s, "first_in_monotonic": first_mono,
        "loop_s": (last - first) if n else 0.0,  # first image handed in to the last pose out
        "wall_s": (ts0 + shutdown_s - first) if n else 0.0,
    }
    (out_dir / "result.json").write_text(json.dumps(summary, indent=1))
    return 0


# --- the bench: runs in the project's interpreter ----------------------------------------


def fail(message: str) -> None:
    print(message)
    sys.exit(2)


def repo_state() -> str:
    root = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, timeout=30).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return f"{head}{' with uncommitted changes' if dirty else ''}" if head else "unknown"


def ours_command() -> list[str]:
    exe = Path(sys.executable).with_name("orbslam-hgcn")
    if exe.is_file():
        return [str(exe)]
    found = shutil.which("orbslam-hgcn")
    return [found] if found else [sys.executable, "-m", "orbslam_hgcn"]


def check_peer(peer_python: str) -> str:
    """pyorbslam3's version in ``peer_python``, or exit 2 with what to install."""
    if shutil.which(peer_python) is None and not Path(peer_python).is_file():
        fail(f"--peer-python {peer_python}: no such interpreter")
    try:
        proc = subprocess.run([peer_python, str(Path(__file__).resolve()), "--peer-check"],
                              capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.SubprocessError) as exc:
        fail(f"--peer-python {peer_python}: cannot run it ({exc})")
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    if proc.returncode == 0 and lines and lines[-1].startswith("ok "):
        return lines[-1].split()[1]
    if lines:
        fail(lines[-1])
    err = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    fail(f"{peer_python} failed the pyorbslam3 check: {err[-1] if err else f'exit status {proc.returncode}'}")
    return ""


class VocabularyNotFound(Exception):
    """ORB-SLAM3's vocabulary cannot be had: the message says why and what to give."""


def _fresh(target: Path, source: Path) -> bool:
    """Whether ``target`` exists and is not older than ``source``."""
    return target.is_file() and target.stat().st_mtime >= source.stat().st_mtime


def gunzip_cached(source: Path, cache: Path) -> Path:
    """The text of the gzip file ``source`` in ``cache`` (written again when ``source`` is
    newer), for ORB-SLAM3 reads its vocabulary as plain text."""
    import gzip

    name = source.name[: -len(".gz")] if source.name.endswith(".gz") else source.name + ".txt"
    target = cache / name
    if _fresh(target, source):
        return target
    cache.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f"{target.name}.{os.getpid()}.part")
    try:
        with gzip.open(source, "rb") as src, tmp.open("wb") as dst:
            shutil.copyfileobj(src, dst, 1 << 20)
        os.replace(tmp, target)
    except (OSError, EOFError) as exc:
        tmp.unlink(missing_ok=True)
        raise VocabularyNotFound(f"{source}: cannot gunzip it ({exc})") from exc
    return target


def export_vocabulary(source: str, cache: Path) -> Path:
    """The orbslam_hgcn ORB-tree vocabulary ``source`` (a .npz file or a shipped name such as
    ``orb``) as a DBoW2 text file in ``cache``, through ``orbslam-hgcn vocab export``
    (exported again when the source file is newer)."""
    from orbslam_hgcn.vocabulary.loading import SHIPPED

    path = Path(source)
    if not path.is_file():
        if source not in SHIPPED:
            raise VocabularyNotFound(f"--peer-vocab {source}: no such file, nor a shipped vocabulary "
                                     f"({', '.join(sorted(SHIPPED))})")
        path = Path(SHIPPED[source])
    target = cache / f"ORBvoc_{path.stem}.txt"
    if _fresh(target, path):
        return target
    cache.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f"{target.stem}.{os.getpid()}.part.txt")
    proc = subprocess.run(ours_command() + ["vocab", "export", str(path), "--format", "dbow2", "--out", str(tmp)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        tmp.unlink(missing_ok=True)
        err = [ln for ln in (proc.stdout + proc.stderr).splitlines() if ln.strip()]
        raise VocabularyNotFound(f"exporting {source} to DBoW2 text failed: {err[-1] if err else proc.returncode}")
    os.replace(tmp, target)
    return target


def resolve_peer_vocab(spec: str | None, cache: Path = CACHE, default: Path = DEFAULT_PEER_VOCAB,
                       export: Any = None) -> tuple[Path, bool]:
    """The DBoW2 text file ORB-SLAM3 is to load for ``--peer-vocab spec``, and whether it was
    exported from an orbslam_hgcn vocabulary (so that figures measured with it depend on the
    package). ``None``: ``default``. A ``.gz`` file is gunzipped into ``cache``; a ``.txt``
    file, or one whose first line is DBoW2's header (four integers), is used as it is; a
    ``.npz`` file or a shipped name is exported into ``cache`` by ``export`` (default
    :func:`export_vocabulary`). Raises :class:`VocabularyNotFound`."""
    if spec is None:
        if not default.is_file():
            raise VocabularyNotFound(
                f"ORB-SLAM3's default vocabulary {default} is missing; give a DBoW2 text vocabulary "
                "(.txt or .txt.gz) or an orbslam_hgcn one (.npz, or a shipped name such as 'orb') "
                "with --peer-vocab FILE")
        path = default
    else:
        path = Path(spec).expanduser()
    if not path.exists() and (path.suffix.lower() in (".txt", ".gz", ".npz") or os.sep in str(spec)):
        raise VocabularyNotFound(f"--peer-vocab {spec}: file not found")
    if path.suffix.lower() == ".npz" or not path.exists():  # an orbslam_hgcn file, or a shipped name
        return (export or export_vocabulary)(str(spec), cache), True
    if not path.is_file():
        raise VocabularyNotFound(f"--peer-vocab {spec}: not a file")
    path = path.resolve()
    if path.suffix.lower() == ".gz":
        return gunzip_cached(path, cache), False
    if path.suffix.lower() == ".txt" or dbow2_header(path):
        return path, False
    raise VocabularyNotFound(f"--peer-vocab {spec}: neither a DBoW2 text vocabulary (.txt, .txt.gz: a first line "
                             "'k L scoring weighting') nor an orbslam_hgcn one (.npz)")


def dbow2_header(path: Path) -> bool:
    """Whether the first line of ``path`` is DBoW2's text header: four integers."""
    try:
        with path.open("rb") as fh:
            head = fh.readline(256).split()
    except OSError:
        return False
    return len(head) == 4 and all(h.lstrip(b"-").isdigit() for h in head)


def vocabulary_with_bow_level(vocab: Path, level: int, out: Path) -> Path:
    """A copy of the DBoW2 text vocabulary ``vocab`` whose header gives the depth
    ``level + 4``, so that ORB-SLAM3, which groups features at depth - 4 (DBoW2 levelsup 4),
    groups them at tree level ``level``. Nodes, words and weights are unchanged."""
    with vocab.open("r", encoding="utf-8", errors="replace") as src:
        head = src.readline().split()
        if len(head) != 4 or not all(h.lstrip("-").isdigit() for h in head):
            fail(f"{vocab}:1: expected 'k L scoring weighting', found {' '.join(head)!r}")
        depth = int(head[1])
        if not 1 <= level < depth:
            fail(f"--peer-bow-level {level}: must lie between 1 and {depth - 1} for the {depth}-level tree {vocab}")
        target = out / f"{vocab.stem}_bow_level{level}.txt"
        with target.open("w", encoding="utf-8") as dst:
            dst.write(f"{head[0]} {level + 4} {head[2]} {head[3]}\n")
            shutil.copyfileobj(src, dst, 1 << 20)
    return target


def yaml_real(x: float) -> str:
    """A float as OpenCV's YAML reads a real (ORB-SLAM3 v1.0 rejects an integer there)."""
    s = repr(float(x))
    if "e" in s and "." not in s.split("e")[0]:
        return f"{x:.9e}"
    return s if ("." in s or "e" in s) else s + ".0"


def write_settings(path: Path, camera: Any, n_features: int) -> Path:
    """ORB-SLAM3 v1.0 settings (``File.version: "1.0"``) for a pinhole monocular camera."""
    d = list(camera.dist_coeffs)
    lines = [
        "%YAML:1.0",
        f"# {camera.name}: written by bench/bench_peer.py",
        'File.version: "1.0"',
        'Camera.type: "PinHole"',
        f"Camera1.fx: {yaml_real(camera.fx)}",
        f"Camera1.fy: {yaml_real(camera.fy)}",
        f"Camera1.cx: {yaml_real(camera.cx)}",
        f"Camera1.cy: {yaml_real(camera.cy)}",
        f"Camera1.k1: {yaml_real(d[0])}",
        f"Camera1.k2: {yaml_real(d[1])}",
        f"Camera1.p1: {yaml_real(d[2])}",
        f"Camera1.p2: {yaml_real(d[3])}",
    ]
    if d[4] != 0.0:
        lines.append(f"Camera1.k3: {yaml_real(d[4])}")
    lines += [
        f"Camera.width: {int(camera.width)}",
        f"Camera.height: {int(camera.height)}",
        f"Camera.fps: {max(1, round(camera.fps))}",
        "# The frames are given grey, so the colour order does not matter.",
        "Camera.RGB: 0",
        f"ORBextractor.nFeatures: {int(n_features)}",
        "ORBextractor.scaleFactor: 1.2",
        "ORBextractor.nLevels: 8",
        "ORBextractor.iniThFAST: 20",
        "ORBextractor.minThFAST: 7",
        # Read by ORB-SLAM3 even with the viewer off.
        "Viewer.KeyFrameSize: 0.1",
        "Viewer.KeyFrameLineWidth: 1.0",
        "Viewer.GraphLineWidth: 1.0",
        "Viewer.PointSize: 2.0",
        "Viewer.CameraSize: 0.15",
        "Viewer.CameraLineWidth: 2.0",
        "Viewer.ViewpointX: 0.0",
        "Viewer.ViewpointY: -100.0",
        "Viewer.ViewpointZ: -0.1",
        "Viewer.ViewpointF: 2000.0",
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


def children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


CPU_SAMPLE_S = 0.02  # TreeCpu's sampling interval
CLOCK_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def proc_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of process ``pid`` (all its threads) from /proc/PID/stat;
    None when it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            stat = fh.read()
    except OSError:
        return None
    fields = stat[stat.rfind(")") + 2:].split()  # fields[0] is the state, field 3 of the file
    try:
        return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS
    except (IndexError, ValueError):
        return None


class TreeCpu:
    """The CPU seconds a process tree has used, sampled every :data:`CPU_SAMPLE_S` on the
    monotonic clock from /proc (Linux): each process of the tree counts with the last figure
    read for it, so a child that ends keeps what it used up to its last sample. :meth:`used`
    interpolates between the samples. ``supported`` is False elsewhere (no figures)."""

    def __init__(self, root: int) -> None:
        self.root = root
        self.samples: list[tuple[float, float]] = []
        self._last: dict[int, float] = {}
        self._stop = threading.Event()
        self.supported = proc_supported()
        self._thread = threading.Thread(target=self._run, name="bench-peer-cpu", daemon=True)
        if self.supported:
            self._thread.start()

    def _run(self) -> None:
        while True:
            for pid in process_tree(self.root):
                c = proc_cpu_s(pid)
                if c is not None:
                    self._last[pid] = max(c, self._last.get(pid, 0.0))
            self.samples.append((time.monotonic(), sum(self._last.values())))
            if self._stop.wait(CPU_SAMPLE_S):
                return

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def used(self, t0: float, t1: float) -> float:
        """CPU seconds used between monotonic times ``t0`` and ``t1`` (NaN when the samples
        do not cover both)."""
        if len(self.samples) < 2 or not (t0 == t0 and t1 == t1):
            return float("nan")
        times = [t for t, _ in self.samples]
        if t0 < times[0] or t1 > times[-1]:
            return float("nan")

        def at(t: float) -> float:
            i = min(max(1, bisect.bisect_left(times, t)), len(times) - 1)
            (ta, ca), (tb, cb) = self.samples[i - 1], self.samples[i]
            return ca if tb <= ta else ca + (cb - ca) * (t - ta) / (tb - ta)

        return at(t1) - at(t0)


def span_cpu(row: dict[str, Any], cpu: TreeCpu, t0: float) -> None:
    """``row["cpu_span_s"]``: the CPU seconds the system's process tree used from the first
    image handed in to the system stopped (start s to start s + span s + shut s after the
    bench started it at monotonic ``t0``), and ``cpu_ms_per_frame`` over the frames given."""
    start = t0 + row["start_s"]
    row["cpu_span_s"] = cpu.used(start, start + row["loop_s"] + max(0.0, row["shutdown_s"]))
    row["cpu_ms_per_frame"] = 1000.0 * row["cpu_span_s"] / row["frames"] if row["frames"] else float("nan")


def keyframe_ate(gt: Any, path: Path) -> dict[str, Any]:
    """ATE after Sim(3) alignment of the trajectory file ``path`` (keyframes or every frame),
    or {"error": why}."""
    from orbslam_hgcn.errors import OrbslamError
    from orbslam_hgcn.app.run import trajectory_ate
    from orbslam_hgcn.trajectory import read_tum

    if gt is None:
        return {"error": "no ground truth"}
    if not path.is_file():
        return {"error": f"{path.name} not written"}
    try:
        est = read_tum(path)
    except OrbslamError as exc:
        return {"error": str(exc)}
    return trajectory_ate(gt, est)


def tail(path: Path, n: int = 1) -> str:
    try:
        lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return " | ".join(lines[-n:])


RUN_READY = re.compile(r": \d+ frames, camera ")  # orbslam-hgcn run's log line just before System.run


def run_ours(args: argparse.Namespace, kind: str, out: Path, gt: Any, camera_span_s: float) -> dict[str, Any]:
    cmd = ours_command() + ["run", str(args.sequence), "--out", str(out), "--dataset", kind, "--no-progress"]
    if args.max_frames is not None:
        cmd += ["--max-frames", str(args.max_frames)]
    if args.config is not None:
        cmd += ["--config", args.config]
    if args.speed != 1.0:
        cmd += ["--speed", str(args.speed)]
    cmd += shlex.split(args.ours_args)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "run.log"
    ready_at = None  # when the run logged "N frames, camera ...", just before System.run
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    c0, t0 = children_cpu(), time.monotonic()
    with log.open("w") as fh:
        fh.write(" ".join(shlex.quote(c) for c in cmd) + "\n")
        fh.flush()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, text=True,
                                errors="replace", bufsize=1)
        cpu = TreeCpu(proc.pid)
        assert proc.stdout is not None
        try:
            for line in proc.stdout:
                if ready_at is None and RUN_READY.search(line):
                    ready_at = time.monotonic()
                fh.write(line)
            rc = proc.wait()
        finally:
            cpu.stop()
    row: dict[str, Any] = {"system": "orbslam-hgcn", "cpu_s": children_cpu() - c0, "call_s": time.monotonic() - t0}
    stats_path = out / "stats.json"
    if rc != 0 or not stats_path.is_file():
        row["error"] = f"exit status {rc}: {tail(log)} (log: {log})"
        return row
    s = json.loads(stats_path.read_text())
    f = s["frames"]
    rt = s.get("real_time", {})
    # frames_wall_s runs from the first frame's extraction to the stages drained; the real-time
    # factor is camera seconds per wall second from that extraction to the last pose out.
    loop_s, shutdown_s = ours_spans(rt.get("frames_wall_s"), rt.get("real_time_factor"), camera_span_s)
    startup = rt.get("startup_s")
    row.update(
        frames=f["frames"], tracked=f["tracked"], lost=f["lost"],
        maps=sum(1 for e in s.get("events", []) if e.get("event") == "initialized"),
        keyframes=s["keyframes"], loop_s=loop_s, shutdown_s=shutdown_s,
        start_s=(ready_at - t0 + float(startup)) if ready_at is not None and startup is not None else float("nan"),
        frame_ms=float(s["timing_ms"]["frame_total"]["median"]),
        ate=keyframe_ate(gt, out / "KeyFrameTrajectory.txt"),
        cam_ate=keyframe_ate(gt, out / "CameraTrajectory.txt"),
        kernels=kernels_of(s),
    )
    row["fps"] = fps(row["frames"], row["loop_s"])
    span_cpu(row, cpu, t0)
    return row


def ours_spans(frames_wall_s: float | None, real_time_factor: float | None,
               camera_span_s: float) -> tuple[float, float]:
    """Ours: (first image handed in to the last pose out, last pose out to stages drained),
    in seconds, from stats.json's ``real_time``. The first span is the camera time from the
    first frame to the last (``camera_span_s``) / the real-time factor; the second, the rest
    of ``frames_wall_s``. Without a factor (a single frame) the first is all of
    ``frames_wall_s`` and the second NaN."""
    if frames_wall_s is None:
        return float("nan"), float("nan")
    if not real_time_factor or camera_span_s <= 0:
        return float(frames_wall_s), float("nan")
    loop_s = camera_span_s / float(real_time_factor)
    return loop_s, float(frames_wall_s) - loop_s


def fps(frames: float, span_s: float) -> float:
    """Frames per second over ``span_s`` (0 when the span is not positive or not known)."""
    return frames / span_s if span_s > 0 else 0.0


def run_peer(args: argparse.Namespace, sequence: Any, n: int, vocab: Path, settings: Path, out: Path,
             gt: Any) -> dict[str, Any]:
    import cv2
    import numpy as np

    out.mkdir(parents=True, exist_ok=True)
    log = out / "orbslam3.log"
    cmd = [args.peer_python, str(Path(__file__).resolve()), "--peer-child", "--vocab", str(vocab),
           "--settings", str(settings), "--out", str(out), "--speed", str(args.speed)]
    duration = float(sequence.timestamps[n - 1] - sequence.timestamps[0]) if n else 0.0
    limit = 300.0 + 5.0 * (duration / args.speed if args.speed > 0 else 0.0) + 2.0 * n
    c0, t0 = children_cpu(), time.monotonic()
    with log.open("w") as fh:
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=fh, stderr=subprocess.STDOUT)
        cpu = TreeCpu(proc.pid)
        assert proc.stdin is not None
        killed = threading.Event()

        def kill() -> None:  # a hung ORB-SLAM3 must not hang the bench
            killed.set()
            proc.kill()

        watchdog = threading.Timer(limit, kill)
        watchdog.start()
        try:
            paths = getattr(sequence, "paths", None)
            for i in range(n):
                if paths is not None:  # OpenCV's decoder, as ORB-SLAM3's example programs read them
                    image = cv2.imread(str(paths[i]), cv2.IMREAD_GRAYSCALE)
                    if image is None:
                        fail(f"{paths[i]}: OpenCV cannot read this image")
                else:  # a video: the reader's frames
                    image = sequence[i].image
                image = np.ascontiguousarray(image, dtype=np.uint8)
                h, w = image.shape[:2]
                c = image.shape[2] if image.ndim == 3 else 1
                proc.stdin.write(FRAME_HEADER.pack(float(sequence.timestamps[i]), h, w, c))
                proc.stdin.write(image.data)
            proc.stdin.write(FRAME_HEADER.pack(0.0, 0, 0, 0))
            proc.stdin.close()
        except (BrokenPipeError, ValueError):
            pass  # ORB-SLAM3 ended early; its exit status says how
        finally:
            if not proc.stdin.closed:  # also on an error here: the process then ends at once
                try:
                    proc.stdin.close()
                except BrokenPipeError:
                    pass
            proc.wait()
            watchdog.cancel()
            cpu.stop()
    note = f"killed after {limit:.0f} s" if killed.is_set() else ""
    row: dict[str, Any] = {"system": "ORB-SLAM3", "cpu_s": children_cpu() - c0, "call_s": time.monotonic() - t0}
    rc = proc.returncode
    states, track_ms = [], []
    tsv = out / "frames.tsv"
    if tsv.is_file():
        for line in tsv.read_text().splitlines()[1:]:
            fields = line.split("\t")
            if len(fields) == 6:
                states.append(fields[2])
                track_ms.append(float(fields[4]))
    result_path = out / "result.json"
    if rc != 0 or not result_path.is_file():
        why = note or (f"signal {-rc}" if rc is not None and rc < 0 else f"exit status {rc}")
        row["error"] = f"ORB-SLAM3 ended early ({why}) after {len(states)} of {n} frames: {tail(log)} (log: {log})"
        return row
    res = json.loads(result_path.read_text())
    inits = sum(1 for a, b in zip(["NOT_INITIALIZED"] + states, states) if a == "NOT_INITIALIZED" and b == "OK")
    kf_path = out / "KeyFrameTrajectory.txt"
    keyframes = sum(1 for ln in kf_path.read_text().splitlines() if ln.strip()) if kf_path.is_file() else 0
    row.update(
        frames=len(states), tracked=states.count("OK"), lost=sum(s in LOST_STATES for s in states), maps=inits,
        keyframes=keyframes, loop_s=float(res["loop_s"]), shutdown_s=float(res["wall_s"]) - float(res["loop_s"]),
        frame_ms=statistics.median(track_ms) if track_ms else 0.0, load_s=float(res["load_s"]),
        start_s=(float(res["first_in_monotonic"]) - t0) if res.get("first_in_monotonic") is not None else float("nan"),
        ate=keyframe_ate(gt, kf_path),
        cam_ate=keyframe_ate(gt, out / "CameraTrajectory.txt"),
    )
    row["fps"] = fps(row["frames"], row["loop_s"])
    span_cpu(row, cpu, t0)
    return row


COLUMNS = (
    ("run", 4), ("system", 13), ("frames", 6), ("tracked", 7), ("lost", 5), ("maps", 4), ("KFs", 4),
    ("KF ATE cm", 10), ("pairs", 5), ("cam ATE cm", 10), ("pairs", 5), ("frames/s", 8), ("ms/frame", 8), ("span s", 7), ("start s", 7),
    ("shut s", 6), ("CPU s", 6), ("CPU ms/f", 8),
)


def format_row(run: str, row: dict[str, Any]) -> str:
    if "error" in row:
        return f"{run:>4s} {row['system']:<13s} failed: {row['error']}"
    ates = []
    for key in ("ate", "cam_ate"):
        ate = row.get(key, {})
        ates += [f"{100 * ate['rmse_m']:.2f}" if "rmse_m" in ate else "n/a", str(ate.get("pairs", "-"))]
    vals = (run, row["system"], f"{row['frames']:.0f}", f"{row['tracked']:.0f}", f"{row['lost']:.0f}",
            f"{row['maps']:.0f}", f"{row['keyframes']:.0f}", *ates, f"{row['fps']:.2f}",
            f"{row['frame_ms']:.1f}", f"{row['loop_s']:.2f}", f"{row['start_s']:.2f}", f"{row['shutdown_s']:.2f}",
            f"{row['cpu_s']:.1f}", f"{row.get('cpu_ms_per_frame', float('nan')):.1f}")
    return " ".join(f"{v:<{w}s}" if name == "system" else f"{v:>{w}s}" for (name, w), v in zip(COLUMNS, vals))


def median_row(rows: list[dict[str, Any]], system: str) -> dict[str, Any] | None:
    """The median of every figure over the runs that completed (None when none did)."""
    ok = [r for r in rows if "error" not in r]
    if not ok:
        return None
    med: dict[str, Any] = {"system": system}
    for key in ("frames", "tracked", "lost", "maps", "keyframes", "fps", "frame_ms", "loop_s", "start_s",
                "shutdown_s", "cpu_s", "cpu_ms_per_frame"):
        vals = [r[key] for r in ok if r.get(key, float("nan")) == r.get(key, float("nan"))]
        med[key] = statistics.median(vals) if vals else float("nan")
    for key in ("ate", "cam_ate"):
        ates = [r[key] for r in ok if "rmse_m" in r.get(key, {})]
        med[key] = ({"rmse_m": statistics.median(a["rmse_m"] for a in ates), "pairs": f"{len(ates)}/{len(rows)}"}
                    if ates else {"error": "none"})
    return med


# --- verdicts: pure functions of the rows -------------------------------------------------


def tracked_of(row: dict[str, Any]) -> int:
    """Frames a run tracked; 0 for a run that failed."""
    return 0 if "error" in row else int(row["tracked"])


def compare_run(ours: dict[str, Any], peer: dict[str, Any], given: int,
                share: float = VALID_SHARE) -> dict[str, Any]:
    """One run's verdict: ``valid`` when both systems tracked at least ``share`` of the
    ``given`` frames (and neither failed), with ``ratio`` = ours' frames/s / ORB-SLAM3's;
    else ``valid`` False, no ratio, and ``failed``: (system, frames tracked, why) for each
    system that fell short."""
    failed = []
    for row in (ours, peer):
        if "error" in row:
            failed.append((row["system"], 0, "the run failed"))
        elif given <= 0 or row["tracked"] < share * given:
            failed.append((row["system"], int(row["tracked"]), f"under {share:.0%} of {given}"))
        elif not row["fps"] > 0:
            failed.append((row["system"], int(row["tracked"]), "no frames/s"))
    if failed:
        return {"valid": False, "failed": failed}
    verdict = {"valid": True, "ratio": ours["fps"] / peer["fps"]}
    # CPU per frame: ORB-SLAM3's over ours (above 1: ours used less), where both were sampled.
    o_cpu, p_cpu = ours.get("cpu_ms_per_frame", float("nan")), peer.get("cpu_ms_per_frame", float("nan"))
    if o_cpu > 0 and p_cpu > 0:
        verdict["cpu_ratio"] = p_cpu / o_cpu
    # Start-up counted: ours from its process's start (start s + span s) against ORB-SLAM3's
    # span alone (its start-up apart: the stricter ratio), and against its start s + span s.
    if all(k in r and r[k] == r[k] for r in (ours, peer) for k in ("start_s", "loop_s")):
        ours_total = ours["start_s"] + ours["loop_s"]
        if ours_total > 0 and peer["loop_s"] > 0:
            verdict["ratio_with_start"] = peer["loop_s"] / ours_total
            verdict["ratio_both_start"] = (peer["start_s"] + peer["loop_s"]) / ours_total
    return verdict


def describe_verdict(verdict: dict[str, Any], given: int) -> str:
    if verdict["valid"]:
        text = f"ratio {verdict['ratio']:.2f}x (ours' frames/s / ORB-SLAM3's)"
        if "ratio_with_start" in verdict:
            text += (f"; with our start-up counted {verdict['ratio_with_start']:.2f}x (ORB-SLAM3's apart), "
                     f"{verdict['ratio_both_start']:.2f}x with both counted")
        if "cpu_ratio" in verdict:
            text += f"; CPU per frame {verdict['cpu_ratio']:.2f}x (ORB-SLAM3's / ours')"
        return text
    why = "; ".join(f"{system} tracked {tracked} of {given} frames ({reason})" for system, tracked, reason in verdict["failed"])
    return f"comparison void: {why}; no ratio"


def median_ratio(verdicts: list[dict[str, Any]], key: str = "ratio") -> tuple[float, list[float]] | None:
    """The median ratio (``key``: "ratio", "ratio_with_start", "ratio_both_start" or
    "cpu_ratio") over
    the valid runs and those runs' ratios (None when no run is valid)."""
    ratios = [v[key] for v in verdicts if v["valid"] and key in v]
    return (statistics.median(ratios), ratios) if ratios else None


def gate_verdict(tracked: list[int], given: int, share: float = GATE_SHARE) -> tuple[bool, float]:
    """Whether a vocabulary passes the gate: the median over the runs of the frames
    ORB-SLAM3 tracked is at least ``share`` of the ``given`` frames (a failed run counts 0).
    Returns (passed, median frames tracked)."""
    if not tracked or given <= 0:
        return False, 0.0
    med = float(statistics.median(tracked))
    return med >= share * given, med


def ours_features(args: argparse.Namespace, camera: Any, kind: str) -> int | None:
    """ORB features per image that ``orbslam-hgcn run`` will use: the orb section of the
    stage settings it picks for the dataset's ``camera``, then of its --config."""
    from orbslam_hgcn.app.settings import resolve_settings
    from orbslam_hgcn.errors import OrbslamError

    config = args.config
    extra = shlex.split(args.ours_args)
    for i, tok in enumerate(extra):
        if tok == "--config" and i + 1 < len(extra):
            config = extra[i + 1]
        elif tok.startswith("--config="):
            config = tok.split("=", 1)[1]
    try:
        return resolve_settings(camera, kind, config).configs.orb.n_features
    except OrbslamError:
        return None


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sequence", type=Path, help="dataset folder (or video file), as for orbslam-hgcn run")
    p.add_argument("--dataset", default=None, help="tum, euroc, kitti, folder or video (default: detected)")
    p.add_argument("--config", default=None, help="camera YAML or shipped name, for both systems (as run --config)")
    p.add_argument("--runs", type=int, default=3, help="runs of each system (default 3); every run and the median")
    p.add_argument("--max-frames", type=int, default=None, help="at most this many frames")
    p.add_argument("--peer-vocab", "--vocab", dest="peer_vocab", default=DEFAULT_PEER_SPEC, metavar="FILE",
                   help="ORB-SLAM3's vocabulary: a DBoW2 text file (.txt, or .txt.gz, gunzipped into "
                   "~/.cache/orbslam_hgcn/peer/) or an orbslam_hgcn ORB tree (.npz, or a shipped name such as "
                   "'orb'), exported to DBoW2 text there (default: 'orb', the shipped tree, which passes --gate; "
                   "../shared/peer/ORBvoc_real_k10L6.txt.gz beside the repository is the independent one)")
    p.add_argument("--gate", action="store_true",
                   help="check the vocabulary: run ORB-SLAM3 only and print frames tracked / given per run; exit "
                   f"status 0 when the median run tracks at least {GATE_SHARE * 100:.0f}%% of them, else 1")
    p.add_argument("--ours-args", default="", help="extra arguments for orbslam-hgcn run, e.g. '--sequential'")
    p.add_argument("--peer-bow-level", type=int, default=None, metavar="N",
                   help="tree level at which ORB-SLAM3 groups features for BoW matching; it uses the "
                   "vocabulary's depth - 4: level 2 of a 6-level tree (ORBvoc.txt, the default), level 1 (10 "
                   "nodes) of orbslam_hgcn's 5-level trees. Given, ORB-SLAM3 gets a copy of the vocabulary whose "
                   "header says depth N + 4 (same words and weights)")
    p.add_argument("--peer-python", default=sys.executable,
                   help="interpreter with pyorbslam3 installed (default: this one)")
    p.add_argument("--peer-features", type=int, default=None,
                   help="ORB-SLAM3's ORBextractor.nFeatures (default: 2000 for KITTI, else 1000)")
    p.add_argument("--speed", type=float, default=1.0,
                   help="both systems take frames at this many times the camera's rate (0: unpaced)")
    p.add_argument("--load", default="none", choices=["none", "nice19", "hog"],
                   help="CPU load beside every run of both systems, as bench_real.py --load (default none)")
    p.add_argument("--out", type=Path, default=None, help="folder for the runs' outputs (default: a new temp folder)")
    p.add_argument("--record", default=None, metavar="NAME",
                   help="write the figures to bench/results/NAME.json (bench/figures.py; refuses on uncommitted code)")
    p.add_argument("--peer-check", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--peer-child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--settings", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.peer_check:
        return peer_check()
    if args.peer_child:
        return peer_child(str(args.peer_vocab), args.settings, str(args.out), args.speed)
    if args.sequence is None:
        p.error("--sequence is required")
    if args.runs < 1:
        p.error("--runs must be at least 1")
    if args.speed < 0:
        p.error("--speed must not be negative")
    load_start = os.getloadavg()[0]

    try:
        vocab, exported = resolve_peer_vocab(args.peer_vocab)
    except VocabularyNotFound as exc:
        fail(str(exc))
    version = check_peer(args.peer_python)

    from orbslam_hgcn.datasets.factory import detect_kind, open_sequence
    from orbslam_hgcn.errors import OrbslamError
    from orbslam_hgcn.app.run import camera_from_config

    try:
        kind = (args.dataset or detect_kind(args.sequence)).lower()
        camera = camera_from_config(args.config) if args.config else None
        sequence = open_sequence(kind, args.sequence, camera)
    except OrbslamError as exc:
        fail(str(exc))
    n = len(sequence) if args.max_frames is None else max(0, min(len(sequence), args.max_frames))
    if n == 0:
        fail("no frames to run")
    camera_span_s = float(sequence.timestamps[n - 1] - sequence.timestamps[0])
    gt = sequence.ground_truth if sequence.ground_truth is not None and len(sequence.ground_truth) >= 3 else None
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_peer_"))
    out.mkdir(parents=True, exist_ok=True)
    source = args.peer_vocab or str(DEFAULT_PEER_VOCAB)
    run_vocab = vocab if args.peer_bow_level is None else vocabulary_with_bow_level(vocab, args.peer_bow_level, out)
    peer_features = args.peer_features or PEER_FEATURES.get(kind, 1000)
    settings = write_settings(out / "orbslam3_settings.yaml", sequence.camera, peer_features)

    cam = sequence.camera
    print(f"{sequence.name}: {n} of {len(sequence)} frames, {cam.width}x{cam.height}, {cam.fps:.1f} Hz, "
          f"ground truth: {'yes' if gt is not None else 'no'}")
    if not args.gate:
        print(f"orbslam_hgcn at {repo_state()}: orbslam-hgcn run {args.ours_args or '(defaults)'}; "
              f"{ours_features(args, cam, kind) or '?'} ORB features")
    print(f"ORB-SLAM3 (pyorbslam3 {version}, monocular, viewer off): {peer_features} ORB features, "
          f"vocabulary {source}{f' (as {vocab})' if str(vocab) != source else ''}"
          f"{f', BoW matching at tree level {args.peer_bow_level}' if args.peer_bow_level else ''}")
    pace = "as fast as they are processed" if args.speed == 0 else f"at {args.speed:g}x the camera's rate"
    print(f"frames {pace}; {os.cpu_count()} CPUs, load average {load_start:.1f} at the start; "
          f"load beside each run: {args.load}; outputs in {out}")
    print("tracked: ours, frames with a pose in the final map; ORB-SLAM3, frames in state OK. lost: ours LOST, "
          "ORB-SLAM3 RECENTLY_LOST or LOST. maps: initialisations (a new map after each reset or loss). "
          "KFs: keyframes of the final map. KF ATE / cam ATE: RMSE after Sim(3) alignment of the keyframes / of every frame with a pose (ours: CameraTrajectory.txt; ORB-SLAM3: its SaveTrajectoryEuRoC). frames/s: frames / span s, "
          "from the first image handed in (ours: its extraction starts; ORB-SLAM3: its first TrackMonocular) "
          "to the last pose out. start s (not in the span): from the bench starting the process to the first "
          "image handed in. shut s (not in the span): from the last pose out to the system stopped (ours: its "
          "stages drained; ORB-SLAM3: Shutdown() returned). ms/frame: median from an image to its pose: ours "
          "from the start of the frame's extraction (unpaced, up to threads.prefetch_frames frames ahead of the "
          "tracker: the wait in that queue counts), ORB-SLAM3 its TrackMonocular call. CPU s: the whole "
          "process tree, start-up included. CPU ms/f: the process tree's CPU from the first image handed in to "
          "the system stopped, per frame (ORB-SLAM3's images are decoded outside its tree, ours inside).")
    if args.gate:
        print(f"gate: ORB-SLAM3 only; the vocabulary passes when the median run tracks at least {GATE_SHARE:.0%} "
              f"of the {n} frames ({GATE_SHARE * n:.1f})")
    else:
        print(f"a run's comparison counts only when both systems track at least {VALID_SHARE:.0%} of the {n} "
              f"frames ({VALID_SHARE * n:.1f}); the median ratio is over those runs")
    header = " ".join(f"{name:<{w}s}" if name == "system" else f"{name:>{w}s}" for name, w in COLUMNS)
    print(header)
    rows: dict[str, list[dict[str, Any]]] = {"orbslam-hgcn": [], "ORB-SLAM3": []}
    verdicts: list[dict[str, Any]] = []
    for i in range(args.runs):
        order = ("peer",) if args.gate else (("ours", "peer") if i % 2 == 0 else ("peer", "ours"))
        run_rows = {}
        for who in order:
            procs = start_load(args.load)
            try:
                if who == "ours":
                    row = run_ours(args, kind, out / f"run{i + 1}_ours", gt, camera_span_s)
                else:
                    row = run_peer(args, sequence, n, run_vocab, settings, out / f"run{i + 1}_orbslam3", gt)
            finally:
                stop_load(procs)
            rows[row["system"]].append(row)
            run_rows[who] = row
            print(format_row(str(i + 1), row), flush=True)
        if args.gate:
            print(f"   run {i + 1}: ORB-SLAM3 tracked {tracked_of(run_rows['peer'])} / {n} frames", flush=True)
        else:
            verdict = compare_run(run_rows["ours"], run_rows["peer"], n)
            verdicts.append(verdict)
            print(f"   run {i + 1}: {describe_verdict(verdict, n)}", flush=True)
    for system, rs in rows.items():
        if args.gate and system == "orbslam-hgcn":
            continue
        med = median_row(rs, system)
        print(format_row("med", med) if med else f" med {system:<13s} every run failed")
    (out / "bench_peer.json").write_text(json.dumps({"rows": rows, "verdicts": verdicts}, indent=1, default=str))

    if args.gate:
        tracked = [tracked_of(r) for r in rows["ORB-SLAM3"]]
        passed, med = gate_verdict(tracked, n)
        verdict_line = (f"{'PASS' if passed else 'FAIL'}: ORB-SLAM3 tracked {', '.join(map(str, tracked))} of {n} "
                        f"frames (median {med:g}, {med / n:.1%}; needed {GATE_SHARE:.0%})")
        print(f"gate {verdict_line} with {source}")
        if args.record:
            figs = [("vocabulary", source), ("frames given", str(n))]
            figs += [(f"run {i + 1}", f"tracked {t} / {n}") for i, t in enumerate(tracked)]
            figs.append(("verdict", verdict_line))
            record(args.record, f"ORB-SLAM3 vocabulary gate on {sequence.name} ({n} frames, {pace})", figs,
                   measures=["orbslam_hgcn"] if exported else ["bench/bench_peer.py"], load_start=load_start,
                   notes=f"pyorbslam3 {version}, {peer_features} ORB features")
        return 0 if passed else 1

    summary = median_ratio(verdicts)
    if summary is None:
        summary_line = f"no valid run of {args.runs}: the comparison is void, no ratio"
    else:
        med_ratio, ratios = summary
        summary_line = (f"median ratio {med_ratio:.2f}x over {len(ratios)} valid run(s) of {args.runs} "
                        f"(run by run {', '.join(f'{r:.2f}x' for r in ratios)})")
        for key, what in (("ratio_with_start", "our start-up counted, ORB-SLAM3's apart"),
                          ("ratio_both_start", "both start-ups counted"),
                          ("cpu_ratio", "CPU per frame, ORB-SLAM3's / ours'")):
            more = median_ratio(verdicts, key)
            if more is not None:
                summary_line += f"; {what}: {more[0]:.2f}x ({', '.join(f'{r:.2f}x' for r in more[1])})"
    print(summary_line)
    kernels = sorted({r.get("kernels", "unknown") for r in rows["orbslam-hgcn"] if "error" not in r})
    print(f"our compiled kernels: {', '.join(kernels) or 'no run finished'}")
    if args.record:
        figs = [("vocabulary", source), ("frames given", str(n)), ("our compiled kernels", ", ".join(kernels))]
        for i, verdict in enumerate(verdicts):
            o, q = rows["orbslam-hgcn"][i], rows["ORB-SLAM3"][i]
            sides = "; ".join(
                f"{r['system']} failed" if "error" in r else
                f"{r['system']} tracked {r['tracked']:.0f}, {r['keyframes']:.0f} keyframes, "
                f"keyframe ATE {ate_cm(r['ate'])}, camera ATE {ate_cm(r['cam_ate'])}, "
                f"{r['fps']:.2f} frames/s, start {r['start_s']:.2f} s, "
                f"shutdown {r['shutdown_s']:.2f} s, CPU {r.get('cpu_ms_per_frame', float('nan')):.1f} ms/frame"
                for r in (o, q))
            figs.append((f"run {i + 1}", f"{sides}; {describe_verdict(verdict, n)}"))
        for system, rs in rows.items():
            med = median_row(rs, system)
            if med is not None:
                figs.append((f"median {system}", f"tracked {med['tracked']:.0f}, {med['keyframes']:.0f} keyframes, "
                             f"keyframe ATE {ate_cm(med['ate'])}, camera ATE {ate_cm(med['cam_ate'])}, "
                             f"{med['fps']:.2f} frames/s, CPU {med['cpu_ms_per_frame']:.1f} ms/frame"))
        figs.append(("median", summary_line))
        record(args.record, f"ORB-SLAM3 beside `orbslam-hgcn run` on {sequence.name} ({n} frames, {pace})", figs,
               load_start=load_start, notes=f"pyorbslam3 {version}, {peer_features} ORB features, "
               f"ours with {args.ours_args or 'defaults'}")
    return 0


def ate_cm(ate: dict[str, Any]) -> str:
    return f"{100 * ate['rmse_m']:.2f} cm" if "rmse_m" in ate else "n/a"


def kernels_of(stats: dict[str, Any]) -> str:
    """Where a run of ours took its compiled kernels from (its stats.json ``kernels``)."""
    k = stats.get("kernels")
    if not k:
        return "unknown"
    if k.get("built_ahead") and not k.get("numba_imported"):
        return "built ahead of time"
    return "numba" + (f" ({k['not_built_why']})" if k.get("not_built_why") else "")


def record(name: str, title: str, figs: list[tuple[str, str]], **kwargs: Any) -> None:
    """Write the figures through bench/figures.py (which refuses on uncommitted code)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import figures

    figures.record(name, title, figs, bench_file=__file__, **kwargs)


if __name__ == "__main__":
    sys.exit(main())
