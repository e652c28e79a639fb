"""A fake of the subset of panda-python's interface that ``PandaPyBackend`` uses.

``FakePanda`` records every call in ``calls`` (name, args) and plays a robot that follows the
impedance target exactly, one control tick later; ``force_fn(target_position)`` scripts the
external force libfranka would estimate (``O_F_ext_hat_K``, reported as the force the robot
exerts, i.e. the negative of the force on the end-effector), plus a constant ``bias``. Poses are
column-major 16-element lists and quaternions ``[x, y, z, w]``, as in libfranka / panda-py.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass
class FakeDuration:
    seconds: float

    def to_sec(self) -> float:
        return self.seconds


@dataclass
class FakeRobotState:
    q: list[float]
    dq: list[float]
    O_T_EE: list[float]
    O_F_ext_hat_K: list[float]
    tau_J_d: list[float]  # noqa: N815 - libfranka's name
    time: FakeDuration


class FakeRobot:
    def __init__(self, calls: list[tuple[str, tuple[Any, ...]]]) -> None:
        self.calls = calls

    def set_collision_behavior(self, *args: Any) -> None:
        self.calls.append(("set_collision_behavior", args))


class CartesianImpedance:
    """Records the gains and the latest target of ``set_control``."""

    instances: ClassVar[list[CartesianImpedance]] = []

    def __init__(self, impedance: Any, damping_ratio: float, nullspace_stiffness: float,
                 filter_coeff: float) -> None:
        self.impedance = np.asarray(impedance, float)
        self.damping_ratio = damping_ratio
        self.nullspace_stiffness = nullspace_stiffness
        self.filter_coeff = filter_coeff
        self.targets: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        CartesianImpedance.instances.append(self)

    def set_control(self, position: Any, orientation: Any, q_nullspace: Any) -> None:
        self.targets.append((np.array(position, float), np.array(orientation, float),
                             np.array(q_nullspace, float)))


class controllers:  # noqa: N801 - stands in for the module panda_py.controllers
    CartesianImpedance = CartesianImpedance


class FakeContext:
    def __init__(self, panda: FakePanda, frequency: float) -> None:
        self.panda = panda
        self.frequency = frequency
        self.entered = False

    def __enter__(self) -> FakeContext:
        self.entered = True
        return self

    def __exit__(self, *exc: object) -> bool:
        return False

    def ok(self) -> bool:
        """One tick: raise the scripted error, else move the robot to the controller target."""
        self.panda.ticks += 1
        if self.panda.error_at_tick is not None and self.panda.ticks >= self.panda.error_at_tick:
            raise RuntimeError("libfranka: Move command aborted: motion aborted by reflex! "
                               "[\"cartesian_reflex\"]")
        self.panda.advance()
        return True


def _default_pose() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", 110, degrees=True).as_matrix()
    T[:3, 3] = (0.55, 0.0, 0.45)
    return T


@dataclass
class FakePanda:
    """``panda_py.Panda`` stand-in with a kinematic "robot" that tracks the target."""

    pose: np.ndarray = field(default_factory=_default_pose)
    q: np.ndarray = field(default_factory=lambda: np.array([0.0, -0.3, 0.0, -2.4, 0.0, 3.3, -2.35]))
    force_fn: Callable[[np.ndarray], np.ndarray] = field(default=lambda _p: np.zeros(6))
    bias: np.ndarray = field(default_factory=lambda: np.zeros(6))
    error_at_tick: int | None = None
    calls: list[tuple[str, tuple[Any, ...]]] = field(default_factory=list)
    ticks: int = 0
    controller: CartesianImpedance | None = None
    t: float = 0.0

    def get_robot(self) -> FakeRobot:
        return FakeRobot(self.calls)

    def get_state(self) -> FakeRobotState:
        f_on_ee = self.force_fn(self.pose[:3, 3].copy()) + self.bias
        return FakeRobotState(q=list(self.q), dq=[0.0] * 7,
                              O_T_EE=list(self.pose.T.reshape(-1)),
                              O_F_ext_hat_K=list(-f_on_ee), tau_J_d=[0.0] * 7,
                              time=FakeDuration(self.t))

    def start_controller(self, ctrl: CartesianImpedance) -> None:
        self.calls.append(("start_controller", (ctrl,)))
        self.controller = ctrl

    def stop_controller(self) -> None:
        self.calls.append(("stop_controller", ()))
        self.controller = None

    def create_context(self, frequency: float, max_runtime: float = 0.0) -> FakeContext:
        self.calls.append(("create_context", (frequency,)))
        return FakeContext(self, frequency)

    def advance(self) -> None:
        self.t += 0.001
        if self.controller is not None and self.controller.targets:
            p, quat, _ = self.controller.targets[-1]
            T = np.eye(4)
            T[:3, :3] = Rotation.from_quat(quat).as_matrix()  # scipy: [x, y, z, w]
            T[:3, 3] = p
            self.pose = T

