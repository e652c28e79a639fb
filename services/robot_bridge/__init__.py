"""Robot bridge: articulate an object along its estimated kinematic model with a Franka Panda.

Modules (nothing heavy is imported here; MuJoCo and panda-python load only where used):

- :mod:`~services.robot_bridge.config`: ``RobotBridgeConfig`` (the ``[robot_bridge]`` section);
- :mod:`~services.robot_bridge.controller`: the Jacobian-transpose Cartesian impedance law;
- :mod:`~services.robot_bridge.trajectory`: model -> base frame, minimum-jerk articulation plans;
- :mod:`~services.robot_bridge.safety`: pure clamps and checks with stable refusal reasons;
- :mod:`~services.robot_bridge.backend`: the ``RobotBackend`` protocol and ``make_backend``;
- :mod:`~services.robot_bridge.mujoco_backend`, :mod:`~services.robot_bridge.panda_scene`:
  the simulated Panda and objects;
- :mod:`~services.robot_bridge.pandapy_backend`: a real Panda through panda-python;
- :mod:`~services.robot_bridge.executor`: ``execute`` (tick loop with aborts) and ``Bridge``;
- :mod:`~services.robot_bridge.service`: ``handkse robot-bridge``;
- :mod:`~services.robot_bridge.simulation`: ``articulate_in_simulation`` (used by the demo);
- :mod:`~services.robot_bridge.trials`: ``handkse robot-trials`` (Table III in simulation).
"""
