"""Accurate inverse kinematics for the Panda grasp frame, in a private kinematics-only client."""

from __future__ import annotations

import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation, Slerp

from demo_factory.sim.world import ARM_JOINTS, FINGER_JOINTS, GRASP_LINK, HOME, JOINT_LOWER, JOINT_UPPER, panda_urdf

POSITION_TOLERANCE = 1e-4  # metres (0.1 mm)
ORIENTATION_TOLERANCE = 1e-3  # radians


def pose_error(a, b) -> tuple[float, float]:
    """Position (m) and orientation (rad) distance between two ``[x,y,z,qx,qy,qz,qw]`` poses."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    dq = abs(float(np.dot(a[3:] / np.linalg.norm(a[3:]), b[3:] / np.linalg.norm(b[3:]))))
    return float(np.linalg.norm(a[:3] - b[:3])), 2.0 * float(np.arccos(min(1.0, dq)))


class Kinematics:
    """Forward and inverse kinematics on a copy of the arm that never touches the physics world.

    IK: a null-space pass (joint limits + rest pose, 100 iterations) then a plain 1000-iteration
    refinement from that result, which reaches ~0.01 mm. The result must lie within the joint
    limits and match the target within 0.1 mm and 1 mrad, else the pose counts as unreachable.
    """

    def __init__(self):
        self.client = p.connect(p.DIRECT)
        self.robot = p.loadURDF(panda_urdf(False), useFixedBase=True, physicsClientId=self.client)

    def close(self) -> None:
        p.disconnect(self.client)

    def _set(self, q) -> None:
        for j, v in zip(ARM_JOINTS, q):
            p.resetJointState(self.robot, j, v, physicsClientId=self.client)
        for j in FINGER_JOINTS:
            p.resetJointState(self.robot, j, 0.02, physicsClientId=self.client)

    def forward(self, q) -> np.ndarray:
        """Grasp-frame pose for arm joints ``q``."""
        self._set(q)
        state = p.getLinkState(self.robot, GRASP_LINK, computeForwardKinematics=True, physicsClientId=self.client)
        return np.array([*state[4], *state[5]])

    def _solve(self, pose, seed) -> np.ndarray:
        pos, orn = list(pose[:3]), list(pose[3:])
        self._set(seed)
        q = p.calculateInverseKinematics(
            self.robot, GRASP_LINK, pos, orn,
            lowerLimits=list(JOINT_LOWER) + [0, 0], upperLimits=list(JOINT_UPPER) + [0.04, 0.04],
            jointRanges=list(JOINT_UPPER - JOINT_LOWER) + [0.04, 0.04], restPoses=list(seed) + [0.02, 0.02],
            maxNumIterations=100, residualThreshold=1e-6, physicsClientId=self.client,
        )
        self._set(q[:7])
        q = p.calculateInverseKinematics(
            self.robot, GRASP_LINK, pos, orn, maxNumIterations=1000, residualThreshold=1e-9, physicsClientId=self.client,
        )
        return np.array(q[:7])

    def inverse(self, pose, seed=HOME) -> np.ndarray | None:
        """Arm joints reaching ``pose`` near ``seed``, or None when the pose is unreachable."""
        seeds = [np.asarray(seed, dtype=float), np.asarray(HOME, dtype=float)]
        # Deterministic extra seeds derived from the target, for poses far from both.
        rng = np.random.default_rng(np.round(np.asarray(pose) * 1e4).astype(np.int64) % (2**31))
        seeds += [rng.uniform(JOINT_LOWER, JOINT_UPPER) for _ in range(4)]
        for start in seeds:
            q = self._solve(pose, start)
            if np.any(q < JOINT_LOWER - 1e-6) or np.any(q > JOINT_UPPER + 1e-6):
                continue
            dp, dr = pose_error(self.forward(q), pose)
            if dp <= POSITION_TOLERANCE and dr <= ORIENTATION_TOLERANCE:
                return np.clip(q, JOINT_LOWER, JOINT_UPPER)
        return None


def slerp_poses(start, goal, n: int) -> list[np.ndarray]:
    """``n`` poses from ``start`` (exclusive) to ``goal`` (inclusive) on a straight line with slerp."""
    start, goal = np.asarray(start, float), np.asarray(goal, float)

    slerp = Slerp([0.0, 1.0], Rotation.from_quat([start[3:], goal[3:]]))
    fractions = np.linspace(0.0, 1.0, n + 1)[1:]
    quats = slerp(fractions).as_quat()
    return [np.concatenate([start[:3] + f * (goal[:3] - start[:3]), qq]) for f, qq in zip(fractions, quats)]
