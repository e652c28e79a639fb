"""Open an RGB-D source by name: the one place that knows every source module.

Kept apart from :mod:`services.detector.sources` (the types every source shares), which the
camera modules import: a factory there would make them import each other.
"""

from __future__ import annotations

from services.detector.sources import FolderSource, FrameSource, KinectSource


def open_source(spec: str, *, rate: float = 1.0, loop: bool = False, device_id: int = 0,
                depth_mode: str = "wfov_binned", fps: int = 30, undistort: bool = True
                ) -> FrameSource:
    """An open source: ``"kinect"``, ``"realsense"`` or ``"realsense:SERIAL"``, ``"bag:FILE"``
    (RealSense recording), ``"kinect-recording:FILE"`` (.mkv), ``"folder:DIR"`` (or ``DIR``).

    The RealSense and recording sources live in :mod:`services.detector.cameras` (imported
    only for them); ``handkse camera`` offers their other options."""
    if spec == "kinect":
        return KinectSource(device_id, depth_mode, fps, undistort)
    kind, _, arg = spec.partition(":")
    if kind == "realsense":
        from services.detector.cameras.realsense import RealSenseSource

        return RealSenseSource(serial=arg or None, fps=fps, undistort=undistort,
                               option=f"--source {spec}")
    if kind == "bag":
        from services.detector.cameras.realsense_recording import RealSenseRecording

        return RealSenseRecording(arg, rate=rate, loop=loop, undistort=undistort,
                                  option="--source")
    if kind == "kinect-recording":
        from services.detector.cameras.kinect_recording import KinectRecordingSource

        return KinectRecordingSource(arg, rate=rate, loop=loop, undistort=undistort,
                                     option="--source")
    path = spec.removeprefix("folder:")
    return FolderSource(path, rate=rate, loop=loop, fps=fps)


__all__ = ["open_source"]
