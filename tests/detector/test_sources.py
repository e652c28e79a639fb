"""Frame sources and the RgbdFrame image codec."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

from services.common.protocol import ProtocolError, RgbdFrame
from services.detector.source_factory import open_source
from services.detector.sources import (
    CapturedFrame,
    FolderSource,
    FolderWriter,
    KinectSource,
    SourceUnavailable,
    decode_frame,
    encode_frame,
)
from tests.detector.conftest import CATCHER_CROP, crop, intrinsics_for


def _frame(image: np.ndarray, stamp_ns: int = 1_000_000_000, depth_mm: int = 700
           ) -> CapturedFrame:
    rng = np.random.default_rng(stamp_ns % 1000)
    depth = (depth_mm + rng.integers(-5, 6, image.shape[:2])).astype(np.uint16)
    depth[:10] = 0  # a band without readings
    return CapturedFrame(stamp_ns=stamp_ns, color_bgr=image, depth=depth, depth_scale_m=0.001,
                         intrinsics=intrinsics_for(image))


@pytest.mark.parametrize(("color", "depth"), [("jpeg", "png16"), ("png", "u16"),
                                              ("bgr8", "png16")])
def test_rgbd_frame_round_trip(opencv_images: dict[str, np.ndarray], color: str,
                               depth: str) -> None:
    image = crop(opencv_images["basketball1.png"], CATCHER_CROP)
    frame = _frame(image)
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.2, 0.3]
    frame = dataclasses.replace(frame, T_world_camera=T)
    message = RgbdFrame.from_msgpack(encode_frame(frame, seq=7, color_encoding=color,
                                                  depth_encoding=depth).to_msgpack())
    assert (message.seq, message.stamp_ns) == (7, frame.stamp_ns)
    back = decode_frame(message)
    np.testing.assert_array_equal(back.depth, frame.depth)  # depth is lossless
    if color == "jpeg":
        assert np.abs(back.color_bgr.astype(int) - image).mean() < 3.0
    else:
        np.testing.assert_array_equal(back.color_bgr, image)
    assert back.intrinsics.to_dict() == frame.intrinsics.to_dict() and back.depth_scale_m == 0.001
    np.testing.assert_array_equal(back.T_world_camera, T)


def test_undecodable_images_are_protocol_errors(opencv_images: dict[str, np.ndarray]) -> None:
    image = crop(opencv_images["basketball1.png"], CATCHER_CROP)
    good = encode_frame(_frame(image))
    bad_color = RgbdFrame(stamp_ns=1, color=type(good.color)(encoding="jpeg", width=160,
                                                            height=160, data=b"\xff\xd8junk"),
                          depth=good.depth, intrinsics=good.intrinsics)
    with pytest.raises(ProtocolError) as info:
        decode_frame(bad_color)
    assert info.value.reason == "bad_image"
    wrong_size = RgbdFrame(stamp_ns=1, color=type(good.color)(encoding="jpeg", width=320,
                                                             height=160, data=good.color.data),
                           depth=good.depth, intrinsics=good.intrinsics)
    with pytest.raises(ProtocolError, match="announced 320x160"):
        decode_frame(wrong_size)


def test_folder_round_trip_and_loop(opencv_images: dict[str, np.ndarray], tmp_path: Path) -> None:
    images = [crop(opencv_images[n], CATCHER_CROP) for n in ("basketball1.png", "basketball2.png")]
    stamps = [5_000_000_000, 5_033_000_000]
    first = _frame(images[0], stamps[0])
    with FolderWriter(tmp_path / "rec", first.intrinsics, 0.001) as writer:
        for image, stamp in zip(images, stamps, strict=True):
            writer.write(_frame(image, stamp))
    source = FolderSource(tmp_path / "rec", rate=0.0)
    assert len(source) == 2 and not source.realtime
    frames = list(source)
    assert [f.stamp_ns for f in frames] == stamps
    np.testing.assert_array_equal(frames[1].depth, _frame(images[1], stamps[1]).depth)
    assert np.abs(frames[0].color_bgr.astype(int) - images[0]).mean() < 3.0
    assert frames[0].intrinsics.to_dict() == first.intrinsics.to_dict()
    looped = FolderSource(tmp_path / "rec", rate=0.0, loop=True)
    got = []
    for f in looped:
        got.append(f.stamp_ns)
        if len(got) == 5:
            looped.close()
    assert got == [*stamps, stamps[0] + 66_000_000, stamps[1] + 66_000_000,
                   stamps[0] + 132_000_000]  # stamps keep increasing across loops
    assert isinstance(open_source(f"folder:{tmp_path / 'rec'}"), FolderSource)


def test_folder_errors_name_the_problem(tmp_path: Path) -> None:
    with pytest.raises(SourceUnavailable, match=r"intrinsics\.json"):
        FolderSource(tmp_path)
    (tmp_path / "intrinsics.json").write_text('{"fx": 500}')
    with pytest.raises(SourceUnavailable, match="fx, fy, cx, cy"):
        FolderSource(tmp_path)


def test_kinect_without_pyk4a_names_the_extra_and_libk4a(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "pyk4a", None)  # import fails as if not installed
    with pytest.raises(SourceUnavailable) as info:
        KinectSource()
    text = str(info.value)
    assert "kinect" in text and "pyk4a" in text and "libk4a" in text
    with pytest.raises(SourceUnavailable, match="libk4a"):
        open_source("kinect")


def test_camera_service_reports_an_unusable_source(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    from services.common.entry import standalone_parser
    from services.detector import camera

    parser = standalone_parser("camera", camera.__doc__ or "", camera.add_arguments)
    assert camera.main(parser.parse_args(["--folder", str(tmp_path / "nothing")])) == 2
    assert "intrinsics.json" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "pyk4a", None)
    assert camera.main(parser.parse_args(["--kinect"])) == 2
    assert "libk4a" in capsys.readouterr().err
