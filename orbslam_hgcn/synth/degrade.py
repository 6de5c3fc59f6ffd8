"""Image degradations of synthetic sequences, each deterministic given the seed.

In the order a camera applies them:

* fog (``fog``): stretches of the sequence in haze and flat light, for low-texture
  stretches. Each (sub-)render is mixed towards a flat grey by the transmission
  ``exp(-f(t) beta z)`` of its own depth ``z`` (the sky turns fully grey) and its contrast
  is lowered by up to half; ``f(t)`` ramps from 0 to 1 and back over a second at each end
  of a stretch. ``fog`` is the contrast lost at the scene's reference depth (1.5 m in the
  office, 15 m in the street) at full strength.
* motion blur along the image motion (:func:`flow_blur`): every pixel is averaged along
  its own path over the shutter time, computed from its depth and the camera poses at
  the start, middle and end of the exposure (parallax, rotation, forward motion all
  included; the sky moves by rotation only). The gather uses the sharp middle render,
  so disocclusions are not filled in exactly; the sub-frame mode of ``synthetic`` is exact
  but renders up to 15 times per frame.
* vignetting (``vignetting``): radial falloff about the principal point, the image corners
  darkened by that fraction (Gaussian in the radius).
* auto-exposure steps (``exposure_steps``): at random times (mean interval
  ``exposure_step_interval`` s, on frame times) the brightness jumps by a factor
  ``1 +- a``, ``a`` uniform in [0.75, 1.25] times ``exposure_steps``, and the camera's
  exposure brings it back within 5 % over ``exposure_settle`` frames (exponentially).
* the sensor noise and slow exposure drift of ``synthetic.CameraEffects``, rounding;
* JPEG compression (``jpeg_quality``): encoded and decoded with OpenCV at that quality
  (skipped when the frames are written as JPEG files, ``image_format="jpg"``).
"""

from __future__ import annotations

import cv2
import numpy as np

from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.se3 import inv_T

MAX_BLUR_SAMPLES = 48  # samples along the longest streaks (one per pixel up to this)
MAX_FLOW_PX = 400.0  # displacements are capped here (points passing right by the camera)
FOG_GREY = 200.0  # grey level of the haze


class ExposureSteps:
    """Sudden auto-exposure steps and their settling: gain(t) multiplies the image."""

    def __init__(self, size: float, interval: float, settle_frames: int, fps: float, t0: float, t1: float, seed: int):
        rng = np.random.default_rng([int(seed), 41])
        self.tau = max(settle_frames, 1) / (3.0 * fps)  # exp(-3) = 5 % left after settle_frames
        times, factors = [], []
        t = t0 + rng.uniform(0.5, 1.5) * interval
        while t < t1 and size > 0:
            a = size * rng.uniform(0.75, 1.25)
            times.append(t0 + round((t - t0) * fps) / fps)  # on a frame time: the jump is whole
            factors.append(1.0 + a if rng.random() < 0.5 else max(1.0 - a, 0.05))
            t += rng.uniform(0.5, 1.5) * interval
        self.times = np.array(times)
        self.log_factors = np.log(np.array(factors))

    def gain(self, t: float) -> float:
        dt = t - self.times
        on = dt >= -1e-9
        return float(np.exp(np.sum(self.log_factors[on] * np.exp(-np.maximum(dt[on], 0.0) / self.tau))))


class FogSegments:
    """Stretches of fog: strength f(t) in [0, 1], one stretch per 25 s (at least one), each
    3-6 s long, in the last three quarters of the sequence, with 1 s smooth ramps."""

    def __init__(self, strength: float, ref_depth: float, t0: float, t1: float, seed: int):
        rng = np.random.default_rng([int(seed), 43])
        self.beta = -np.log(max(1.0 - strength, 1e-3)) / ref_depth
        self.contrast = 0.5 * strength
        span = t1 - t0
        n = max(1, int(round(span / 25.0)))
        lo = t0 + 0.25 * span
        slot = (t1 - lo) / n
        self.segments = []
        for k in range(n):
            length = min(rng.uniform(3.0, 6.0), 0.9 * slot)
            start = lo + k * slot + rng.uniform(0.0, max(slot - length, 0.0))
            self.segments.append((start, start + length))

    def strength(self, t: float) -> float:
        f = 0.0
        for a, b in self.segments:
            ramp = min(1.0, (b - a) / 2)
            x = min(np.clip((t - a) / ramp, 0, 1), np.clip((b - t) / ramp, 0, 1))
            f = max(f, float(x * x * (3 - 2 * x)))
        return f

    def apply(self, img: np.ndarray, inv_depth: np.ndarray, t: float) -> np.ndarray:
        """img (H, W[, 3]) in fog at time t -> float32 image."""
        f = self.strength(t)
        if f <= 0:
            return img
        with np.errstate(divide="ignore"):
            z = np.where(inv_depth > 0, 1.0 / np.maximum(inv_depth, 1e-9), np.inf).astype(np.float32)
        trans = np.exp(-np.float32(f * self.beta) * z) * np.float32(1.0 - f * self.contrast)
        if img.ndim == 3:
            trans = trans[..., None]
        return np.float32(FOG_GREY) + (img.astype(np.float32) - np.float32(FOG_GREY)) * trans


def vignette_map(camera: PinholeCamera, amount: float) -> np.ndarray:
    """(H, W) float32 falloff: 1 at the principal point, 1 - amount at the farthest corner."""
    u = np.arange(camera.width, dtype=np.float64) - camera.cx
    v = np.arange(camera.height, dtype=np.float64) - camera.cy
    r2 = u[None, :] ** 2 + v[:, None] ** 2
    r2max = max((x * x + y * y) for x in (u[0], u[-1]) for y in (v[0], v[-1]))
    return np.power(1.0 - amount, r2 / r2max).astype(np.float32)


def pixel_motion(camera: PinholeCamera, inv_depth: np.ndarray, T_wc: np.ndarray, T_other: np.ndarray) -> np.ndarray:
    """(H, W, 2) float32 displacement of the point seen at each pixel from pose T_wc to
    T_other (both (4, 4) T_wc); pixels with inverse depth 0 are at infinity."""
    h, w = inv_depth.shape
    x = ((np.arange(w, dtype=np.float32) - np.float32(camera.cx)) / np.float32(camera.fx))[None, :]
    y = ((np.arange(h, dtype=np.float32) - np.float32(camera.cy)) / np.float32(camera.fy))[:, None]
    T = (inv_T(T_other) @ np.asarray(T_wc, np.float64)).astype(np.float32)  # this camera -> the other
    R, t = T[:3, :3], T[:3, 3]
    X = [R[i, 0] * x + R[i, 1] * y + R[i, 2] + t[i] * inv_depth for i in range(3)]
    z = np.maximum(X[2], np.float32(1e-3))
    du = np.float32(camera.fx) * X[0] / z + np.float32(camera.cx) - (x * np.float32(camera.fx) + np.float32(camera.cx))
    dv = np.float32(camera.fy) * X[1] / z + np.float32(camera.cy) - (y * np.float32(camera.fy) + np.float32(camera.cy))
    flow = np.stack(np.broadcast_arrays(du, dv), -1)
    return np.clip(flow, -MAX_FLOW_PX, MAX_FLOW_PX).astype(np.float32)


def flow_blur(img: np.ndarray, inv_depth: np.ndarray, camera: PinholeCamera, T_mid: np.ndarray,
              T_start: np.ndarray, T_end: np.ndarray) -> np.ndarray:
    """Blur img (H, W[, 3]) along each pixel's motion over the exposure -> float32 image.

    The point seen at pixel p mid-exposure is at p + d(s) at shutter fraction s in [-1, 1],
    d quadratic through the displacements to the start and end poses. The pixel records
    what passes over it: the mean over s of the sharp image at p - d(s), with samples about
    a pixel apart along the longest streaks (99th percentile, at most MAX_BLUR_SAMPLES).
    """
    f0 = pixel_motion(camera, inv_depth, T_mid, T_start)
    f1 = pixel_motion(camera, inv_depth, T_mid, T_end)
    half = np.float32(0.5) * (f1 - f0)  # linear part
    bend = np.float32(0.5) * (f1 + f0)  # quadratic part
    length = np.linalg.norm(f1 - f0, axis=-1)
    n = int(min(MAX_BLUR_SAMPLES, np.ceil(np.percentile(length, 99))))
    src = img.astype(np.float32)
    if n < 2:
        return src
    n += 1 - n % 2  # odd: the middle sample is the sharp image itself
    h, w = inv_depth.shape
    gx = np.arange(w, dtype=np.float32)[None, :]
    gy = np.arange(h, dtype=np.float32)[:, None]
    acc = src.copy()
    for k in range(n):
        if k == n // 2:
            continue
        s = np.float32(-1.0 + 2.0 * k / (n - 1))
        d = s * half + (s * s) * bend
        acc += cv2.remap(src, gx - d[..., 0], gy - d[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return acc * np.float32(1.0 / n)


def jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    """img uint8 (H, W[, 3]) after a JPEG encode and decode at ``quality`` (1-100)."""
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)


class Degradations:
    """The degradations an options set asks for, over a sequence's time span [t0, t1].

    options: a ``SynthOptions`` (its fields ``fog``, ``vignetting``, ``exposure_steps``,
    ``exposure_step_interval``, ``exposure_settle``, ``jpeg_quality``, ``seed``, ``fps``,
    and ``image_format`` where it has one);
    ref_depth: the scene's typical depth (m) for the fog.
    """

    def __init__(self, options, camera: PinholeCamera, t0: float, t1: float, ref_depth: float):
        self.o = options
        self.fog = FogSegments(options.fog, ref_depth, t0, t1, options.seed) if options.fog > 0 else None
        self.vignette = vignette_map(camera, options.vignetting) if options.vignetting > 0 else None
        self.steps = (ExposureSteps(options.exposure_steps, options.exposure_step_interval, options.exposure_settle,
                                    options.fps, t0, t1, options.seed) if options.exposure_steps > 0 else None)

    def scene_post(self, t: float):
        """What to apply to each (sub-)render (img, inv_depth) at frame time t, or None."""
        if self.fog is None or self.fog.strength(t) <= 0:
            return None
        return lambda img, inv_depth: self.fog.apply(img, inv_depth, t)

    def photometric(self, img: np.ndarray, t: float) -> np.ndarray:
        """Vignetting and auto-exposure gain (before noise and rounding)."""
        if self.vignette is None and self.steps is None:
            return img
        out = img.astype(np.float32)
        if self.vignette is not None:
            out *= self.vignette if out.ndim == 2 else self.vignette[..., None]
        if self.steps is not None:
            out *= np.float32(self.steps.gain(t))
        return out

    def compress(self, img: np.ndarray) -> np.ndarray:
        """The in-memory JPEG round trip of ``jpeg_quality``; none when the frames are
        written as JPEG files (``image_format="jpg"``), which are the compression."""
        if not self.o.jpeg_quality or getattr(self.o, "image_format", "png") == "jpg":
            return img
        return jpeg(img, self.o.jpeg_quality)
