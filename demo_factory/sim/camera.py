"""Pinhole RGB-D cameras: rendering, intrinsics/extrinsics, and depth → world point clouds."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

@dataclass
class CameraObservation:
    """One camera's images at one frame."""

    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 metres (millimetre precision after recording)
    segmentation: np.ndarray  # (H, W) int32 body ids, -1 background
    intrinsics: np.ndarray  # (4,) float64: fx, fy, cx, cy
    extrinsics: np.ndarray  # (4, 4) float64 world-from-camera, OpenCV axes


# OpenGL camera axes (x right, y up, looking down -z) → OpenCV axes (x right, y down, z forward).
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class CameraSpec:
    """A camera fixed in the world (``eye``/``target`` in world coordinates) or on the hand.

    For a wrist camera (``on_hand``) ``eye``, ``target`` and ``up`` are in the hand link's frame.
    """

    name: str
    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    fov_deg: float = 55.0  # vertical field of view
    near: float = 0.01
    far: float = 3.0
    on_hand: bool = False


DEFAULT_CAMERAS: tuple[CameraSpec, ...] = (
    CameraSpec("left_shoulder", eye=(0.15, 0.45, 0.55), target=(0.5, 0.0, 0.0), fov_deg=50.0),
    CameraSpec("right_shoulder", eye=(0.15, -0.45, 0.55), target=(0.5, 0.0, 0.0), fov_deg=50.0),
    # Behind the fingers on the hand, looking along the fingers (hand z) past the fingertips.
    CameraSpec("wrist", eye=(0.06, 0.0, 0.02), target=(0.0, 0.0, 0.3), up=(1.0, 0.0, 0.0), fov_deg=70.0, on_hand=True),
)
CAMERA_NAMES = tuple(c.name for c in DEFAULT_CAMERAS)


def intrinsics(spec: CameraSpec, size: tuple[int, int]) -> np.ndarray:
    """``(fx, fy, cx, cy)`` for a square-pixel pinhole with the spec's vertical field of view.

    The principal point is ``(w/2 - 1, h/2 - 1)``, not the textbook ``((w-1)/2, (h-1)/2)``: PyBullet's
    tiny renderer samples pixel (u, v) half a pixel off the centre convention; with this value the
    rebuilt table plane is flat to the micrometre (tests/test_sim.py checks it).
    """
    height, width = size
    fy = height / (2.0 * np.tan(np.radians(spec.fov_deg) / 2.0))
    return np.array([fy, fy, width / 2.0 - 1.0, height / 2.0 - 1.0])


def _world_eye_target_up(spec: CameraSpec, hand_pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    eye, target, up = (np.array(v, dtype=float) for v in (spec.eye, spec.target, spec.up))
    if spec.on_hand:
        position, orientation = hand_pose
        rotation = Rotation.from_quat(orientation).as_matrix()
        eye, target, up = rotation @ eye + position, rotation @ target + position, rotation @ up
    return eye, target, up


# The tiny renderer's own light when none is given (these reproduce its images exactly). Its light settings
# persist from one getCameraImage call to the next in a process, so every render states all of them.
DEFAULT_LIGHT = {"lightDirection": [-50.0, 30.0, 100.0], "lightColor": [1.0, 1.0, 1.0], "lightDistance": 2.0,
                 "lightAmbientCoeff": 0.6, "lightDiffuseCoeff": 0.35, "lightSpecularCoeff": 0.05}


def render(client: int, spec: CameraSpec, size: tuple[int, int], hand_pose,
           light: dict | None = None) -> CameraObservation:
    """Render RGB, metric depth and segmentation, with the camera's calibration; ``light``: changes to the light
    (``DEFAULT_LIGHT``'s keys, those of PyBullet's ``getCameraImage``)."""
    height, width = size
    eye, target, up = _world_eye_target_up(spec, hand_pose)
    view = p.computeViewMatrix(eye.tolist(), target.tolist(), up.tolist(), physicsClientId=client)
    projection = p.computeProjectionMatrixFOV(spec.fov_deg, width / height, spec.near, spec.far, physicsClientId=client)
    _, _, rgba, depth_buffer, seg = p.getCameraImage(
        width, height, view, projection, renderer=p.ER_TINY_RENDERER, shadow=0, physicsClientId=client,
        **(DEFAULT_LIGHT | (light or {})),
    )
    rgb = np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[:, :, :3]
    depth_buffer = np.asarray(depth_buffer, dtype=np.float64).reshape(height, width)
    depth = spec.far * spec.near / (spec.far - (spec.far - spec.near) * depth_buffer)
    depth[depth_buffer >= 1.0] = 0.0  # nothing hit
    seg = np.asarray(seg, dtype=np.int64).reshape(height, width)
    seg = np.where(seg < 0, -1, seg & 0xFFFFFF).astype(np.int32)
    world_from_gl = np.linalg.inv(np.asarray(view, dtype=np.float64).reshape(4, 4, order="F"))
    return CameraObservation(
        rgb=np.ascontiguousarray(rgb),
        depth=depth.astype(np.float32),
        segmentation=seg,
        intrinsics=intrinsics(spec, size),
        extrinsics=world_from_gl @ GL_TO_CV,
    )


def depth_to_points(depth: np.ndarray, intrinsics_: np.ndarray, extrinsics: np.ndarray) -> np.ndarray:
    """World-frame point per pixel, ``(H, W, 3)``; pixels with depth 0 (no hit) give NaN."""
    height, width = depth.shape
    fx, fy, cx, cy = intrinsics_
    v, u = np.mgrid[0:height, 0:width]
    z = depth.astype(np.float64)
    camera_points = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], axis=-1)
    world = camera_points @ extrinsics[:3, :3].T + extrinsics[:3, 3]
    world[z <= 0] = np.nan
    return world
