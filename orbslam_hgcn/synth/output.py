"""Writers of rendered sequences: the TUM RGB-D layout and the KITTI odometry layout, and
the folder they write into.

A writer takes the frames one by one (``frame``), then the ground truth (``finish``);
``complete(out)`` says whether a folder already holds every frame it lists.

A sequence is rendered into a temporary folder beside its output folder
(:func:`partial_folder`, ``.NAME.partial-PID``) and moved into place only once complete
(:func:`install`), so an output folder never holds a half-written sequence: a render that
is interrupted leaves only its temporary folder, which the next render of that folder
removes (:func:`remove_stale_partials`) once the process that made it has ended.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

import cv2
import numpy as np

from orbslam_hgcn.errors import ConfigError, DatasetError
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.se3 import inv_T
from orbslam_hgcn.trajectory import Trajectory, write_tum

log = logging.getLogger(__name__)

# Every file and folder a render writes into its output folder (either layout).
OUTPUTS = ("rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "camera.yaml", "scene.json", "loop_gt.npy",
           "sequences", "poses")

# zlib level 1 with run-length matching: ~25 % faster than plain level 1 and ~10 % smaller
# on these frames (measured with OpenCV 5.0).
PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
IMAGE_FORMATS = ("png", "jpg")  # the frames' file formats (depth images are always 16-bit PNG)


def frame_encoding(image_format: str = "png", jpeg_quality: int = 0) -> tuple[str, list[int]]:
    """(file suffix, cv2.imwrite parameters) of the frames of an ``image_format`` render:
    lossless PNG, or baseline JPEG at ``jpeg_quality`` (1-100)."""
    if image_format == "jpg":
        return ".jpg", [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)]
    if image_format != "png":
        raise ConfigError(f"image format must be one of {', '.join(IMAGE_FORMATS)}, not {image_format!r}")
    return ".png", PNG_PARAMS


class TumWriter:
    """rgb/<timestamp>.png (or .jpg), rgb.txt, groundtruth.txt (and depth/, depth.txt, 5000
    per metre, PNG)."""

    grey = False

    def __init__(self, out: Path, stamps: np.ndarray, depth: bool, image_format: str = "png",
                 jpeg_quality: int = 0):
        self.out = out
        self.depth = depth
        self.ext, self.params = frame_encoding(image_format, jpeg_quality)
        self.names = [f"{t:.6f}" for t in stamps]
        if len(set(self.names)) != len(self.names):
            raise ConfigError("frame rate too high for 6-decimal timestamps")
        (out / "rgb").mkdir(parents=True, exist_ok=True)
        if depth:
            (out / "depth").mkdir(exist_ok=True)

    @property
    def dataset_dir(self) -> Path:
        return self.out

    @staticmethod
    def complete(out: Path, sequence: int = 0, image_format: str = "png") -> bool:
        """Whether ``out`` holds every frame its rgb.txt lists (whatever their format)."""
        if not (out / "rgb.txt").is_file():
            return False
        listed = [ln.split()[1] for ln in (out / "rgb.txt").read_text().splitlines() if ln and ln[0] != "#"]
        return bool(listed) and all((out / p).is_file() for p in listed)

    def frame(self, k: int, img: np.ndarray, inv_depth: np.ndarray) -> None:
        name = self.names[k]
        if not cv2.imwrite(str(self.out / "rgb" / f"{name}{self.ext}"), img, self.params):
            raise DatasetError(f"{self.out / 'rgb'}: cannot write {name}{self.ext}")
        if self.depth:
            z = np.where(inv_depth > 0, 5000.0 / np.maximum(inv_depth, 1e-9), 0.0)
            cv2.imwrite(str(self.out / "depth" / f"{name}.png"), np.clip(z + 0.5, 0, 65535).astype(np.uint16),
                        PNG_PARAMS)

    def finish(self, stamps: np.ndarray, poses_wc: np.ndarray, camera: PinholeCamera) -> None:
        out, names = self.out, self.names
        with (out / "rgb.txt").open("w", encoding="utf-8") as fh:
            fh.write("# synthetic colour images\n# timestamp filename\n")
            fh.writelines(f"{n} rgb/{n}{self.ext}\n" for n in names)
        if self.depth:
            with (out / "depth.txt").open("w", encoding="utf-8") as fh:
                fh.write("# synthetic depth images, 5000 per metre\n# timestamp filename\n")
                fh.writelines(f"{n} depth/{n}.png\n" for n in names)
        write_tum(out / "groundtruth.txt", Trajectory(stamps, poses_wc))


class KittiWriter:
    """sequences/NN/{image_0/, times.txt, calib.txt} and poses/NN.txt, as KITTI's odometry
    benchmark lays them out; grey frames (image_0/NNNNNN.png, or .jpg). Poses are T_wc with the first camera as the world
    (KITTI's convention), 12 row-major values, 10 significant digits. Depth (on request):
    sequences/NN/depth/, 16-bit, 256 per metre (KITTI's depth benchmark scale)."""

    grey = True

    def __init__(self, out: Path, stamps: np.ndarray, depth: bool, sequence: int = 0, image_format: str = "png",
                 jpeg_quality: int = 0):
        self.out = out
        self.seq = out / "sequences" / f"{sequence:02d}"
        self.sequence = sequence
        self.depth = depth
        self.ext, self.params = frame_encoding(image_format, jpeg_quality)
        (self.seq / "image_0").mkdir(parents=True, exist_ok=True)
        if depth:
            (self.seq / "depth").mkdir(exist_ok=True)

    @property
    def dataset_dir(self) -> Path:
        return self.seq

    @staticmethod
    def complete(out: Path, sequence: int = 0, image_format: str = "png") -> bool:
        """Whether ``out`` holds every frame its times.txt lists, as ``image_format`` files."""
        seq = out / "sequences" / f"{sequence:02d}"
        ext = frame_encoding(image_format)[0]
        if not (seq / "times.txt").is_file() or not (out / "poses" / f"{sequence:02d}.txt").is_file():
            return False
        n = sum(1 for ln in (seq / "times.txt").read_text().splitlines() if ln.strip())
        return n > 0 and all((seq / "image_0" / f"{k:06d}{ext}").is_file() for k in range(n))

    def frame(self, k: int, img: np.ndarray, inv_depth: np.ndarray) -> None:
        if not cv2.imwrite(str(self.seq / "image_0" / f"{k:06d}{self.ext}"), img, self.params):
            raise DatasetError(f"{self.seq / 'image_0'}: cannot write {k:06d}{self.ext}")
        if self.depth:
            z = np.where(inv_depth > 0, 256.0 / np.maximum(inv_depth, 1e-9), 0.0)
            cv2.imwrite(str(self.seq / "depth" / f"{k:06d}.png"), np.clip(z + 0.5, 0, 65535).astype(np.uint16),
                        PNG_PARAMS)

    def finish(self, stamps: np.ndarray, poses_wc: np.ndarray, camera: PinholeCamera) -> None:
        with (self.seq / "times.txt").open("w", encoding="utf-8") as fh:
            fh.writelines(f"{t - stamps[0]:.6e}\n" for t in stamps)
        K = camera.K
        with (self.seq / "calib.txt").open("w", encoding="utf-8") as fh:
            for key, shift in (("P0", 0.0), ("P1", -0.54), ("P2", 0.0), ("P3", -0.54)):
                P = np.hstack([K, [[shift * camera.fx], [0.0], [0.0]]])
                fh.write(f"{key}: " + " ".join(f"{v:.12e}" for v in P.ravel()) + "\n")
        rel = inv_T(poses_wc[0]) @ poses_wc
        (self.out / "poses").mkdir(exist_ok=True)
        with (self.out / "poses" / f"{self.sequence:02d}.txt").open("w", encoding="utf-8") as fh:
            fh.writelines(" ".join(f"{v:.9e}" for v in T[:3].ravel()) + "\n" for T in rel)


def make_writer(layout: str, out: Path, stamps: np.ndarray, depth: bool, sequence: int = 0,
                image_format: str = "png", jpeg_quality: int = 0):
    if layout == "kitti":
        return KittiWriter(out, stamps, depth, sequence, image_format, jpeg_quality)
    return TumWriter(out, stamps, depth, image_format, jpeg_quality)


def writer_class(layout: str):
    return KittiWriter if layout == "kitti" else TumWriter


def existing_render(out: Path, meta_options: dict, writer=TumWriter, sequence: int = 0) -> str:
    """What the folder ``out`` holds: ``"empty"`` (missing or empty), ``"same"`` (this very
    sequence, every frame present), ``"incomplete"`` (nothing but a render's files, and no
    complete sequence: a render interrupted before renders were made atomic) or ``"other"``
    (another sequence, or files of the user's)."""
    if not out.exists() or (out.is_dir() and not any(out.iterdir())):
        return "empty"
    if not out.is_dir():
        return "other"
    meta = out / "scene.json"
    old = None
    if meta.is_file():
        try:
            old = json.loads(meta.read_text(encoding="utf-8")).get("options")
        except (OSError, json.JSONDecodeError, AttributeError):
            old = None
    # Complete by the options it was rendered with (the frames' format among them: a PNG
    # render asked for as JPEG is another, complete sequence, not an interrupted one).
    old_format = old.get("image_format", "png") if isinstance(old, dict) else "png"
    complete = (old is not None and old_format in IMAGE_FORMATS
                and writer.complete(out, sequence, old_format))
    if complete and old == meta_options:
        return "same"
    if not complete and all(p.name in OUTPUTS for p in out.iterdir()):
        return "incomplete"
    return "other"


def partial_folder(out: Path) -> Path:
    """The temporary folder this process renders ``out`` into (beside it, so that the
    final rename stays on one file system)."""
    return out.parent / f".{out.name}.partial-{os.getpid()}"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_partials(out: Path) -> None:
    """Remove the temporary folders of renders of ``out`` whose process has ended (killed,
    or the machine stopped) and this process's own."""
    if not out.parent.is_dir():
        return
    for p in out.parent.glob(f".{out.name}.partial-*"):
        try:
            pid = int(p.name.rsplit("-", 1)[1])
        except ValueError:
            continue
        if pid == os.getpid() or not _alive(pid):
            log.info("removing %s, left by an interrupted render", p)
            shutil.rmtree(p, ignore_errors=True)


def clear_outputs(out: Path) -> None:
    """Remove a render's files from ``out``, leaving any other file there."""
    for name in OUTPUTS:
        p = out / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()


def install(partial: Path, out: Path) -> None:
    """Move a complete render from ``partial`` to ``out``: one rename when ``out`` is
    missing or empty; otherwise the render's files in ``out`` are replaced entry by entry
    (its other files stay)."""
    if out.is_dir() and not any(out.iterdir()):
        out.rmdir()
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        os.replace(partial, out)
        return
    clear_outputs(out)
    for p in sorted(partial.iterdir(), key=lambda q: q.name == "scene.json"):  # scene.json last
        os.replace(p, out / p.name)
    partial.rmdir()
