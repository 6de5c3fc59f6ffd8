"""Map part of a sequence, save the map, then relocalise later frames on it (localisation only).

    python examples/relocalise_saved_map.py ../shared/data/tum_fr3_sitting_xyz_148 --out out

The first half of the frames builds the map; a second Slam loads it with localization=True and
tracks every later frame against it without changing it (ORB-SLAM's localisation mode).
"""

import argparse
import sys
from pathlib import Path

from orbslam_hgcn import OrbslamError, Slam
from orbslam_hgcn.datasets import open_sequence


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset", help="a TUM, EuRoC or KITTI folder")
    p.add_argument("--out", required=True)
    args = p.parse_args()
    out = Path(args.out)
    try:
        frames = open_sequence(None, args.dataset)
        half = len(frames) // 2
        with Slam(camera=frames.camera) as slam:
            for i in range(half):
                rec = frames[i]
                slam.track(rec.image, rec.timestamp)
            slam.close()
            map_file = slam.save_map(out / "map.npz")
        print(f"mapped frames 0-{half - 1}: {map_file}")
        with Slam(camera=frames.camera, load_map=map_file, localization=True) as loc:
            located = 0
            for i in range(half, len(frames)):
                rec = frames[i]
                located += loc.track(rec.image, rec.timestamp, frame=i).ok
            loc.close()
            loc.save(out / "localised")
        print(f"localised {located} of {len(frames) - half} later frames on the saved map")
    except OrbslamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
