"""Robot bridge: articulate an object along its estimated kinematic model with a Franka Panda.

Modules (nothing heavy is imported here; MuJoCo and panda-python load only where used):

- :mod:`~services.robot_bridge.config`: ``RobotBridgeConfig`` (the ``[robot_bridge]`` section);
- :mod:`~services.robot_bridge.controller`: the Jacobian-transpose Cartesian impedance law;
- :mod:`~services.robot_bridge.trajectory`: model -> base frame, minimum-jerk articulation plans;
- :mod:`~services.robot_bridge.safety`: pure clamps and checks with stable refusal reasons;
- :mod:`~services.robot_bridge.backend`: the ``RobotBackend`` protocol and ``BackendState``;
- :mod:`~services.robot_bridge.factory`: ``make_backend`` (panda-python is imported there only);
- :mod:`~services.robot_bridge.mujoco_backend`, :mod:`~services.robot_bridge.panda_scene`:
  the simulated Panda and objects;
- :mod:`~services.robot_bridge.pandapy_backend`: a real Panda through panda-python;
- :mod:`~services.robot_bridge.executor`: ``execute`` (tick loop with aborts) and ``Bridge``;
- :mod:`~services.robot_bridge.service`: ``handkse robot-bridge``;
- :mod:`~services.robot_bridge.client`: ``handkse articulate`` (also what ``handkse demo`` asks
  through);
- :mod:`~services.robot_bridge.simulation`: a synthetic demonstration's (or a calibration file's)
  true object placed and grasped in simulation, for the service and the robot trials
  (``articulate_in_simulation``).

The simulated robot trials (``handkse robot-trials``) are evaluation: :mod:`services.evaluation.robot_trials`.
"""
