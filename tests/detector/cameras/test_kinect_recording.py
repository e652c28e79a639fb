"""Azure Kinect / Femto recordings, against a stand-in for pyk4a (libk4a cannot be installed
here): colour decoding, depth in the colour camera, intrinsics, stamps, errors, the command.

What this does not test: reading a real ``.mkv`` (Matroska demuxing, MJPG tracks, the SDK's
depth-to-colour transformation), which only the real pyk4a + libk4a do.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from services.common.bus import Bus
from services.common.keys import Keys
from services.common.protocol import RgbdFrame
from services.detector.source_factory import open_source
from services.detector.sources import SourceUnavailable, decode_frame
from tests.conftest import Processes, output_of, wait_until, zenoh_args
from tests.detector.cameras.images import block_image, smooth_image

FAKE_SDK = Path(__file__).parent / "fake_sdk"
K = np.array([[605.0, 0.0, 639.5], [0.0, 604.0, 359.5], [0.0, 0.0, 1.0]])
TIMES_USEC = [200_000, 233_344, 266_678, 300_011]  # capture 0 has colour only
KEYS = Keys("k4a")


@pytest.fixture
def pyk4a(monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    """The stand-in, imported as ``pyk4a`` for this test only."""
    spec = importlib.util.spec_from_file_location("pyk4a", FAKE_SDK / "pyk4a" / "__init__.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    monkeypatch.setitem(sys.modules, "pyk4a", module)
    return module


def colors(fmt: str) -> list[np.ndarray]:
    """Four colour images with the capture's index in the top-left block's green."""
    rng = np.random.default_rng(5)
    out = []
    for i in range(4):
        image = smooth_image(720, 1280) if fmt == "COLOR_MJPG" else block_image(rng, 720, 1280)
        image[:16, :16] = (40, 60 + 40 * i, 80)
        out.append(image)
    return out


def depth_mm() -> np.ndarray:
    depth = np.full((720, 1280), 1000, np.uint16)
    depth[:, :100] = 0  # outside the depth camera's view
    return depth


def write(pyk4a: ModuleType, path: Path, fmt: str = "COLOR_MJPG", **kwargs: object) -> Path:
    images = colors(fmt)
    pyk4a.write_recording(path, [pyk4a.encode_color(c, fmt) for c in images],
                          [None, depth_mm(), depth_mm(), depth_mm()], TIMES_USEC, K=K,
                          color_format=fmt, **kwargs)
    return path


def test_a_recording_gives_colour_depth_in_metres_and_intrinsics(
        pyk4a: ModuleType, tmp_path: Path) -> None:
    from services.detector.cameras.kinect_recording import KinectRecordingSource

    source = KinectRecordingSource(write(pyk4a, tmp_path / "rec.mkv"), rate=0.0)
    assert not source.realtime
    assert source.intrinsics.to_dict() == {"fx": 605.0, "fy": 604.0, "cx": 639.5, "cy": 359.5,
                                           "width": 1280, "height": 720}
    frames = list(source)
    assert len(frames) == 3 and source.dropped["incomplete"] == 1  # capture 0: no depth
    assert source._playback.closed  # released when the recording ended
    expected = colors("COLOR_MJPG")
    for i, frame in enumerate(frames, start=1):
        assert frame.color_bgr.shape == (720, 1280, 3)
        assert np.abs(frame.color_bgr.astype(int) - expected[i]).mean() < 3.0  # MJPG
        metres = frame.depth.astype(float) * frame.depth_scale_m
        np.testing.assert_allclose(metres[:, 100:], 1.0)
        assert not frame.depth[:, :100].any()
    # the first complete capture anchors the host clock; device spacing in ns after it
    assert np.diff([f.stamp_ns for f in frames]).tolist() == [33_334_000, 33_333_000]


@pytest.mark.parametrize("fmt", ["COLOR_BGRA32", "COLOR_NV12", "COLOR_YUY2"])
def test_uncompressed_colour_formats(pyk4a: ModuleType, tmp_path: Path, fmt: str) -> None:
    from services.detector.cameras.kinect_recording import KinectRecordingSource

    frames = list(KinectRecordingSource(write(pyk4a, tmp_path / "rec.mkv", fmt), rate=0.0))
    expected = colors(fmt)
    assert len(frames) == 3
    for i, frame in enumerate(frames, start=1):
        error = np.abs(frame.color_bgr.astype(int) - expected[i])
        assert error.mean() < (0.01 if fmt == "COLOR_BGRA32" else 2.5), error.mean()


def test_kept_stamps_and_looping(pyk4a: ModuleType, tmp_path: Path) -> None:
    from services.detector.cameras.kinect_recording import KinectRecordingSource

    path = write(pyk4a, tmp_path / "rec.mkv")
    kept = KinectRecordingSource(path, rate=0.0, keep_stamps=True)
    assert [f.stamp_ns for f in kept] == [t * 1000 for t in TIMES_USEC[1:]]
    looped = KinectRecordingSource(path, rate=0.0, loop=True)
    stamps, indices = [], []
    for frame in looped:
        stamps.append(frame.stamp_ns)
        indices.append((int(frame.color_bgr[8, 8, 1]) - 60 + 20) // 40)
        if len(stamps) == 7:
            looped.close()
    assert indices == [1, 2, 3, 1, 2, 3, 1]
    assert np.all(np.diff(stamps) > 0)
    assert looped._playback.closed


def test_the_colour_lens_distortion_is_removed_by_default(
        pyk4a: ModuleType, tmp_path: Path) -> None:
    from services.detector.cameras.kinect_recording import KinectRecordingSource

    path = write(pyk4a, tmp_path / "rec.mkv", "COLOR_BGRA32",
                 dist=(0.5, -2.6, 0.0007, -0.0002, 1.5, 0.38, -2.4, 1.4))  # a rational model
    raw = next(iter(KinectRecordingSource(path, rate=0.0, undistort=False)))
    corrected = next(iter(KinectRecordingSource(path, rate=0.0)))
    np.testing.assert_array_equal(raw.depth, depth_mm())
    assert (corrected.depth != raw.depth).any()  # the depth's edge moved with the colour
    assert set(np.unique(corrected.depth)) <= {0, 1000}


def test_recording_errors_name_the_file_and_the_fix(
        pyk4a: ModuleType, tmp_path: Path) -> None:
    from services.detector.cameras.kinect_recording import KinectRecordingSource

    with pytest.raises(SourceUnavailable, match=r"--kinect-recording .*none\.mkv: no such file"):
        KinectRecordingSource(tmp_path / "none.mkv")
    (tmp_path / "junk.mkv").write_bytes(b"\x1a\x45\xdf\xa3 not matroska")
    with pytest.raises(SourceUnavailable, match="not a readable Azure Kinect recording"):
        KinectRecordingSource(tmp_path / "junk.mkv")
    path = write(pyk4a, tmp_path / "ir.mkv", depth_track=False)
    with pytest.raises(SourceUnavailable, match="needs a colour and a depth track"):
        KinectRecordingSource(path)
    with pytest.raises(SourceUnavailable, match=r"^--source .*none\.mkv: no such file"):
        open_source(f"kinect-recording:{tmp_path / 'none.mkv'}")


def test_a_missing_pyk4a_is_one_line_naming_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    from services.detector.cameras.kinect_recording import KinectRecordingSource

    monkeypatch.setitem(sys.modules, "pyk4a", None)  # import fails as if not installed
    with pytest.raises(SourceUnavailable) as info:
        KinectRecordingSource("any.mkv")
    text = str(info.value)
    assert text.startswith("--kinect-recording needs pyk4a: pip install 'handkse[kinect]'")
    assert "libk4a" in text and "\n" not in text


def test_camera_command_publishes_a_recording_over_the_router(
        procs: Processes, router: str, client_bus: Bus, pyk4a: ModuleType, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The real ``handkse camera`` process, with the stand-in as its pyk4a."""
    path = write(pyk4a, tmp_path / "rec.mkv")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(
        p for p in (str(FAKE_SDK), os.environ.get("PYTHONPATH")) if p))
    received: list[RgbdFrame] = []
    client_bus.subscribe(KEYS.camera_rgbd,
                         lambda k, p: received.append(RgbdFrame.from_msgpack(p)))
    camera = procs.start("camera", "--rig", KEYS.rig, *zenoh_args(router),
                         "--kinect-recording", str(path), "--rate", "0", name="camera")
    wait_until(lambda: camera.poll() is not None, 60, what=f"camera end; {output_of(camera)}")
    assert camera.returncode == 0, output_of(camera)
    assert "camera published 3 frames" in output_of(camera)
    wait_until(lambda: bool(received), 10, what="frames on camera/rgbd")
    for message in received:
        assert message.intrinsics.to_dict()["fx"] == 605.0
        frame = decode_frame(message)
        assert frame.depth[360, 640] * message.depth.scale_m == pytest.approx(1.0)


def test_camera_command_without_pyk4a_is_one_line(procs: Processes, tmp_path: Path) -> None:
    result = procs.run("camera", "--kinect-recording", str(tmp_path / "rec.mkv"))
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    assert lines[0].startswith("handkse camera: --kinect-recording")
    assert "pip install 'handkse[kinect]'" in lines[0] or "no such file" in lines[0]
