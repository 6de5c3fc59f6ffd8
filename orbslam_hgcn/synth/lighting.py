"""Baked lighting of the synthetic scenes: point lights and contact shadows.

Lighting is view independent (diffuse), so it is baked into each surface texture once:
Lambertian irradiance from the scene's point lights (no cast shadows), and a soft
darkening of upward-facing surfaces next to the bottom edges of the objects standing on
them (ambient occlusion along contact lines), which keeps boxes from looking as if they
floated.
"""

from __future__ import annotations

import cv2
import numpy as np

from orbslam_hgcn.synth.scene import Quad, Scene

AO_DEPTH = 0.45  # darkening right at a contact line
AO_RANGE_M = 0.06  # e-folding distance of the contact darkening


def contact_edges(scene: Scene) -> list[np.ndarray]:
    """For every quad, the (K, 2, 3) bottom edges of vertical quads standing on it (scene frame).

    Only upward-facing quads get edges: those of vertical quads whose lowest edge lies in
    the quad's plane (within 1 cm) and whose middle lies over the quad.
    """
    normals = np.stack([q.normal for q in scene.quads])
    vertical = np.flatnonzero(np.abs(normals[:, 2]) < 0.1)
    bottoms = []
    for i in vertical:
        c = scene.quads[i].corners
        low = np.argsort(c[:, 2])[:2]
        if abs(c[low[0], 2] - c[low[1], 2]) < 1e-6:
            bottoms.append(c[low])
    bottoms = np.asarray(bottoms).reshape(-1, 2, 3)
    out = []
    for q, n in zip(scene.quads, normals):
        if n[2] < 0.99 or len(bottoms) == 0:
            out.append(np.zeros((0, 2, 3)))
            continue
        mid = bottoms.mean(axis=1) - q.origin
        a, b = mid @ q.u_axis, mid @ q.v_axis
        on = (np.abs(bottoms[:, 0, 2] - q.origin[2]) < 0.01) & (a > -0.01) & (a < q.size_u + 0.01) & \
            (b > -0.01) & (b < q.size_v + 0.01)
        out.append(bottoms[on])
    return out


def shading(quad: Quad, lights: np.ndarray, nv: int, nu: int, contacts: np.ndarray | None = None) -> np.ndarray:
    """(nv, nu) float32 brightness factor of a quad's texture.

    Lambertian irradiance from point lights (L, 3), sampled every 5 cm and normalised so
    that a desk-top point 1.9 m below the lights gets 1; times the contact darkening near
    the edges (K, 2, 3), from a distance transform at 1 cm.
    """
    shade = np.ones((nv, nu), np.float32)
    if len(lights):
        gu = max(2, int(np.ceil(quad.size_u / 0.05)) + 1)
        gv = max(2, int(np.ceil(quad.size_v / 0.05)) + 1)
        a = np.linspace(0.0, quad.size_u, gu)
        b = np.linspace(0.0, quad.size_v, gv)
        P = quad.origin + b[:, None, None] * quad.v_axis + a[None, :, None] * quad.u_axis  # (gv, gu, 3)
        E = np.zeros((gv, gu))
        for L in lights:
            d = L - P
            r = np.linalg.norm(d, axis=-1)
            E += np.maximum(d @ quad.normal, 0.0) / np.maximum(r, 0.3) ** 3
        E = np.clip(0.45 + 0.55 * E / (len(lights) * 0.5 / 1.9 ** 2), 0.3, 1.35).astype(np.float32)
        shade = cv2.resize(E, (nu, nv), interpolation=cv2.INTER_LINEAR)
    if contacts is not None and len(contacts):
        cm = 0.01
        gu, gv = int(np.ceil(quad.size_u / cm)) + 1, int(np.ceil(quad.size_v / cm)) + 1
        mask = np.full((gv, gu), 255, np.uint8)
        rel = contacts - quad.origin
        ends = np.stack([rel @ quad.u_axis, rel @ quad.v_axis], axis=-1) / cm  # (K, 2, 2) grid coords
        for p0, p1 in np.round(ends * 16).astype(np.int32).tolist():
            cv2.line(mask, tuple(p0), tuple(p1), 0, 1, cv2.LINE_8, 4)
        dist = cv2.distanceTransform(mask, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * cm
        ao = (1.0 - AO_DEPTH * np.exp(-dist / AO_RANGE_M)).astype(np.float32)
        shade = shade * cv2.resize(ao, (nu, nv), interpolation=cv2.INTER_LINEAR)
    return shade
