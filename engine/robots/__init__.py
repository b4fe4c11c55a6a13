"""Robots: the motion model ``f`` (eq. 5), controllers, sensors ``g`` (eq. 6), agents.

Per twin step (paper, Algorithm 1)::

    state = robot.step(u, dt)          # kinematics.DiffDriveRobot: 1. s_t = f(s_{t-1}, u)
    msg = sensor.poll(t, state)        # sensors.*: 4. observations (None if not due)
    u = controller(state)              # control.PurePursuit / GoalReacher: 6. next u

or all of it on the bus with :class:`~engine.robots.agent.RobotAgent`.
"""

from engine.robots.agent import (OpenCRStep, RobotAgent, SensorOptions, build_robots,
                                 cast_scans)
from engine.robots.control import (CirclePath, FigureEightPath, GoalReacher, PathError,
                                   PlanarPath, PolylinePath, PurePursuit,
                                   controller_from_spec)
from engine.robots.kinematics import (ROBOT_SPECS, DiffDriveRobot, ProcessNoise, RobotSpec,
                                      KinematicState, SpeedLimitError, robot_spec)
from engine.robots.sensors import (DepthCamera, ImuNoise, ImuSensor, Lidar2D, WheelEncoders,
                                   WheelOdometry)

__all__ = ["OpenCRStep", "RobotAgent", "SensorOptions", "build_robots", "cast_scans",
           "CirclePath",
           "FigureEightPath",
           "GoalReacher", "controller_from_spec", "PlanarPath", "PathError", "PolylinePath",
           "PurePursuit", "ROBOT_SPECS",
           "DiffDriveRobot", "ProcessNoise", "RobotSpec", "KinematicState", "SpeedLimitError",
           "robot_spec", "DepthCamera", "ImuNoise", "ImuSensor", "Lidar2D", "WheelEncoders",
           "WheelOdometry"]
