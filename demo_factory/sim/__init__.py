"""Simulation: a headless PyBullet world with a Franka Panda, three RGB-D cameras and kinematics.

Owns physics stepping, the arm's controllers and gripper, bodies, camera rendering (RGB, metric depth,
calibration) and inverse kinematics. Reads the Panda model from ``pybullet_data``; writes nothing.
"""

from demo_factory.sim.camera import CAMERA_NAMES, DEFAULT_CAMERAS, CameraSpec, depth_to_points
from demo_factory.sim.kinematics import Kinematics
from demo_factory.sim.world import HOME, TOP_DOWN, World

__all__ = ["CAMERA_NAMES", "DEFAULT_CAMERAS", "HOME", "TOP_DOWN", "CameraSpec", "Kinematics", "World", "depth_to_points"]
