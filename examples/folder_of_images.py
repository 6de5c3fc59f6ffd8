"""Track a folder of images with the Python API and write the trajectory and map.

    python examples/folder_of_images.py ../shared/data/tum_fr3_sitting_xyz_148/rgb --camera tum_fr3 --out out

The images are taken in name order. Images named by their timestamp in seconds (as TUM's are)
keep it; others are stamped at --fps frames per second. --camera is a shipped camera name or a
YAML file with fx, fy, cx, cy, width, height.
"""

import argparse
import sys
from pathlib import Path

import cv2

from orbslam_hgcn import OrbslamError, Slam

IMAGES = (".png", ".jpg", ".jpeg", ".bmp")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folder")
    p.add_argument("--camera", required=True, help="shipped camera name (tum_fr3, ...) or camera YAML")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--out", required=True)
    args = p.parse_args()
    files = sorted(f for f in Path(args.folder).iterdir() if f.suffix.lower() in IMAGES)
    if not files:
        print(f"{args.folder}: no images", file=sys.stderr)
        return 2
    try:
        stamps = [float(f.stem) for f in files]
    except ValueError:
        stamps = [i / args.fps for i in range(len(files))]
    try:
        with Slam(camera=args.camera) as slam:
            for i, (f, t) in enumerate(zip(files, stamps)):
                image = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
                result = slam.track(image, t)
                if i % 20 == 0:
                    print(f"frame {i}: {result.state}, {result.points} points")
            slam.close()  # finish mapping before reading the map
            m = slam.map()
            print(f"{len(m.keyframe_ids)} keyframes, {len(m.points)} map points")
            for path in slam.save(args.out).values():
                print("wrote", path)
            print("wrote", slam.save_map(Path(args.out) / "map.npz"))
            print("wrote", slam.export_ply(Path(args.out) / "map.ply")["points"])
    except OrbslamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
