"""The narrow robot interface the bridge drives: the ``RobotBackend`` protocol and its state.

A backend runs a Cartesian impedance controller on the arm (the law of
:mod:`services.robot_bridge.controller`) whose target the bridge moves every control tick:
``command(target, twist)`` then ``step()``, reading ``read()`` in between. Two
implementations: :class:`~services.robot_bridge.mujoco_backend.MujocoBackend` (simulated Panda
and object; the test double) and :class:`~services.robot_bridge.pandapy_backend.PandaPyBackend`
(a real Panda through panda-python); :func:`services.robot_bridge.factory.make_backend` picks one.
This module imports neither, so both can import it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from services.robot_bridge.controller import ImpedanceGains

Array = NDArray[np.float64]


class BackendError(RuntimeError):
    """The robot (or simulation) reported an error; the message says what happened."""


@dataclass(frozen=True)
class BackendState:
    """One reading of the arm, base frame.

    ``t_s`` backend time (s); ``q``/``dq`` (7,) rad, rad/s; ``T_base_ee`` 4x4 TCP pose;
    ``wrench`` (6,) external force (N) then torque (N m, about the TCP) acting on the end-effector,
    with the offset captured by ``zero_wrench()`` removed; ``tau`` (7,) joint torque last sent
    (N m, including gravity in simulation); ``saturated`` whether that command was clamped at a
    torque limit; ``object_joint`` the articulated object's joint value (rad or m) and
    ``object_pose`` the 4x4 pose ``T_base_part`` of its grasped part, where the backend can
    measure them (simulation), else None.
    """

    t_s: float
    q: Array
    dq: Array
    T_base_ee: Array
    wrench: Array
    tau: Array
    saturated: bool
    object_joint: float | None = None
    object_pose: Array | None = None


class RobotBackend(Protocol):
    """What the bridge needs from an arm: read, command an impedance target, step, stop."""

    name: str
    control_period_s: float
    object_axis_base: Array | None  # simulated object's true axis (None on a real robot)

    def read(self) -> BackendState:
        """The latest state (no waiting)."""
        ...

    def start(self, gains: ImpedanceGains) -> None:
        """Start the impedance controller holding the current pose with ``gains``."""
        ...

    def command(self, T_base_target: Array, twist_target: Array | None = None) -> Array:
        """Set the impedance target (4x4) and feed-forward twist (6,); returns the twist sent."""
        ...

    def step(self) -> None:
        """Advance one control period (simulate it, or wait for the robot's next tick).

        Raises :class:`BackendError` when the robot stops on an error (reflex, communication).
        """
        ...

    def zero_wrench(self) -> None:
        """Take the current wrench reading as zero (call right after grasping)."""
        ...

    def hold(self) -> None:
        """Stop moving: make the current measured pose the target, with zero twist."""
        ...

    def stop(self) -> None:
        """Hold, then end the controller (real robot: hand back to the robot's own hold)."""
        ...

    def close(self) -> None:
        """Release the robot or simulation."""
        ...
