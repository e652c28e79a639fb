"""A RealSense recording written without a camera: the SDK's software device and recorder.

``pyrealsense2`` 2.59 and later record to rosbag2 ``.db3`` files; the recorder refuses any other
name, so the legacy ROS 1 ``.bag`` format cannot be produced here (its reader is the same SDK's,
exercised only by users' files).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class StreamSetup:
    """One recorded video stream: size and pinhole intrinsics (pixels)."""

    width: int
    height: int
    f: float

    def intrinsics(self, rs: Any) -> Any:
        out = rs.intrinsics()
        out.width, out.height = self.width, self.height
        out.fx = out.fy = self.f
        out.ppx, out.ppy = self.width / 2, self.height / 2
        out.model = rs.distortion.brown_conrady
        out.coeffs = [0.0] * 5
        return out


def write_recording(path: Path, colors_rgb: Sequence[NDArray[np.uint8]],
                    depths: Sequence[NDArray[np.uint16]], times_ms: Sequence[float], *,
                    color: StreamSetup, depth: StreamSetup, depth_units_m: float = 0.001,
                    fps: int = 30) -> None:
    """Record rgb8 colour and z16 depth frames (same count), both stamped ``times_ms`` in the
    hardware clock domain, the two cameras at the same pose."""
    import pyrealsense2 as rs

    device = rs.software_device()
    depth_sensor, color_sensor = device.add_sensor("Depth"), device.add_sensor("Color")
    profiles = []
    for uid, (sensor, setup, kind, fmt, bpp) in enumerate(
            [(depth_sensor, depth, rs.stream.depth, rs.format.z16, 2),
             (color_sensor, color, rs.stream.color, rs.format.rgb8, 3)]):
        stream = rs.video_stream()
        stream.type, stream.index, stream.uid = kind, 0, uid
        stream.width, stream.height, stream.fps, stream.bpp, stream.fmt = (
            setup.width, setup.height, fps, bpp, fmt)
        stream.intrinsics = setup.intrinsics(rs)
        profiles.append(sensor.add_video_stream(stream))
    depth_sensor.add_read_only_option(rs.option.depth_units, depth_units_m)
    same_pose = rs.extrinsics()
    same_pose.rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    same_pose.translation = [0.0, 0.0, 0.0]
    profiles[0].register_extrinsics_to(profiles[1], same_pose)
    recorder = rs.recorder(str(path), device)
    recorded = recorder.query_sensors()  # frames are written only through these
    sink = rs.frame_queue(100)
    for sensor in recorded:
        sensor.open(sensor.get_stream_profiles()[0])
        sensor.start(sink)
    for n, (rgb, z, t) in enumerate(zip(colors_rgb, depths, times_ms, strict=True)):
        for sensor, profile, pixels, bpp in ((depth_sensor, profiles[0], z, 2),
                                             (color_sensor, profiles[1], rgb, 3)):
            frame = rs.software_video_frame()
            frame.pixels = np.ascontiguousarray(pixels)
            frame.bpp, frame.stride = bpp, pixels.shape[1] * bpp
            frame.timestamp, frame.domain = t, rs.timestamp_domain.hardware_clock
            frame.frame_number = n
            frame.profile = profile.as_video_stream_profile()
            if bpp == 2:
                frame.depth_units = depth_units_m
            sensor.on_video_frame(frame)
    for sensor in recorded:
        sensor.stop()
        sensor.close()
    del recorder  # the file is complete once the recorder is gone
