"""Robots: the motion model ``f`` (eq. 5), controllers, sensors ``g`` (eq. 6), agents.

Per twin step (paper, Algorithm 1)::

    state = robot.step(u, dt)          # kinematics.DiffDriveRobot: 1. s_t = f(s_{t-1}, u)
    msg = sensor.poll(t, state)        # sensors.*: 4. observations (None if not due)
    u = controller(state)              # control.PurePursuit / GoalReacher: 6. next u

or all of it on the bus with :class:`~isac_twin.robots.agent.RobotAgent`.
"""

from ..errors import PathError, SpeedLimitError
from .agent import OpenCRStep, RobotAgent, SensorOptions, build_robots, cast_scans
from .control import (
           CirclePath,
           FigureEightPath,
           GoalReacher,
           PlanarPath,
           PolylinePath,
           PurePursuit,
           controller_from_spec,
)
from .kinematics import (
           ROBOT_SPECS,
           DiffDriveRobot,
           KinematicState,
           ProcessNoise,
           RobotSpec,
           robot_spec,
)
from .sensors import DepthCamera, ImuNoise, ImuSensor, Lidar2D, WheelEncoders, WheelOdometry

__all__ = ["OpenCRStep", "RobotAgent", "SensorOptions", "build_robots", "cast_scans",
           "CirclePath",
           "FigureEightPath",
           "GoalReacher", "controller_from_spec", "PlanarPath", "PathError", "PolylinePath",
           "PurePursuit", "ROBOT_SPECS",
           "DiffDriveRobot", "ProcessNoise", "RobotSpec", "KinematicState", "SpeedLimitError",
           "robot_spec", "DepthCamera", "ImuNoise", "ImuSensor", "Lidar2D", "WheelEncoders",
           "WheelOdometry"]
