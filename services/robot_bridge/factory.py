"""``make_backend``: the robot backend named by the configuration; ``configured_backend``: the
one the service runs, with its simulated object placed.

Kept apart from :mod:`services.robot_bridge.backend` (the protocol both implementations import),
so that no import cycle joins the protocol and its implementations. Vendor packages (MuJoCo,
panda-python) are imported inside :func:`make_backend` only, so the package imports without them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from services.robot_bridge.backend import RobotBackend

if TYPE_CHECKING:
    from services.robot_bridge.config import RobotBridgeConfig
    from services.robot_bridge.panda_scene import ObjectSpec


def make_backend(config: RobotBridgeConfig, obj: ObjectSpec | None = None) -> RobotBackend:
    """The backend named by ``config.backend``; vendor packages are imported only here.

    ``obj``: the simulated object (MuJoCo only; default: the configured ``sim_object`` preset at
    the nominal grasp pose).
    """
    if config.backend == "mujoco":
        from services.robot_bridge.mujoco_backend import MujocoBackend, preset_object

        return MujocoBackend(obj or preset_object(config.sim_object), config)
    if config.backend == "panda":
        if not config.robot_host:
            raise ValueError("robot_bridge.robot_host must name the Panda's address for "
                             "backend 'panda'")
        if np.allclose(config.base_T_camera(), np.eye(4)):
            raise ValueError("robot_bridge.T_base_camera is the identity: set the hand-eye "
                             "calibration before driving a real robot")
        try:
            import panda_py
            from panda_py import controllers
        except ImportError as exc:
            raise ValueError("backend 'panda' needs panda-python: pip install 'handkse[panda]'"
                             ) from exc
        from services.robot_bridge.pandapy_backend import PandaPyBackend

        return PandaPyBackend(panda_py.Panda(config.robot_host), controllers, config)
    raise ValueError(f"unknown backend {config.backend!r}")


def configured_backend(config: RobotBridgeConfig
                       ) -> tuple[RobotBridgeConfig, RobotBackend, str]:
    """The service's backend, the config it runs under and a sentence saying what it drives.

    In simulation, a ``synthetic:...`` or file ``sim_object`` is placed through
    ``T_base_camera`` (:func:`services.robot_bridge.simulation.place_configured_object`; an
    identity calibration is replaced by the one that makes the object reachable, and the returned
    config carries it); a preset sits at the nominal grasp pose. Raises ``ValueError`` for an
    object that cannot be read or grasped, and as :func:`make_backend`.
    """
    from services.robot_bridge.config import sim_object_source

    if config.backend == "mujoco" and sim_object_source(config.sim_object).kind != "preset":
        from services.robot_bridge.simulation import place_configured_object

        config, scene, where = place_configured_object(config)
        return config, scene.backend(config), where
    backend = make_backend(config)
    if config.backend == "mujoco":
        return config, backend, f"{config.sim_object} at the nominal grasp pose"
    return config, backend, f"the Panda at {config.robot_host}"
