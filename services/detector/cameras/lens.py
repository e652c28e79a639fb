"""The colour camera's lens distortion, and its removal from colour and registered depth.

``RgbdFrame`` carries pinhole intrinsics only, so a source whose camera reports a distortion
model removes it before publishing (``--no-undistort`` keeps the images as they are).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from services.common.protocol import CameraIntrinsics

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LensDistortion:
    """The colour camera's lens distortion, as the SDK reports it.

    ``model`` ``"opencv"``: Brown-Conrady in OpenCV's order and meaning, ``(k1, k2, p1, p2[,
    k3[, k4, k5, k6]])`` (RealSense ``brown_conrady``, the Azure Kinect's and Orbbec Femto's
    rational model); another name is a model this code does not remove (e.g. RealSense
    ``inverse_brown_conrady``, whose coefficients are zero on D400 colour streams).
    """

    model: str
    coeffs: tuple[float, ...] = ()

    @property
    def is_identity(self) -> bool:
        return not any(self.coeffs)


NO_DISTORTION = LensDistortion("none")


class Undistorter:
    """Removes the colour camera's distortion from colour and registered depth alike.

    Both images are remapped with the same map onto the pinhole model of the same camera
    matrix, so the published intrinsics hold and depth stays registered (depth with nearest
    neighbour: no invented readings between surfaces). Inactive when disabled, when the
    coefficients are all zero, or for a model it does not know (then the images go out as they
    are and a warning names the model: pinhole intrinsics are then an approximation).
    """

    def __init__(self, intrinsics: CameraIntrinsics, distortion: LensDistortion,
                 enabled: bool = True) -> None:
        self._linear: tuple[NDArray[np.int16], NDArray[np.uint16]] | None = None
        self._nearest: NDArray[np.int16] | None = None
        if not enabled or distortion.is_identity:
            return
        if distortion.model != "opencv" or len(distortion.coeffs) not in (4, 5, 8):
            log.warning("colour lens model %s %s is not removed: images are published as the "
                        "camera delivers them", distortion.model, list(distortion.coeffs))
            return
        K = np.array([[intrinsics.fx, 0.0, intrinsics.cx], [0.0, intrinsics.fy, intrinsics.cy],
                      [0.0, 0.0, 1.0]])
        map_x, map_y = cv2.initUndistortRectifyMap(K, np.asarray(distortion.coeffs, np.float64),
                                                   None, K, (intrinsics.width, intrinsics.height),
                                                   cv2.CV_32FC1)
        # fixed-point maps are faster; the nearest-neighbour one must be rounded when made, as
        # remap's nearest mode on a bilinear fixed-point map truncates (up to a pixel off)
        self._linear = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)
        self._nearest = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2, nninterpolation=True)[0]

    @property
    def active(self) -> bool:
        return self._linear is not None

    def apply(self, color_bgr: NDArray[np.uint8], depth: NDArray[np.uint16]
              ) -> tuple[NDArray[np.uint8], NDArray[np.uint16]]:
        """Colour (bilinear) and depth registered to it (nearest), both undistorted."""
        if self._linear is None or self._nearest is None:
            return color_bgr, depth
        color = cv2.remap(color_bgr, *self._linear, cv2.INTER_LINEAR)
        registered = cv2.remap(depth, self._nearest, None, cv2.INTER_NEAREST)
        return np.asarray(color, np.uint8), np.asarray(registered, np.uint16)


__all__ = ["NO_DISTORTION", "LensDistortion", "Undistorter"]
