"""Reading a video file as a run reads it: frame after frame, against a seek per frame.

Writes a 1,000-frame 640x480 clip at 30 fps of a camera panning and bobbing over a
textured wall (the renderer's surface textures, with sensor noise), once per codec:
mp4v and XVID (inter-coded: a key frame every 12 frames, the others predicted from
their neighbours) and MJPG (every frame a JPEG). Then, on one core (the process is
pinned to one CPU; OpenCV and FFmpeg get one thread):

* ``VideoSequence`` frame by frame (``seq[i]`` for i = 0, 1, ..., as the run's reader
  thread asks), grey frames as the tracker gets them;
* the previous reader: ``CAP_PROP_POS_FRAMES`` set before every frame, then read and
  converted to grey, over the first ``--seek-frames`` frames (it is slow);
* a bare ``cv2.VideoCapture.read`` loop, the decoder's own speed.

Prints frames/s for each, and the seeks ``VideoSequence`` made (0 expected).

    python bench/bench_video.py [--frames 1000] [--seek-frames 200] [--codecs mp4v XVID MJPG]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from orbslam_hgcn.datasets.video import VideoSequence
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.synth.textures import STYLES, make_texture

SUFFIX = {"mp4v": ".mp4", "XVID": ".avi", "MJPG": ".avi"}
WIDTH, HEIGHT = 640, 480


def write_clip(path: Path, fourcc: str, frames: int) -> None:
    """A camera panning along a textured wall and bobbing, with sensor noise."""
    rng = np.random.default_rng(0)
    wall = np.concatenate([make_texture(rng, 900, 1000, 0.004, STYLES[s]) for s in ("print", "wall", "wood")], 1)
    span = wall.shape[1] - WIDTH - 1
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 30.0, (WIDTH, HEIGHT), True)
    if not w.isOpened():
        raise SystemExit(f"OpenCV cannot write {fourcc} here")
    for i in range(frames):
        x = int(span * (0.5 - 0.5 * np.cos(2 * np.pi * i / frames)))
        y = int(200 + 150 * np.sin(i / 23.0))
        img = wall[y:y + HEIGHT, x:x + WIDTH].astype(np.int16) + rng.normal(0, 2, (HEIGHT, WIDTH, 1)).astype(np.int16)
        w.write(np.clip(img, 0, 255).astype(np.uint8))
    w.release()


def sequential(path: Path, camera: PinholeCamera) -> tuple[float, int, int]:
    seq = VideoSequence(path, camera)
    t0 = time.perf_counter()
    n = 0
    for i in range(len(seq)):
        seq[i]
        n += 1
    dt = time.perf_counter() - t0
    seq.close()
    return n / dt, n, seq.seeks


def seek_per_frame(path: Path, frames: int) -> float:
    cap = cv2.VideoCapture(str(path))
    t0 = time.perf_counter()
    for i in range(frames):
        cap.set(cv2.CAP_PROP_POS_FRAMES, i)
        ok, frame = cap.read()
        if not ok:
            raise SystemExit(f"{path}: cannot decode frame {i} by seeking")
        cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    dt = time.perf_counter() - t0
    cap.release()
    return frames / dt


def bare_read(path: Path) -> float:
    cap = cv2.VideoCapture(str(path))
    t0 = time.perf_counter()
    n = 0
    while cap.read()[0]:
        n += 1
    dt = time.perf_counter() - t0
    cap.release()
    return n / dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--seek-frames", type=int, default=200, help="frames read by seeking (default 200)")
    ap.add_argument("--codecs", nargs="+", default=["mp4v", "XVID", "MJPG"], choices=sorted(SUFFIX))
    ap.add_argument("--cpu", type=int, default=None, help="the CPU to pin to (default: the first allowed)")
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        cpu = args.cpu if args.cpu is not None else min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        print(f"pinned to CPU {cpu}")
    cv2.setNumThreads(1)
    camera = PinholeCamera(500.0, 500.0, WIDTH / 2, HEIGHT / 2, WIDTH, HEIGHT, fps=30.0, name="clip")
    print(f"{args.frames} frames {WIDTH}x{HEIGHT} at 30 fps; frames/s (higher is better)")
    print(f"{'codec':6} {'MB':>6} {'in order':>9} {'seeks':>6} {'seek/frame':>11} {'bare read':>10}")
    with tempfile.TemporaryDirectory() as tmp:
        for fourcc in args.codecs:
            path = Path(tmp) / f"clip_{fourcc}{SUFFIX[fourcc]}"
            write_clip(path, fourcc, args.frames)
            mb = path.stat().st_size / 1e6
            fps_seq, n, seeks = sequential(path, camera)
            if n != args.frames:
                raise SystemExit(f"{fourcc}: read {n} of {args.frames} frames")
            fps_seek = seek_per_frame(path, min(args.seek_frames, args.frames))
            fps_bare = bare_read(path)
            print(f"{fourcc:6} {mb:6.1f} {fps_seq:9.0f} {seeks:6d} {fps_seek:11.0f} {fps_bare:10.0f}")


if __name__ == "__main__":
    main()
