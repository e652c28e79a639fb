"""RealSense: recordings played through the real SDK, its errors, and the camera command.

The recordings are written in the test with the SDK's software device and recorder (no camera
needed). pyrealsense2 2.59 and later only write rosbag2 ``.db3``, so playback of the legacy
ROS 1 ``.bag`` format (same ``--bag`` option, same SDK call) is not exercised here. A live camera
cannot be tested without one; its path shares the frame conversion tested here and in
test_convert.py.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from services.common.bus import Bus
from services.common.keys import Keys
from services.common.protocol import RgbdFrame
from services.detector.cameras.realsense_recording import FramePairer, RealSenseRecording
from services.detector.source_factory import open_source
from services.detector.sources import SourceUnavailable, decode_frame
from tests.conftest import Processes, output_of, wait_until, zenoh_args
from tests.detector.cameras.software_recording import StreamSetup, write_recording


def _sdk() -> object | None:
    try:
        import pyrealsense2
    except (ImportError, OSError):
        return None
    return pyrealsense2


rs = _sdk()
needs_sdk = pytest.mark.skipif(rs is None, reason="pyrealsense2 is not installed or does not "
                                                  "load (pip install 'handkse[realsense]')")
KEYS = Keys("rs")

# colour 80x60 (f = 60 px) and a depth camera with a narrower view (64x48, f = 80 px) at the
# same pose: aligned to colour, depth covers colour columns 16..63 and rows 12..47 only
COLOR, DEPTH = StreamSetup(80, 60, 60.0), StreamSetup(64, 48, 80.0)
N = 12
TIMES_MS = [1000.0 + i * 33.3 for i in range(N)]


def rgb_frame(i: int) -> np.ndarray:
    """R 200, G 100 + i, B 10: the frame's index is in its green channel."""
    rgb = np.empty((COLOR.height, COLOR.width, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200, 100 + i, 10
    return rgb


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    path = tmp_path / "hand.db3"
    write_recording(path, [rgb_frame(i) for i in range(N)],
                    [np.full((DEPTH.height, DEPTH.width), 1000, np.uint16)] * N, TIMES_MS,
                    color=COLOR, depth=DEPTH)
    return path


@needs_sdk
def test_a_recording_plays_every_frame_aligned_to_colour(recording: Path) -> None:
    before = time.time_ns()
    with RealSenseRecording(recording, rate=0.0) as source:
        assert not source.realtime
        assert source.intrinsics.to_dict() == {"fx": 60.0, "fy": 60.0, "cx": 40.0, "cy": 30.0,
                                               "width": 80, "height": 60}
        assert source.depth_scale_m == 0.001
        frames = list(source)
    after = time.time_ns()
    assert len(frames) == N
    # rgb8 as recorded -> BGR, in recorded order
    assert [f.color_bgr[30, 40].tolist() for f in frames] == [[10, 100 + i, 200]
                                                             for i in range(N)]
    depth = frames[0].depth
    assert depth.shape == (60, 80)  # aligned: the colour image's size
    covered = np.zeros_like(depth, bool)
    covered[12:48, 16:64] = True
    assert (depth[covered] == 1000).mean() > 0.95 and not depth[~covered].any()
    assert np.allclose(depth[covered].astype(float) * frames[0].depth_scale_m, 1.0, atol=1e-9)
    # re-stamped onto the host clock at the first frame, recorded spacing kept
    stamps = [f.stamp_ns for f in frames]
    assert before <= stamps[0] <= after
    assert np.diff(stamps).tolist() == [33_300_000] * (N - 1)


@needs_sdk
def test_kept_stamps_and_a_looped_recording(recording: Path) -> None:
    with RealSenseRecording(recording, rate=0.0, keep_stamps=True) as source:
        assert [f.stamp_ns for f in source] == [round(t * 1e6) for t in TIMES_MS]
    looped = RealSenseRecording(recording, rate=0.0, loop=True)
    stamps, indices = [], []
    for frame in looped:
        stamps.append(frame.stamp_ns)
        indices.append(int(frame.color_bgr[0, 0, 1]) - 100)
        if len(stamps) == 2 * N + 5:
            looped.close()
    assert indices == [*range(N), *range(N), *range(5)]  # started again twice, none lost
    assert np.all(np.diff(stamps) == 33_300_000)  # and stamps kept increasing evenly


@needs_sdk
def test_recording_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(SourceUnavailable, match=r"--bag .*missing\.bag: no such file"):
        RealSenseRecording(tmp_path / "missing.bag")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(SourceUnavailable, match=r"expected a RealSense recording \(\.bag or"):
        RealSenseRecording(tmp_path / "notes.txt")
    (tmp_path / "garbage.bag").write_bytes(b"#ROSBAG V2.0\n" + bytes(200))
    with pytest.raises(SourceUnavailable, match=r"garbage\.bag: not a readable RealSense "
                                                r"recording"):
        RealSenseRecording(tmp_path / "garbage.bag")
    with pytest.raises(SourceUnavailable, match=r"^--source .*missing\.db3: no such file"):
        open_source(f"bag:{tmp_path / 'missing.db3'}")


@needs_sdk
def test_without_a_camera_the_error_says_what_to_check() -> None:
    from services.detector.cameras.realsense import RealSenseSource

    connected = rs.context().query_devices()  # type: ignore[attr-defined]
    if len(connected):
        pytest.skip("a RealSense camera is connected to this machine")
    with pytest.raises(SourceUnavailable, match="no RealSense camera found"):
        RealSenseSource()
    with pytest.raises(SourceUnavailable, match=r"--source realsense:123: no RealSense"):
        open_source("realsense:123")


def test_sdk_intrinsics_and_clock_domains_translate() -> None:
    from services.detector.cameras.realsense import clock_domain, intrinsics_from_realsense

    d455_colour = SimpleNamespace(  # the fields of an rs.intrinsics, as a D455 reports them
        width=1280, height=720, fx=643.2, fy=642.4, ppx=651.9, ppy=361.6,
        model=SimpleNamespace(name="brown_conrady"),
        coeffs=[-0.0553, 0.0652, -0.0006, 0.0008, -0.0210])
    intrinsics, lens = intrinsics_from_realsense(d455_colour)
    assert intrinsics.to_dict() == {"fx": 643.2, "fy": 642.4, "cx": 651.9, "cy": 361.6,
                                    "width": 1280, "height": 720}
    assert lens.model == "opencv" and lens.coeffs == (-0.0553, 0.0652, -0.0006, 0.0008, -0.0210)
    d435_colour = SimpleNamespace(width=640, height=480, fx=615.0, fy=615.0, ppx=320.0,
                                  ppy=240.0, model=SimpleNamespace(name="inverse_brown_conrady"),
                                  coeffs=[0.0] * 5)
    assert intrinsics_from_realsense(d435_colour)[1].is_identity
    assert [clock_domain(d) for d in ("global_time", "system_time", "hardware_clock")] == [
        "host", "host", "device"]


def test_colour_and_depth_pair_by_time_and_strays_are_dropped() -> None:
    pairer: FramePairer[str] = FramePairer(tolerance_ms=16.7)
    for is_color, t, name in [(False, 0.0, "d0"), (False, 33.3, "d1"), (True, 1.0, "c0"),
                              (True, 34.0, "c1"), (True, 66.6, "c2"), (False, 120.0, "d3")]:
        pairer.add(is_color, t, name)
    assert pairer.take() == [("c0", "d0"), ("c1", "d1")]  # either stream may run ahead
    assert pairer.unpaired == 1  # c2: its depth frame never came
    pairer.add(True, 121.0, "c3")
    assert pairer.take() == [("c3", "d3")] and pairer.take() == []


def test_a_missing_sdk_is_one_line_naming_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    from services.detector.cameras.realsense import RealSenseSource

    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import fails as if not installed
    with pytest.raises(SourceUnavailable) as info:
        RealSenseSource()
    assert str(info.value) == ("--realsense needs pyrealsense2: "
                               "pip install 'handkse[realsense]'")
    with pytest.raises(SourceUnavailable, match=r"^--bag needs pyrealsense2: pip install"):
        RealSenseRecording("any.bag")


def _camera_args(*argv: str) -> argparse.Namespace:
    from services.common.entry import standalone_parser
    from services.detector import camera

    return standalone_parser("camera", camera.__doc__ or "", camera.add_arguments).parse_args(
        list(argv))


def test_camera_command_refusals_are_one_line_exit_2(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    from services.detector import camera

    monkeypatch.setitem(sys.modules, "pyrealsense2", None)
    assert camera.main(_camera_args("--realsense", "--serial", "0123")) == 2
    assert capsys.readouterr().err == ("handkse camera: --realsense needs pyrealsense2: "
                                       "pip install 'handkse[realsense]'\n")
    assert camera.main(_camera_args("--folder", "x", "--serial", "0123")) == 2
    assert capsys.readouterr().err == ("handkse camera: --serial selects a RealSense camera: "
                                       "use it with --realsense\n")
    for bad, message in ((["--realsense", "--color-size", "1280"], "expected WIDTHxHEIGHT"),
                         (["--realsense", "--depth-size", "0x480"], "must be positive"),
                         (["--bag", "f.bag", "--rate", "-1"], "must be >= 0")):
        with pytest.raises(SystemExit) as exited:
            _camera_args(*bad)
        assert exited.value.code == 2
        assert message in capsys.readouterr().err


@needs_sdk
def test_camera_command_publishes_a_bag_over_the_router(
        procs: Processes, router: str, client_bus: Bus, recording: Path) -> None:
    received: list[RgbdFrame] = []
    client_bus.subscribe(KEYS.camera_rgbd,
                         lambda k, p: received.append(RgbdFrame.from_msgpack(p)))
    camera = procs.start("camera", "--rig", KEYS.rig, *zenoh_args(router), "--bag",
                         str(recording), "--rate", "0", name="camera")
    wait_until(lambda: camera.poll() is not None, 60, what=f"camera end; {output_of(camera)}")
    assert camera.returncode == 0, output_of(camera)
    assert f"camera published {N} frames" in output_of(camera)
    wait_until(lambda: bool(received), 10, what="frames on camera/rgbd")
    stamps = [m.stamp_ns for m in received]
    assert stamps == sorted(set(stamps))
    for message in received:
        frame = decode_frame(message)
        assert message.intrinsics.to_dict()["fx"] == 60.0 and frame.depth.shape == (60, 80)
        assert frame.depth[30, 40] * message.depth.scale_m == pytest.approx(1.0)
        assert np.abs(frame.color_bgr[30, 40].astype(int) - [10, 100, 200]).max() <= 2 + N


def test_camera_command_without_a_camera_is_one_line(procs: Processes) -> None:
    """A real ``handkse camera --realsense`` on a machine without one (or without the SDK)."""
    if rs is not None and len(rs.context().query_devices()):  # type: ignore[attr-defined]
        pytest.skip("a RealSense camera is connected to this machine")
    result = procs.run("camera", "--realsense")
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    assert lines[0].startswith("handkse camera: --realsense")
    assert ("no RealSense camera found" in lines[0] or "pip install" in lines[0]), lines[0]
