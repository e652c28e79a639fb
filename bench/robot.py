"""Robot bridge benchmark: simulation speed and controller step time.

- Simulation speed: full simulated trials (the key and the window lock turned 180 deg in 6 s plus
  a 0.5 s hold, the 1 kHz Python loop with the Jacobian-transpose controller, grasp spring, safety
  checks and trace recording), simulated seconds per wall second on this machine, one process.
- Controller step: the per-tick work the bridge does on the real robot's state, timed over the
  states of a simulated trial: the numpy Jacobian-transpose law (``impedance_torque``, with the
  null-space projector) plus the torque clamp (``clamp_torque``). Goal p99 < 0.5 ms so a 1 kHz
  loop keeps headroom. The whole simulated tick (physics + controller + grasp) is timed too.
"""

from __future__ import annotations

import math
import time

import mujoco
import numpy as np

from bench.common import percentiles_ms, write_result
from services.robot_bridge.config import RobotBridgeConfig
from services.robot_bridge.controller import impedance_torque
from services.robot_bridge.executor import execute
from services.robot_bridge.mujoco_backend import MujocoBackend, preset_object
from services.robot_bridge.panda_scene import TAU_MAX_NM, TAU_RATE_MAX_NM_PER_S
from services.robot_bridge.safety import clamp_torque
from services.robot_bridge.trajectory import ArticulationPlan, JointInBase


def _plan(backend: MujocoBackend, duration_s: float = 6.0) -> ArticulationPlan:
    obj = backend.obj
    assert obj is not None
    joint = JointInBase(obj.joint_type, obj.axis_base, obj.point_base)
    return ArticulationPlan(joint, backend.read().T_base_ee.copy(), math.pi, duration_s, 0.5)


def sim_speed(config: RobotBridgeConfig, repeats: int = 3) -> dict[str, float]:
    """Simulated seconds per wall second of full trials (best and median of ``repeats``)."""
    speeds = []
    for i in range(repeats):
        be = MujocoBackend(preset_object("key" if i % 2 == 0 else "window_lock"), config)
        plan = _plan(be)
        t0 = time.perf_counter()
        ex = execute(be, plan, config)
        wall = time.perf_counter() - t0
        assert ex.success, ex.reason
        speeds.append(ex.duration_s / wall)
    return {"median_x_real_time": float(np.median(speeds)), "best_x_real_time": max(speeds),
            "per_tick_us_median": 1e3 / float(np.median(speeds)), "trials": repeats}


def controller_step(config: RobotBridgeConfig, ticks: int = 6500) -> tuple[list[float],
                                                                          list[float]]:
    """Per-tick seconds of (controller + clamp) and of the whole simulated tick."""
    be = MujocoBackend(preset_object("key"), config)
    plan = _plan(be)
    gains = config.gains()
    be.start(gains)
    m, d = be.model, be.data
    jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    site = m.site("tcp").id
    q_null = be.read().q.copy()
    tau_prev = be.read().tau
    ctrl_s: list[float] = []
    tick_s: list[float] = []
    for i in range(ticks):
        T_d, twist_d, _ = plan.sample(i * be.control_period_s)
        be.command(T_d, twist_d)
        # the controller on the latest state (what the real robot would compute each tick)
        mujoco.mj_jacSite(m, d, jacp, jacr, site)
        J = np.vstack([jacp[:, :7], jacr[:, :7]])
        s = be.read()
        t0 = time.perf_counter()
        tau, _ = impedance_torque(J, s.q, s.dq, s.T_base_ee, T_d, twist_d, q_null, gains)
        cmd = clamp_torque(tau, tau_prev, be.control_period_s, TAU_MAX_NM, TAU_RATE_MAX_NM_PER_S)
        ctrl_s.append(time.perf_counter() - t0)
        tau_prev = cmd.tau
        t0 = time.perf_counter()
        be.step()
        tick_s.append(time.perf_counter() - t0)
    return ctrl_s, tick_s


def main() -> None:
    config = RobotBridgeConfig()
    speed = sim_speed(config)
    ctrl_s, tick_s = controller_step(config)
    ctrl = percentiles_ms(ctrl_s)
    write_result("robot", {
        "sim_speed": speed,
        "controller_step_ms": ctrl,
        "sim_tick_ms": percentiles_ms(tick_s),
        "controller": "Jacobian-transpose Cartesian impedance (numpy) + null space + torque clamp",
        "goal": ">= 3x real time on 2 cores; controller step p99 < 0.5 ms",
        "goal_met": bool(speed["median_x_real_time"] >= 3.0 and ctrl["p99"] < 0.5),
    })


if __name__ == "__main__":
    main()
