"""Track a live camera (or a network stream) with the Python API until Ctrl-C.

    python examples/webcam.py cam:0 --camera my_camera.yaml --out out
    python examples/webcam.py rtsp://192.168.1.20/stream --camera my_camera.yaml --out out

The camera YAML holds the calibration at the resolution the device delivers (fx, fy, cx, cy,
width, height, and dist when the lens distorts). Frames that arrive while the system is busy
are dropped, so the pose printed is always that of a recent frame. `orbslam-hgcn run cam:0
--config my_camera.yaml --out out` does the same from the command line.
"""

import argparse
import sys

from orbslam_hgcn import OrbslamError, Slam
from orbslam_hgcn.datasets.live import LiveSource


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("source", help="cam:N, or a stream URL (rtsp://, http://, ...)")
    p.add_argument("--camera", required=True, help="camera YAML (or a shipped camera name)")
    p.add_argument("--out", required=True)
    p.add_argument("--max-frames", type=int, default=None)
    args = p.parse_args()
    try:
        with Slam(camera=args.camera) as slam:
            try:
                with LiveSource(args.source, slam.camera) as source:
                    for n, frame in enumerate(source, 1):
                        result = slam.track(frame.image, frame.timestamp)
                        where = "" if result.pose is None else " at " + " ".join(f"{x:+.3f}" for x in result.pose[:3, 3])
                        print(f"\rframe {frame.index}: {result.state}{where}, dropped {source.dropped}   ", end="")
                        if args.max_frames and n >= args.max_frames:
                            break
            except KeyboardInterrupt:
                pass
            print()
            slam.close()
            for path in slam.save(args.out).values():
                print("wrote", path)
    except OrbslamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
