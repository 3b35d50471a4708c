"""The LeRobot feature layout of a converted dataset, and recording frame → dataset frame.

Per camera ``<cam>`` (the recording's cameras, e.g. left_shoulder / right_shoulder / wrist):
- ``observation.images.<cam>``       image (H, W, 3) uint8 RGB, stored as lossless PNG.
- ``observation.depth.<cam>``        LeRobot's native depth image (H, W, 1): z-depth in whole
  millimetres as a 16-bit PNG (lossless; 0 = no hit), flagged ``info: {is_depth_map: true,
  depth_unit: mm}`` so LeRobot reads it back as (1, H, W) float32 millimetres, keeps image transforms
  and ImageNet statistics off it, and its tools show it as depth.
- ``observation.calibration.<cam>``  float32 (20,): fx, fy, cx, cy, then the 4×4 world-from-camera
  transform (OpenCV axes) row-major. Per frame because the wrist camera moves. Its feature's ``info``
  says how to rebuild the point cloud (``CALIBRATION_LAYOUT``).
Robot and labels:
- ``observation.state``  float32 (15,): gripper x, y, z, qx, qy, qz, qw, gripper_open, joint_0..joint_6.
- ``action``             float32 (8,), by granularity and action space:
  keyframe:       the next keyframe's target x, y, z, qx, qy, qz, qw and open command (the last
                  keyframe repeats its own target);
  dense, joints:  the 7 arm joint positions and the gripper command at the next control tick;
  dense, ee:      the grasp-frame pose x, y, z, qx, qy, qz, qw (quaternion sign: qx >= 0, the
                  hemisphere of the top-down grasp) and the gripper command at the next control tick.
  The last frame of a dense episode repeats its own state (hold still).
- ``variation_id``, ``keyframe_index``  int64 (1,): for breaking results down.
- the instruction is the frame's ``task`` string.
"""

from __future__ import annotations

import numpy as np
from lerobot_policy_hiveformer.dataset_format import CALIBRATION_DIM

from demo_factory.record.episode import CameraObservation, Episode, Frame, RobotState

KEYFRAME_FPS = 10  # nominal rate of keyframe datasets: LeRobot needs one; keyframes are not evenly timed
POSE_NAMES = ["x", "y", "z", "qx", "qy", "qz", "qw"]
STATE_NAMES = [*POSE_NAMES, "gripper_open", *(f"joint_{i}" for i in range(7))]
ACTION_NAMES = [*POSE_NAMES, "open"]
CALIBRATION_NAMES = ["fx", "fy", "cx", "cy", *(f"T_world_cam_{r}{c}" for r in range(4) for c in range(4))]
STATE_SIZE = len(STATE_NAMES)  # 15: gripper pose, open, 7 joints
ACTION_SIZE = len(ACTION_NAMES)  # 8: the next keyframe's pose and open (a dense joints action has 8 too)
CALIBRATION_SIZE = CALIBRATION_DIM  # 20 per camera: intrinsics, then the 4x4 camera-to-world matrix (the policy's)
assert len(CALIBRATION_NAMES) == CALIBRATION_SIZE
DEPTH_INFO = {"is_depth_map": True, "depth_unit": "mm"}  # LeRobot 0.6's native depth flag and unit
CALIBRATION_LAYOUT = {
    "intrinsics": "fx, fy, cx, cy in pixels (pixel centres at integer coordinates)",
    "extrinsics": "4x4 world-from-camera, OpenCV axes (x right, y down, z forward), row-major",
    "unproject": "p_world = T @ [(u - cx) * z / fx, (v - cy) * z / fy, z, 1] for pixel (u=column, v=row)",
}
GRANULARITIES = ("keyframe", "dense")
ACTION_SPACES = ("joints", "ee")  # of dense exports; a keyframe export's action is always the next keyframe
DEFAULT_ACTION_SPACE = "joints"
# The control rate recommended for the tasks (generate --dense-fps 20): presses and grasps are brief
# straight moves, and at 10 fps the ticks often miss their deepest point: replaying the expert's own
# 10 fps actions closed loop solves 1 of 6 push_buttons test episodes, its 20 fps actions 6 of 6 (and
# 3 of 3 tower episodes; measured with the dense environment and the expert reference).
DEFAULT_CONTROL_FPS = 20
JOINT_ACTION_NAMES = [*(f"joint_{i}" for i in range(7)), "open"]


def image_key(camera: str) -> str:
    return f"observation.images.{camera}"


def depth_key(camera: str) -> str:
    return f"observation.depth.{camera}"


def calibration_key(camera: str) -> str:
    return f"observation.calibration.{camera}"


def action_names(action_space: str | None = None) -> list[str]:
    """The ``action`` feature's names: keyframe (``None``), ``joints`` or ``ee``."""
    if action_space is None or action_space == "ee":
        return ACTION_NAMES
    if action_space == "joints":
        return JOINT_ACTION_NAMES
    raise ValueError(f"unknown action space {action_space!r}; accepted: {', '.join(ACTION_SPACES)}")


def dataset_features(cameras: list[str], image_size: tuple[int, int], action_space: str | None = None) -> dict[str, dict]:
    """The ``features`` argument of ``LeRobotDataset.create`` for these cameras and (H, W); the action is
    the next keyframe (``action_space=None``) or a dense action space (``joints`` / ``ee``)."""
    height, width = image_size
    names = ["height", "width", "channels"]
    features: dict[str, dict] = {}
    for camera in cameras:
        features[image_key(camera)] = {"dtype": "image", "shape": (height, width, 3), "names": names}
        features[depth_key(camera)] = {"dtype": "image", "shape": (height, width, 1), "names": names,
                                       "info": dict(DEPTH_INFO)}
        features[calibration_key(camera)] = {"dtype": "float32", "shape": (CALIBRATION_SIZE,), "names": CALIBRATION_NAMES,
                                             "info": dict(CALIBRATION_LAYOUT)}
    features["observation.state"] = {"dtype": "float32", "shape": (STATE_SIZE,), "names": STATE_NAMES}
    features["action"] = {"dtype": "float32", "shape": (ACTION_SIZE,), "names": action_names(action_space)}
    features["variation_id"] = {"dtype": "int64", "shape": (1,), "names": None}
    features["keyframe_index"] = {"dtype": "int64", "shape": (1,), "names": None}
    return features


def depth_mm(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) metres → (H, W, 1) uint16 whole millimetres (0 = no hit), as a dataset stores depth."""
    return np.clip(np.rint(depth_m * 1000.0), 0, 65535).astype(np.uint16)[..., None]


def pack_depth(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) metres → (H, W, 3) uint8 millimetres, R = mm // 256, G = mm % 256, B = 0: how a gym
    environment, whose images must be uint8, hands depth to ``lerobot-eval`` (its processor step unpacks it:
    ``evaluate.gym_layout``)."""
    mm = depth_mm(depth_m)[..., 0]
    packed = np.zeros((*mm.shape, 3), np.uint8)
    packed[..., 0] = mm >> 8
    packed[..., 1] = mm & 0xFF
    return packed


def calibration_vector(camera: CameraObservation) -> np.ndarray:
    """(20,) float32: fx, fy, cx, cy, world-from-camera 4×4 row-major."""
    return np.concatenate([np.asarray(camera.intrinsics, np.float64), np.asarray(camera.extrinsics).ravel()]).astype(np.float32)


def world_points(depth_m: np.ndarray, calibration: np.ndarray) -> np.ndarray:
    """(H, W) metric depth + (20,) calibration → (H, W, 3) world points (NaN where depth is 0)."""
    calibration = np.asarray(calibration, np.float64)
    fx, fy, cx, cy = calibration[:4]
    transform = calibration[4:].reshape(4, 4)
    height, width = depth_m.shape
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    z = np.where(depth_m > 0, depth_m, np.nan).astype(np.float64)
    camera_points = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], axis=-1)
    return camera_points @ transform[:3, :3].T + transform[:3, 3]


def episode_frames(episode: Episode, granularity: str, stride: int = 1) -> list[Frame]:
    """The recording frames that become dataset frames: keyframe observations, or every ``stride``-th
    dense frame (the recorded dense rate divided by ``stride`` is the dataset's control rate)."""
    if granularity == "keyframe":
        return episode.keyframe_frames()
    if granularity == "dense":
        return episode.dense_frames()[::stride]
    raise ValueError(f"unknown granularity {granularity!r}; accepted: {', '.join(GRANULARITIES)}")


def canonical_quaternion(quaternion) -> np.ndarray:
    """``q`` or ``-q`` (the same rotation), whichever has ``qx >= 0``: the hemisphere around the top-down
    grasp (1, 0, 0, 0), so that a regressed ee action does not jump between the two signs."""
    quaternion = np.asarray(quaternion, np.float64)
    return -quaternion if quaternion[0] < 0 else quaternion


def robot_action(robot: RobotState, action_space: str) -> np.ndarray:
    """(8,) float32: a robot state as a dense action, ``joints`` = 7 joint positions + gripper command,
    ``ee`` = grasp-frame pose (canonical quaternion sign) + gripper command."""
    if action_space == "joints":
        values = [*robot.joint_positions, robot.gripper_open]
    elif action_space == "ee":
        pose = np.asarray(robot.gripper_pose, np.float64)
        values = [*pose[:3], *canonical_quaternion(pose[3:]), robot.gripper_open]
    else:
        raise ValueError(f"unknown action space {action_space!r}; accepted: {', '.join(ACTION_SPACES)}")
    return np.asarray(values, np.float64).astype(np.float32)


def dense_actions(frames: list[Frame], action_space: str) -> list[np.ndarray]:
    """The action of each dense frame: the robot's state at the next control tick (the last frame
    repeats its own, i.e. holds still)."""
    return [robot_action(frames[min(i + 1, len(frames) - 1)].robot, action_space) for i in range(len(frames))]


def episode_items(episode: Episode, granularity: str, action_space: str | None = None,
                  stride: int = 1) -> list[tuple[Frame, np.ndarray]]:
    """(frame, action) pairs of one episode: what a dataset stores, frame by frame."""
    frames = episode_frames(episode, granularity, stride)
    if granularity == "keyframe":
        return [(f, action_for(episode, f.keyframe_index)) for f in frames]
    return list(zip(frames, dense_actions(frames, action_space or DEFAULT_ACTION_SPACE)))


def action_for(episode: Episode, keyframe_index: int) -> np.ndarray:
    """(8,) float32 action of an observation taken at or after keyframe ``keyframe_index``:
    keyframe k+1's target pose and gripper command (the last keyframe repeats its own)."""
    target = episode.keyframes[min(keyframe_index + 1, len(episode.keyframes) - 1)]
    return np.append(np.asarray(target.target_pose, np.float64), target.gripper_open).astype(np.float32)


def observation_item(frame: Frame, cameras: list[str]) -> dict[str, np.ndarray]:
    """The ``observation.*`` features of one frame (images (H, W, 3) uint8, depth (H, W, 1) uint16
    millimetres): what a dataset stores and what a policy is shown during evaluation."""
    robot = frame.robot
    item: dict[str, np.ndarray] = {}
    for camera in cameras:
        observation = frame.cameras[camera]
        item[image_key(camera)] = observation.rgb
        item[depth_key(camera)] = depth_mm(observation.depth)
        item[calibration_key(camera)] = calibration_vector(observation)
    item["observation.state"] = np.concatenate(
        [robot.gripper_pose, [robot.gripper_open], robot.joint_positions]
    ).astype(np.float32)
    return item


def dataset_frame(episode: Episode, frame: Frame, instruction: str, action: np.ndarray | None = None) -> dict:
    """One ``add_frame`` dict for LeRobot from a recording frame (default action: the next keyframe)."""
    item: dict = observation_item(frame, episode.info.cameras)
    item["action"] = action_for(episode, frame.keyframe_index) if action is None else action
    item["variation_id"] = np.array([episode.info.variation_id], np.int64)
    item["keyframe_index"] = np.array([frame.keyframe_index], np.int64)
    item["task"] = instruction
    return item
