"""Landmark pixels + registered depth -> 3-D points in the camera frame.

Camera frame: OpenCV convention (x right, y down, z forward), metres. The depth image is
registered to the colour image (one depth value per colour ray; it may have a different
resolution, e.g. half, and is then sampled at the scaled pixel). Depth stores z, not the ray
length, so ``X = z K^-1 [u, v, 1]^T``.

Robust depth of a landmark (:func:`landmark_depths`): in a small window around its pixel,
1. drop holes (0 / outside ``[depth_min_m, depth_max_m]``) and *edge pixels*, whose depth differs
   from a 4-neighbour by more than ``edge_jump_m`` (flying pixels between a finger and what is
   behind it, and the pixels on either side of a depth discontinuity);
2. pick the reference depth: the centre pixel when it survived, else the nearest surviving
   value (a landmark sits on the hand, which is in front of what is around it);
3. return the median of the surviving pixels within ``cluster_m`` of the reference, or NaN when
   fewer than ``min_valid`` pixels are left.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import CameraIntrinsics


def landmark_depths(depth: NDArray[Any], scale_m: float, pixels: NDArray[Any],
                    color_size: tuple[int, int], *, window: int = 5, min_valid: int = 3,
                    edge_jump_m: float = 0.02, cluster_m: float = 0.015,
                    depth_min_m: float = 0.15, depth_max_m: float = 5.0) -> NDArray[np.float64]:
    """Robust depth z (m) at each colour pixel ``pixels`` (N, 2); NaN where there is none.

    ``depth``: (H_d, W_d) raw depth units (``scale_m`` metres each; 0 = no reading), registered
    to a colour image of ``color_size = (width, height)``.
    """
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    n = len(pixels)
    hd, wd = depth.shape
    cw, ch = color_size
    # colour pixel (continuous, pixel centres at integers) -> nearest depth pixel
    du = np.rint((pixels[:, 0] + 0.5) * (wd / cw) - 0.5).astype(np.int64)
    dv = np.rint((pixels[:, 1] + 0.5) * (hd / ch) - 0.5).astype(np.int64)
    r = window // 2
    # window plus a one-pixel ring for the neighbour test: (N, window + 2, window + 2)
    offsets = np.arange(-r - 1, r + 2)
    rows = dv[:, None] + offsets[None, :]
    cols = du[:, None] + offsets[None, :]
    inside = ((rows >= 0) & (rows < hd))[:, :, None] & ((cols >= 0) & (cols < wd))[:, None, :]
    patch = depth[np.clip(rows, 0, hd - 1)[:, :, None],
                  np.clip(cols, 0, wd - 1)[:, None, :]].astype(np.float64) * scale_m
    valid = inside & (patch >= depth_min_m) & (patch <= depth_max_m)
    patch = np.where(valid, patch, np.nan)
    centre = patch[:, 1:-1, 1:-1]
    with np.errstate(invalid="ignore"):
        jump = np.zeros_like(centre)
        for dr, dc in ((0, 1), (2, 1), (1, 0), (1, 2)):
            neighbour = patch[:, dr:dr + window, dc:dc + window]
            # a missing neighbour is no evidence of an edge (holes are common on skin)
            jump = np.fmax(jump, np.abs(centre - neighbour))
        usable = np.isfinite(centre) & ~(jump > edge_jump_m)
    values = np.where(usable, centre, np.nan).reshape(n, -1)
    mid = values[:, (window * window) // 2]
    out = np.full(n, np.nan)
    has_any = np.asarray(np.isfinite(values).any(axis=1), np.bool_)
    if not has_any.any():
        return out
    with np.errstate(invalid="ignore"):
        nearest = np.nanmin(np.where(has_any[:, None], values, np.inf), axis=1)
        reference = np.where(np.isfinite(mid), mid, nearest)
        member = np.abs(values - reference[:, None]) <= cluster_m
        counts = member.sum(axis=1)
        clustered = np.where(member, values, np.nan)
        ok = has_any & (counts >= min_valid)
        if ok.any():
            out[ok] = np.nanmedian(clustered[ok], axis=1)
    return out


def backproject(pixels: NDArray[Any], z: NDArray[Any], intrinsics: CameraIntrinsics
                ) -> NDArray[np.float64]:
    """Points (N, 3) in the camera frame: ``X = z K^-1 [u, v, 1]``; NaN rows where z is NaN."""
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    z = np.asarray(z, np.float64).reshape(-1)
    x = (pixels[:, 0] - intrinsics.cx) / intrinsics.fx * z
    y = (pixels[:, 1] - intrinsics.cy) / intrinsics.fy * z
    return np.column_stack([x, y, z])


def project(points: NDArray[Any], intrinsics: CameraIntrinsics) -> NDArray[np.float64]:
    """Inverse of :func:`backproject`: camera-frame points (N, 3) -> pixels (N, 2)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    return np.column_stack([intrinsics.fx * p[:, 0] / p[:, 2] + intrinsics.cx,
                            intrinsics.fy * p[:, 1] / p[:, 2] + intrinsics.cy])


def to_world(points: NDArray[Any], T_world_camera: NDArray[Any]) -> NDArray[np.float64]:
    """Camera-frame points (N, 3) -> world frame (NaN rows stay NaN)."""
    T = np.asarray(T_world_camera, np.float64)
    return np.asarray(points, np.float64) @ T[:3, :3].T + T[:3, 3]


__all__ = ["backproject", "landmark_depths", "project", "to_world"]
