"""A tiny keyframe dataset in the project's converter format, and helpers to build HiveFormer on it.

The scene is a table plane (z = 0) seen by two shoulder cameras and a wrist camera that follows the
gripper; depth is exact for that plane, so the point cloud the policy rebuilds is consistent with the
calibration. Gripper poses are random, and every action is the next keyframe's pose.
"""

from pathlib import Path

import numpy as np
import pytest
import torch

CAMERAS = ("left_shoulder", "right_shoulder", "wrist")
IMAGE_SIZE = 32
FPS = 10
STATE_NAMES = ["x", "y", "z", "qx", "qy", "qz", "qw", "gripper_open"] + [f"joint_{i}" for i in range(7)]
ACTION_NAMES = ["x", "y", "z", "qx", "qy", "qz", "qw", "open"]
INSTRUCTIONS = ("push the maroon button", "stack 2 navy blocks")
EPISODE_LENGTHS = (4, 5, 4, 6)


def dataset_features(image_size: int = IMAGE_SIZE, cameras=CAMERAS) -> dict:
    """Features exactly as the project's converter writes them."""
    features = {}
    for camera in cameras:
        image = {
            "dtype": "image",
            "shape": (image_size, image_size, 3),
            "names": ["height", "width", "channels"],
        }
        features[f"observation.images.{camera}"] = dict(image)
        features[f"observation.depth.{camera}"] = {
            **image,
            "shape": (image_size, image_size, 1),
            "info": {"is_depth_map": True, "depth_unit": "mm"},
        }
        features[f"observation.calibration.{camera}"] = {"dtype": "float32", "shape": (20,), "names": None}
    features["observation.state"] = {"dtype": "float32", "shape": (15,), "names": STATE_NAMES}
    features["action"] = {"dtype": "float32", "shape": (8,), "names": ACTION_NAMES}
    features["variation_id"] = {"dtype": "int64", "shape": (1,), "names": None}
    features["keyframe_index"] = {"dtype": "int64", "shape": (1,), "names": None}
    return features


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """World-from-camera 4x4 with OpenCV axes (x right, y down, z forward)."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    transform = np.eye(4)
    transform[:3, :3] = np.stack([right, down, forward], axis=1)
    transform[:3, 3] = eye
    return transform


def table_depth_m(intrinsics: np.ndarray, world_from_camera: np.ndarray, size: int) -> np.ndarray:
    """Depth along the optical axis of the plane z = 0; 0 where the ray misses it (or beyond 2 m)."""
    fx, fy, cx, cy = intrinsics
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1) @ world_from_camera[:3, :3].T
    depth = -world_from_camera[2, 3] / rays[..., 2]
    return np.where((depth > 0) & (depth < 2.0), depth, 0.0)


def depth_mm(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) metres -> (H, W, 1) uint16 millimetres, LeRobot's native depth."""
    return np.clip(np.round(depth_m * 1000.0), 0, 65535).astype(np.uint16)[..., None]


def random_pose(rng: np.random.Generator) -> np.ndarray:
    xyz = rng.uniform([-0.15, -0.15, 0.02], [0.15, 0.15, 0.25])
    quaternion = rng.normal(size=4)
    quaternion /= np.linalg.norm(quaternion)
    return np.concatenate([xyz, quaternion * np.sign(quaternion[3])])


def camera_pose(camera: str, gripper_xyz: np.ndarray) -> np.ndarray:
    if camera == "left_shoulder":
        return look_at(np.array([-0.5, -0.6, 0.7]), np.zeros(3))
    if camera == "right_shoulder":
        return look_at(np.array([0.5, -0.6, 0.7]), np.zeros(3))
    return look_at(gripper_xyz + np.array([0.0, -0.05, 0.3]), gripper_xyz * np.array([1.0, 1.0, 0.0]))


def write_tiny_dataset(
    root: Path,
    cameras=CAMERAS,
    image_size: int = IMAGE_SIZE,
    episode_lengths=EPISODE_LENGTHS,
    drop_features: tuple[str, ...] = (),
    seed: int = 0,
):
    """Create and finalise a LeRobot v3.0 keyframe dataset at `root` (which must not exist)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {k: v for k, v in dataset_features(image_size, cameras).items() if k not in drop_features}
    dataset = LeRobotDataset.create(
        repo_id="local/tiny", fps=FPS, features=features, root=root, use_videos=False, image_writer_threads=0
    )
    rng = np.random.default_rng(seed)
    focal = image_size * 1.1
    intrinsics = np.array([focal, focal, (image_size - 1) / 2, (image_size - 1) / 2])
    for episode, length in enumerate(episode_lengths):
        variation = episode % len(INSTRUCTIONS)
        poses = [random_pose(rng) for _ in range(length + 1)]
        opens = [float((step + episode) % 2) for step in range(length + 1)]
        for step in range(length):
            frame = {"task": INSTRUCTIONS[variation]}
            for camera in cameras:
                world_from_camera = camera_pose(camera, poses[step][:3])
                rgb = rng.integers(0, 256, size=(image_size, image_size, 3), dtype=np.uint8)
                frame[f"observation.images.{camera}"] = rgb
                frame[f"observation.depth.{camera}"] = depth_mm(
                    table_depth_m(intrinsics, world_from_camera, image_size)
                )
                frame[f"observation.calibration.{camera}"] = np.concatenate(
                    [intrinsics, world_from_camera.reshape(-1)]
                ).astype(np.float32)
            joints = rng.uniform(-1, 1, size=7)
            frame["observation.state"] = np.concatenate([poses[step], [opens[step]], joints]).astype(
                np.float32
            )
            frame["action"] = np.concatenate([poses[step + 1], [opens[step + 1]]]).astype(np.float32)
            frame["variation_id"] = np.array([variation], dtype=np.int64)
            frame["keyframe_index"] = np.array([step], dtype=np.int64)
            frame = {k: v for k, v in frame.items() if k not in drop_features}
            dataset.add_frame(frame)
        dataset.save_episode()
    dataset.finalize()
    return dataset


@pytest.fixture(scope="session")
def tiny_dataset_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("hiveformer") / "tiny"
    write_tiny_dataset(root)
    return root


def tiny_config(root: Path, **overrides):
    """A small HiveFormer config on the dataset at `root`, with features read from it."""
    from lerobot.configs.types import FeatureType
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.utils.feature_utils import dataset_to_policy_features
    from lerobot_policy_hiveformer import HiveformerConfig

    meta = LeRobotDatasetMetadata("local/tiny", root=root)
    features = dataset_to_policy_features(meta.features)
    settings = {
        "device": "cpu",
        "text_encoder": "clip_tiny_random",
        "n_history": 3,
        "hidden_dim": 32,
        "num_heads": 4,
        "feedforward_dim": 64,
        "dropout": 0.0,
        "input_features": {k: f for k, f in features.items() if f.type is not FeatureType.ACTION},
        "output_features": {k: f for k, f in features.items() if f.type is FeatureType.ACTION},
    }
    settings.update(overrides)
    return HiveformerConfig(**settings), meta


def history_batch(root: Path, config, indices) -> dict:
    """A collated, pre-processed training batch of the dataset frames `indices` with history."""
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot_policy_hiveformer import make_hiveformer_pre_post_processors

    meta_dataset = LeRobotDataset("local/tiny", root=root)
    dataset = LeRobotDataset(
        "local/tiny", root=root, delta_timestamps=resolve_delta_timestamps(config, meta_dataset.meta)
    )
    items = [dataset[i] for i in indices]
    batch = torch.utils.data.default_collate(items)
    preprocessor, _ = make_hiveformer_pre_post_processors(config, dataset.meta.stats)
    return preprocessor(batch)
