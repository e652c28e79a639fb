"""The bridge's simulated object: where it comes from and where it is placed.

``synthetic:OBJECT[:PARTICIPANT[:SEED]]`` is the demonstration's true object, moved from the
camera frame into the base frame by the bridge's own ``T_base_camera`` (the one it maps models
with), so that a camera-frame model of the truth is the robot's truth; an object calibration
file does the same for an object measured in the camera frame. Robot trials place their objects
with the same code.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")

from services.common.protocol import (
    ArticulateRequest,
    KinematicModel,
    PrismaticParams,
    RevoluteParams,
)
from services.common.se3 import se3_inverse, so3_exp
from services.robot_bridge.config import RobotBridgeConfig, SimObjectSource, sim_object_source
from services.robot_bridge.executor import Bridge
from services.robot_bridge.factory import configured_backend
from services.robot_bridge.mujoco_backend import MujocoBackend, nominal_grasp_pose
from services.robot_bridge.simulation import (
    ObjectInCamera,
    articulate_in_simulation,
    default_hand_eye,
    object_from_file,
    object_from_source,
    object_in_camera,
    place_configured_object,
    true_task,
)
from services.robot_bridge.trajectory import default_duration
from services.synthetic.generator import generate

CONFIG = RobotBridgeConfig(sim_realtime_factor=0.0)


def _truth_model(obj: ObjectInCamera) -> KinematicModel:
    """The true joint as a camera-frame model (P = 1), stamped now."""
    probs = {"rigid": 0.0, "prismatic": 0.0, "revolute": 0.0, "disconnected": 0.0}
    probs[obj.joint_type] = 1.0
    if obj.joint_type == "revolute":
        p = obj.point - (obj.point @ obj.axis) * obj.axis
        return KinematicModel(stamp_ns=time.time_ns(), type="revolute", probabilities=probs,
                              revolute=RevoluteParams(axis=obj.axis, point=p, q=1.0, dq=0.0,
                                                      covariance=np.zeros((7, 7))))
    ref = np.eye(4)
    ref[:3, 3] = obj.grasp
    return KinematicModel(stamp_ns=time.time_ns(), type="prismatic", probabilities=probs,
                          reference_pose=ref,
                          prismatic=PrismaticParams(axis=obj.axis, q=0.05, dq=0.0,
                                                    covariance=np.zeros((4, 4))))


def _write_object(path: Path, obj: ObjectInCamera) -> Path:
    def vec(v: np.ndarray) -> str:
        return "[" + ", ".join(repr(float(x)) for x in v) + "]"

    path.write_text(f'name = "{obj.name}"\ntype = "{obj.joint_type}"\naxis = {vec(obj.axis)}\n'
                    f"point = {vec(obj.point)}\ngrasp = {vec(obj.grasp)}\n"
                    f"normal = {vec(obj.normal)}\ntravel = {obj.demonstrated!r}\n")
    return path


# --- the source ---


def test_sources_parse() -> None:
    assert sim_object_source("bolt") == SimObjectSource("preset", name="bolt")
    assert sim_object_source("synthetic:key") == SimObjectSource("synthetic", name="key",
                                                                 participant=3, seed=0)
    assert sim_object_source("synthetic:slider:6:4") == SimObjectSource(
        "synthetic", name="slider", participant=6, seed=4)
    assert str(sim_object_source("synthetic:slider:6")) == "synthetic:slider:6:0"
    whole = sim_object_source("synthetic:key:3:0:whole")
    assert whole == SimObjectSource("synthetic", name="key", participant=3, seed=0,
                                    variant="whole")
    assert str(whole) == "synthetic:key:3:0:whole"
    assert sim_object_source("lab/key.toml") == SimObjectSource("file", path="lab/key.toml")


@pytest.mark.parametrize(("text", "message"), [
    ("synthetic:kee", "unknown object 'kee'; known: "),
    ("synthetic:key:99", "participant must be 1..7, got 99"),
    ("synthetic:key:3:x", "participant and seed must be whole numbers"),
    ("synthetic:key:3:-1", "seed must be >= 0"),
    ("synthetic:free", "stream has no object"),
    ("synthetic:key:3:0:long", "variant must be one of cut, whole"),
    ("synthetic:key:3:0:whole:x", "must look like synthetic:OBJECT"),
    ("synthetic:", "must look like synthetic:OBJECT"),
    ("door", "sim_object must be a preset (key, window_lock, bolt), synthetic:OBJECT"),
])
def test_a_bad_source_is_refused_with_the_rule(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        RobotBridgeConfig(sim_object=text)


def test_a_synthetic_variant_is_that_variants_object() -> None:
    """``handkse demo`` plays the whole demonstration; its object is placed elsewhere in the
    camera than the cut one's, and the bridge must hold that one."""
    whole = object_from_source(sim_object_source("synthetic:key:3:0:whole"))
    truth = object_in_camera(generate("key", 3, 0, variant="whole"))
    cut = object_from_source(sim_object_source("synthetic:key:3:0"))
    np.testing.assert_array_equal(whole.point, truth.point)
    np.testing.assert_array_equal(whole.axis, truth.axis)
    assert np.linalg.norm(whole.point - cut.point) > 0.01


# --- placement ---


def test_the_synthetic_object_is_the_truth_through_the_calibration() -> None:
    obj = object_in_camera(generate("key", 3, 0))
    config, backend, what = configured_backend(replace(CONFIG, sim_object="synthetic:key"))
    assert isinstance(backend, MujocoBackend) and backend.obj is not None
    # an uncalibrated (identity) T_base_camera becomes the one that makes the key reachable
    T_bc = config.base_T_camera()
    assert np.allclose(T_bc, default_hand_eye(obj))
    assert "synthetic:key:3:0" in what and "nominal grasp pose" in what
    assert np.allclose(backend.obj.axis_base, T_bc[:3, :3] @ obj.axis)
    d = backend.obj.point_base - (T_bc[:3, :3] @ obj.point + T_bc[:3, 3])
    assert np.linalg.norm(d - (d @ backend.obj.axis_base) * backend.obj.axis_base) < 1e-9
    # held at the nominal grasp, the hand turned by pi about the approach when the task's turn
    # needs joint 7's other branch
    T_ee, T_nominal = backend.read().T_base_ee, nominal_grasp_pose()
    assert np.allclose(T_ee[:3, 2:], T_nominal[:3, 2:], atol=1e-6)
    assert np.allclose(np.abs(T_ee[:3, :2]), np.abs(T_nominal[:3, :2]), atol=1e-6)
    # what the camera saw (the true joint in the camera frame) turns the key gently
    amount = true_task(obj)
    result = Bridge(backend, config).articulate(
        ArticulateRequest(amount=amount, duration_s=default_duration(amount, "revolute")),
        _truth_model(obj), now_ns=time.time_ns())
    assert (result.success, result.reason) == (True, "ok"), result.detail
    assert result.articulated == pytest.approx(math.pi, rel=0.03)
    assert result.peak_force_n < 15.0


def test_a_configured_calibration_is_used_as_it_is() -> None:
    """The camera 20 deg about the base z axis from the default: the object moves with it."""
    obj = object_in_camera(generate("window_lock", 3, 2))
    turn = np.eye(4)
    turn[:3, :3] = so3_exp(np.array([0.0, 0.0, math.radians(20.0)]))
    T_bc = turn @ default_hand_eye(obj)
    config = replace(CONFIG, sim_object="synthetic:window_lock:3:2",
                     T_base_camera=tuple(T_bc.ravel()))
    placed, scene, what = place_configured_object(config)
    assert placed.T_base_camera == config.T_base_camera
    assert "configured T_base_camera" in what
    assert np.allclose(scene.obj.axis_base, T_bc[:3, :3] @ obj.axis)
    result = Bridge(scene.backend(placed), placed).articulate(
        ArticulateRequest(amount=math.pi, duration_s=6.0), _truth_model(obj),
        now_ns=time.time_ns())
    assert result.success, result.detail
    far = np.eye(4)
    far[:3, 3] = (2.0, 0.0, 0.0)  # 2 m away: nothing to grasp
    with pytest.raises(ValueError, match="cannot grasp synthetic:window_lock:3:2"):
        place_configured_object(replace(config, T_base_camera=tuple((far @ T_bc).ravel())))


@pytest.mark.parametrize("name", ["key", "slider"])
def test_robot_trials_place_the_object_the_same_way(name: str) -> None:
    obj = object_in_camera(generate(name, 3, 0))
    _, scene, _ = place_configured_object(replace(CONFIG, sim_object=f"synthetic:{name}"))
    model = _truth_model(obj)
    trial = articulate_in_simulation(model, obj, config=CONFIG)
    assert trial.object_base is not None
    assert np.allclose(trial.T_base_camera, scene.T_base_camera)
    assert np.allclose(trial.object_base.T_base_handle, scene.obj.T_base_handle)
    assert np.allclose(trial.object_base.axis_base, scene.obj.axis_base)
    assert trial.object_base.range == scene.obj.range


def test_an_object_calibration_file_places_like_the_truth(tmp_path: Path) -> None:
    obj = object_in_camera(generate("slider", 3, 0))
    path = _write_object(tmp_path / "slider.toml", obj)
    read = object_from_file(path)
    assert read.joint_type == "prismatic" and read.demonstrated == obj.demonstrated
    assert np.allclose(read.axis, obj.axis) and np.allclose(read.normal, obj.normal)
    _, from_file, what = place_configured_object(replace(CONFIG, sim_object=str(path)))
    _, synthetic, _ = place_configured_object(replace(CONFIG, sim_object="synthetic:slider"))
    assert str(path) in what
    assert np.allclose(from_file.obj.T_base_handle, synthetic.obj.T_base_handle)
    assert from_file.obj.range == synthetic.obj.range


def test_the_documented_object_file_is_the_synthetic_key(tmp_path: Path) -> None:
    page = (Path(__file__).resolve().parents[2] / "docs" / "robot_bridge.md").read_text()
    block = page.split("## Simulated object", 1)[1].split("```toml\n", 1)[1].split("```", 1)[0]
    path = tmp_path / "key.toml"
    path.write_text(block)
    _, documented, _ = place_configured_object(replace(CONFIG, sim_object=str(path)))
    _, synthetic, _ = place_configured_object(replace(CONFIG, sim_object="synthetic:key"))
    assert np.allclose(documented.obj.axis_base, synthetic.obj.axis_base, atol=2e-3)
    assert np.allclose(documented.obj.T_base_handle[:3, 3], synthetic.obj.T_base_handle[:3, 3],
                       atol=2e-3)


def test_an_object_calibration_file_names_what_is_wrong(tmp_path: Path) -> None:
    obj = object_in_camera(generate("key", 3, 0))
    good = _write_object(tmp_path / "key.toml", obj).read_text()
    cases = {
        "missing.toml": (None, "does not exist"),
        "typo.toml": (good + "axes = [0, 0, 1]\n", "unknown key\\(s\\) axes"),
        "type.toml": (good.replace('"revolute"', '"screw"'), "type must be"),
        "short.toml": (good.replace("travel", "#"), None),  # travel is optional
        "vector.toml": ("\n".join(line for line in good.splitlines()
                                  if not line.startswith("normal")), "normal is missing"),
        "zero.toml": (good.replace("axis = [", "axis = [0, 0, 0] #["), "axis must not be zero"),
        "bad.toml": ("type = ", "cannot be read"),
    }
    for name, (text, message) in cases.items():
        path = tmp_path / name
        if text is not None:
            path.write_text(text)
        if message is None:
            assert object_from_file(path).demonstrated == pytest.approx(math.pi)
            continue
        with pytest.raises(ValueError, match=f"object calibration file {path}.*{message}"):
            object_from_file(path)


def test_a_preset_stays_at_the_nominal_grasp() -> None:
    config, backend, what = configured_backend(replace(CONFIG, sim_object="bolt"))
    assert config == replace(CONFIG, sim_object="bolt")
    assert isinstance(backend, MujocoBackend) and backend.obj is not None
    assert backend.obj.name == "bolt" and "nominal grasp pose" in what
    assert np.allclose(backend.obj.T_base_handle, nominal_grasp_pose())
    assert np.allclose(se3_inverse(backend.obj.T_base_handle) @ nominal_grasp_pose(), np.eye(4))
