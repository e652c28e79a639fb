"""``handkse view --save``: a synthetic demonstration through router, tracker and kinematics as
real processes, the view as one more client, and the ``.rrd`` read back with Rerun's reader."""

from __future__ import annotations

import re
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from services.common.keys import Keys
from services.common.protocol import HandBody, HandLandmarks, KinematicModel
from services.common.recording import read_recording
from tests.conftest import Processes, output_of, wait_until, zenoh_args

pytest.importorskip("rerun", reason="handkse view needs the 'view' extra (rerun-sdk)")

from services.view import rerun_scene as scene
from tests.view.chromium import Chromium, available
from tests.view.ports import free_ports
from tests.view.rrd import at, read_entities

RIG = "view"
KEYS = Keys(RIG)


class Published:
    """What the pipeline published, as a subscriber beside the view saw it."""

    def __init__(self) -> None:
        self.landmarks: list[HandLandmarks] = []
        self.bodies: list[HandBody] = []
        self.models: list[KinematicModel] = []
        self.last_arrival = time.monotonic()
        self._lock = threading.Lock()

    def subscribe(self, bus: object) -> None:
        for key, cls, store in ((KEYS.hand_landmarks, HandLandmarks, self.landmarks),
                                (KEYS.hand_body, HandBody, self.bodies),
                                (KEYS.kinematics_model, KinematicModel, self.models)):
            bus.subscribe(key, self._keeper(cls, store))  # type: ignore[attr-defined]

    def _keeper(self, cls: type, store: list[object]):  # type: ignore[no-untyped-def]
        def keep(_key: str, payload: bytes) -> None:
            with self._lock:
                store.append(cls.from_msgpack(payload))
                self.last_arrival = time.monotonic()
        return keep

    @property
    def total(self) -> int:
        return len(self.landmarks) + len(self.bodies) + len(self.models)


def _logged(view_output: str) -> int:
    counts = [int(n) for n in re.findall(r"view: logged (\d+) messages", view_output)]
    return counts[-1] if counts else 0


def _run_pipeline_into_view(procs: Processes, router: str, tmp_path: Path, client_bus: object,
                            *view_args: str) -> tuple[Published, object]:
    z = [*zenoh_args(router), "--rig", RIG]
    for service in ("tracker", "kinematics"):
        procs.start(service, *z, "--state-file", str(tmp_path / f"{service}.state"), name=service)
    published = Published()
    published.subscribe(client_bus)
    view = procs.start("view", *z, *view_args, name="view")
    wait_until(lambda: "view: subscribed" in output_of(view) or view.poll() is not None, 60,
               what="view subscribed")
    assert view.poll() is None, output_of(view)
    play = procs.run("replay", "--synthetic", "slider", "--rate", "0", *z, "--wait-for", "tracker",
                     "--wait-for", "kinematics", "--wait-for", "view", "--wait-timeout", "60",
                     timeout=180)
    assert play.returncode == 0, play.stdout + play.stderr
    n = int(re.search(r"replayed (\d+) messages", play.stdout).group(1))  # type: ignore[union-attr]
    wait_until(lambda: len(published.landmarks) == n and len(published.bodies) == n
               and time.monotonic() - published.last_arrival > 2.0, 120,
               what="the pipeline to drain")
    wait_until(lambda: _logged(output_of(view)) >= published.total, 60,
               what=f"the view to log all {published.total} messages")
    return published, view


def test_view_saves_landmarks_body_and_model_as_published(procs: Processes, router: str,
                                                          client_bus: object,
                                                          tmp_path: Path) -> None:
    rrd = tmp_path / "view.rrd"
    published, view = _run_pipeline_into_view(procs, router, tmp_path, client_bus,
                                               "--save", str(rrd))
    view.terminate()  # type: ignore[attr-defined]
    assert view.wait(60) == 0, output_of(view)  # type: ignore[attr-defined]
    assert "rejected {}" in output_of(view)
    entities = read_entities(rrd)

    final = max(published.models, key=lambda m: m.stamp_ns)
    assert final.type in ("prismatic", "revolute"), final.type
    axis_entity = scene.ARROW if final.type == "prismatic" else scene.AXIS
    for path in (scene.DETECTED, scene.TRACKED, scene.BODY, scene.BODY_COVARIANCE, scene.TRAIL,
                 axis_entity, scene.CONE, scene.SWEEP, *(f"{scene.PROBABILITY}/{t}" for t in
                                                       final.probabilities)):
        assert f"/{path}" in entities, (path, sorted(entities))
    assert f"/{scene.ERROR_LOG}" not in entities

    # every landmark message: as many 3-D points as it had landmarks with depth
    detected = entities[f"/{scene.DETECTED}"]
    assert len([r for r in detected if r["stamp_ns"] is not None]) == len(published.landmarks)
    for msg in published.landmarks:
        finite = int(np.isfinite(msg.hands[0].points).all(axis=1).sum())
        assert len(at(detected, msg.stamp_ns, "Points3D:positions")) == finite, msg.stamp_ns

    # the body pose at a given stamp is the published HandBody's
    bodies = [b for b in published.bodies if b.initialized]
    body = bodies[len(bodies) // 2]
    rows = entities[f"/{scene.BODY}"]
    translation = np.array(at(rows, body.stamp_ns, "Transform3D:translation")[0])
    np.testing.assert_allclose(translation, body.pose[:3, 3], atol=1e-6)
    x, y, z, w = at(rows, body.stamp_ns, "Transform3D:quaternion")[0]
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    np.testing.assert_allclose(R, body.pose[:3, :3], atol=2e-6)
    centre = at(entities[f"/{scene.BODY_COVARIANCE}"], body.stamp_ns, "Ellipsoids3D:centers")[0]
    np.testing.assert_allclose(centre, body.pose[:3, 3], atol=1e-6)

    # the axis drawn last is the final model's axis
    if final.type == "prismatic":
        assert final.prismatic is not None
        rows = entities[f"/{scene.ARROW}"]
        vector = np.array(at(rows, final.stamp_ns, "Arrows3D:vectors")[0])
        origin = np.array(at(rows, final.stamp_ns, "Arrows3D:origins")[0])
        np.testing.assert_allclose(vector / np.linalg.norm(vector), final.prismatic.axis, atol=1e-6)
        np.testing.assert_allclose(origin, final.reference_pose[:3, 3], atol=1e-6)
    else:
        assert final.revolute is not None
        strip = np.array(at(entities[f"/{scene.AXIS}"], final.stamp_ns, "LineStrips3D:strips")[0])
        direction = strip[1] - strip[0]
        np.testing.assert_allclose(direction / np.linalg.norm(direction), final.revolute.axis,
                                   atol=1e-6)
        offset = strip[0] - final.revolute.point
        np.testing.assert_allclose(np.cross(offset, final.revolute.axis), 0.0, atol=1e-6)
    for joint_type, probability in final.probabilities.items():
        logged = at(entities[f"/{scene.PROBABILITY}/{joint_type}"], final.stamp_ns,
                    "Scalars:scalars")
        assert logged == [pytest.approx(probability, abs=1e-12)]


def _yellow_pixels(png: Path) -> tuple[int, float]:
    """Landmark-coloured (yellow) pixels in the 3-D scene's part of the screenshot, and the
    standard deviation of the whole screenshot's grey levels (the loading page is one colour;
    the 3-D scene alone may be a smooth gradient of a few grey levels, so it cannot tell)."""
    from PIL import Image

    image = np.asarray(Image.open(png).convert("RGB")).astype(int)
    h, w, _ = image.shape
    region = image[int(0.08 * h):int(0.6 * h), : int(0.55 * w)]
    r, g, b = region[..., 0], region[..., 1], region[..., 2]
    yellow = (r > 150) & (g > 120) & (b < 110) & (r - b > 90)
    return int(yellow.sum()), float(image.mean(axis=2).std())


@pytest.mark.skipif(not available(), reason="headless Chromium not installed (/usr/bin/chromium, "
                                            "Debian package chromium; make test installs it as root)")
def test_web_viewer_shows_the_landmarks(procs: Processes, router: str, tmp_path: Path) -> None:
    """The default view: Rerun's web viewer on loopback, opened in headless Chromium (WebGL on
    the SwiftShader software rasterizer). The 3-D view is empty before data and shows the
    landmarks after; the screenshot is kept in the test's directory."""
    web_port, grpc_port = free_ports(2)
    z = [*zenoh_args(router), "--rig", RIG]
    view = procs.start("view", *z, "--web-port", str(web_port), "--grpc-port", str(grpc_port),
                       name="view")
    wait_until(lambda: "view: subscribed" in output_of(view) or view.poll() is not None, 60,
               what="view subscribed")
    assert view.poll() is None, output_of(view)
    url = re.search(r"web viewer at (\S+)", output_of(view)).group(1)  # type: ignore[union-attr]
    assert url.startswith(f"http://127.0.0.1:{web_port}/")

    browser = Chromium(tmp_path / "chromium-profile", tmp_path / "chromium.log")
    try:
        browser.open(url)
        before = tmp_path / "view-before-data.png"
        # Loading and compiling the viewer on the software rasterizer takes 10-30 s on a 2-core
        # machine. (Its two failures came from judging "drawn" by the 3-D scene alone, a
        # gradient when the view's layout arrived before the first screenshot.)
        deadline = time.monotonic() + 180
        while True:  # until the viewer's interface is drawn (the loading page is uniform)
            time.sleep(3)
            yellow_before, spread = _yellow_pixels(browser.screenshot(before))
            if spread > 8.0:
                break
            assert time.monotonic() < deadline, f"the viewer never drew; see {before}"
        play = procs.run("replay", "--synthetic", "slider", "--rate", "0", *z, "--wait-for",
                         "view", timeout=120)
        assert play.returncode == 0, play.stdout + play.stderr
        after = tmp_path / "view.png"
        deadline = time.monotonic() + 180
        while True:
            time.sleep(3)
            yellow, spread = _yellow_pixels(browser.screenshot(after))
            if yellow > 300 or time.monotonic() > deadline:
                break
    finally:
        browser.close()
    print(f"web viewer screenshot: {after} (before the data: {before})")
    assert yellow_before < 50, f"landmark colours before any data? see {before}"
    assert yellow > 300, f"no landmarks drawn ({yellow} yellow pixels); see {after}"
    assert spread > 8.0, f"the viewer looks blank; see {after}"


def test_view_of_a_recording_logs_every_message_at_its_stamp(procs: Processes,
                                                            tmp_path: Path) -> None:
    recording, rrd = tmp_path / "demo.mcap", tmp_path / "demo.rrd"
    saved = procs.run("replay", "--synthetic", "bolt", "--save", str(recording))
    assert saved.returncode == 0, saved.stdout + saved.stderr
    shown = procs.run("view", str(recording), "--save", str(rrd), timeout=120)
    assert shown.returncode == 0, shown.stdout + shown.stderr
    stamps = [m.publish_time_ns for m in read_recording(recording)]
    assert f"view: logged {len(stamps)} messages from {recording}" in shown.stdout
    rows = read_entities(rrd)[f"/{scene.DETECTED}"]
    assert sorted(r["stamp_ns"] for r in rows if r["stamp_ns"] is not None) == sorted(stamps)


def test_a_taken_port_is_refused_with_the_option_to_change(procs: Processes) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = procs.run("view", "--web-port", str(port), timeout=60)
    assert result.returncode != 0
    assert f"port {port} on 127.0.0.1 is taken" in result.stderr and "--web-port" in result.stderr
