"""Test images in the pixel formats cameras deliver, made with OpenCV's own BGR -> YUV."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray


def block_image(rng: np.random.Generator, height: int, width: int) -> NDArray[np.uint8]:
    """(height, width, 3) BGR of random colours constant over 2x2 blocks, so 4:2:0 and 4:2:2
    chroma subsampling loses nothing."""
    blocks = rng.integers(20, 236, (height // 2, width // 2, 3), dtype=np.uint8)
    return np.ascontiguousarray(blocks.repeat(2, axis=0).repeat(2, axis=1))


def _yuv_planes(bgr: NDArray[np.uint8]) -> tuple[NDArray[np.uint8], NDArray[np.uint8],
                                                 NDArray[np.uint8]]:
    """Y (h, w), U and V (h/2, w/2) of BGR, BT.601 as OpenCV's YUV 4:2:0 conversions."""
    h, w = bgr.shape[:2]
    i420 = np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_I420), np.uint8).reshape(-1)
    y = i420[:h * w].reshape(h, w)
    u = i420[h * w:h * w * 5 // 4].reshape(h // 2, w // 2)
    v = i420[h * w * 5 // 4:].reshape(h // 2, w // 2)
    return y, u, v


def nv12_from_bgr(bgr: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """NV12: the Y plane, then rows of interleaved U, V; shape (h * 3 / 2, w)."""
    y, u, v = _yuv_planes(bgr)
    uv = np.stack([u, v], axis=-1).reshape(u.shape[0], -1)
    return np.concatenate([y, uv], axis=0)


def yuv422_from_bgr(bgr: NDArray[np.uint8], order: str) -> NDArray[np.uint8]:
    """Packed 4:2:2, shape (h, w, 2): ``order`` "yuyv" (Y0 U Y1 V) or "uyvy" (U Y0 V Y1)."""
    y, u, v = _yuv_planes(bgr)
    u, v = u.repeat(2, axis=0), v.repeat(2, axis=0)  # 4:2:0 chroma on every row
    out = np.empty((*y.shape, 2), np.uint8)
    luma, chroma = (0, 1) if order == "yuyv" else (1, 0)
    out[:, :, luma] = y
    out[:, 0::2, chroma] = u
    out[:, 1::2, chroma] = v
    return out


def smooth_image(height: int, width: int) -> NDArray[np.uint8]:
    """(height, width, 3) BGR of slow colour gradients, which JPEG keeps within a few levels."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    channels = [128 + 90 * np.sin(x / width * 3.0 + k) * np.cos(y / height * 2.0 - k)
                for k in (0.0, 1.0, 2.0)]
    return np.ascontiguousarray(np.stack(channels, axis=-1).round(), np.uint8)
