"""Headless PyBullet simulation: the world, cameras and kinematics."""

from demo_factory.sim.camera import CAMERA_NAMES, DEFAULT_CAMERAS, CameraSpec, depth_to_points
from demo_factory.sim.kinematics import Kinematics
from demo_factory.sim.world import HOME, TOP_DOWN, World

__all__ = ["CAMERA_NAMES", "DEFAULT_CAMERAS", "HOME", "TOP_DOWN", "CameraSpec", "Kinematics", "World", "depth_to_points"]
