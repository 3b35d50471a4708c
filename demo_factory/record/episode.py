"""Typed episodes: what the recorder writes and the reader yields (the converter's input).

Conventions (the data contract shared by recorder, reader, converter and policy):
- Poses are ``[x, y, z, qx, qy, qz, qw]`` in the world frame (= robot base frame, metres).
- ``gripper_open`` is 1.0 for an open gripper and 0.0 for a closed one.
- Camera intrinsics are ``(fx, fy, cx, cy)`` in pixels with pixel centres at integer coordinates;
  extrinsics are the 4x4 world-from-camera transform in OpenCV axes (x right, y down, z forward).
  A pixel (u = column, v = row) with metric depth z lies at
  ``T_world_cam @ [(u - cx) * z / fx, (v - cy) * z / fy, z, 1]``.
- Depth is metric z-depth in metres; 0 where nothing was hit (background beyond the far plane).
- Segmentation holds PyBullet body ids, -1 for background.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from demo_factory.planning.planner import PlannerAttempt  # recorded with each episode
from demo_factory.sim.camera import CameraObservation  # recorded in each frame

__all__ = ["FORMAT_VERSION", "OLDEST_READABLE_FORMAT", "CameraObservation", "Episode", "EpisodeInfo", "Frame",
           "Keyframe", "PlannerAttempt", "RobotState"]

# 2: push_buttons and tower variation ids are the HiveFormer paper's (train 0-99, test 100-199);
# version 1 recordings numbered them differently and are refused by the reader.
# 3: the planner takes the straight joint-space line where it is free, so a transition's path (and the
# frames after it) can differ from a version 2 recording of the same seed; the contents are the same,
# and version 2 recordings are still read.
# 4: that straight line is checked in the simulation process between PyBullet's saveState and
# restoreState instead of in a forked child (~4x faster planning). restoreState gives back every
# position, velocity and contact point, but not the collision pairs' internal caches, so in some
# scenes (e.g. take_money_out_safe) the physics after it differs at the 1e-7 level: the paths are
# those of version 3, a file of the same seed can differ in its last digits. Inverse kinematics also
# stops at a 0.1 um residual instead of always iterating 1000 times: joint targets move by < 1e-4 rad.
# 5: push_buttons' expert presses as deep as it says (9 mm of cap travel; it was 5.9 mm): the fingertips'
# height is measured on their collision geometry instead of their AABB, which is padded by 3 mm. Its
# press and approach keyframes lie 3 mm lower. Every task's straight-line moves run at 0.2 m/s (was
# 0.12) with IK waypoints 1 cm apart (was 5 mm): the same keyframes, reached in fewer physics steps, so
# keyframe times, the frames between keyframes (dense) and the last digits of poses differ.
# 6: the info carries the perturbations applied to the scene (`rollout.perturbations`), {} for none.
FORMAT_VERSION = 6
OLDEST_READABLE_FORMAT = 2


@dataclass
class RobotState:
    """Proprioception at one frame."""

    joint_positions: np.ndarray  # (7,) radians
    gripper_pose: np.ndarray  # (7,) x, y, z, qx, qy, qz, qw of the grasp frame
    gripper_open: float  # 1.0 open, 0.0 closed (the last command)
    finger_width: float  # metres between the fingers


@dataclass
class Frame:
    """Everything observed at one instant of simulated time."""

    time_ns: int  # simulation time since the episode start
    is_keyframe: bool  # observation taken when keyframe ``keyframe_index`` was reached
    is_dense: bool  # observation on the fixed-rate dense clock
    keyframe_index: int  # keyframe reached at or before this frame
    robot: RobotState
    cameras: dict[str, CameraObservation]


@dataclass
class Keyframe:
    """A macro-step of the expert: the pose it targets and the gripper command.

    Keyframe 0 is the initial state (target = start pose); keyframe k > 0 is the expert's k-th
    target. The observation recorded when keyframe k is reached is the frame with
    ``is_keyframe and keyframe_index == k``; its action is keyframe k+1 (the last repeats itself).
    """

    index: int
    time_ns: int  # when it was reached
    target_pose: np.ndarray  # (7,)
    gripper_open: float  # command: 1.0 open, 0.0 closed
    reached_pose: np.ndarray  # (7,) the grasp-frame pose actually reached
    motion: str  # "start", "planned", "cartesian" or "gripper"


@dataclass
class EpisodeInfo:
    """Metadata written at the start and completed at the end of the recording."""

    format_version: int
    task: str
    split: str
    variation_id: int
    variation: list[str]  # e.g. the colour sequence
    episode_seed: int
    instruction: str
    cameras: list[str]
    image_size: tuple[int, int]  # (height, width)
    dense_fps: float  # 0 when no dense frames were recorded
    success: bool = False
    planner_attempts: list[PlannerAttempt] = field(default_factory=list)
    versions: dict[str, str] = field(default_factory=dict)
    extra: dict = field(default_factory=dict)  # task-specific scene facts (object colours, ...)
    perturbations: dict = field(default_factory=dict)  # {name: the parameters drawn} (rollout.perturbations)


@dataclass
class Episode:
    """A whole recorded episode."""

    info: EpisodeInfo
    keyframes: list[Keyframe]
    frames: list[Frame]

    def keyframe_frames(self) -> list[Frame]:
        """The observation frames at keyframes, in keyframe order."""
        return [f for f in self.frames if f.is_keyframe]

    def dense_frames(self) -> list[Frame]:
        """The fixed-rate dense frames, in time order (empty if none were recorded)."""
        return [f for f in self.frames if f.is_dense]
