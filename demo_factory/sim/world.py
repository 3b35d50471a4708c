"""The PyBullet world: a Franka Panda on a table, task objects, cameras, fixed-step physics."""

from __future__ import annotations

import os
import re
import tempfile
from functools import cache
from pathlib import Path

import numpy as np
import pybullet as p
import pybullet_data

from demo_factory.sim.camera import DEFAULT_CAMERAS, CameraSpec, render

TIME_STEP = 1.0 / 240.0
ARM_JOINTS = tuple(range(7))
FINGER_JOINTS = (9, 10)
HAND_LINK = 8
GRASP_LINK = 11
FINGER_OPEN = 0.04  # metres per finger
# The "ready" configuration: grasp frame 0.3 m in front of the base, 0.49 m up, pointing down.
HOME = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)
TOP_DOWN = (1.0, 0.0, 0.0, 0.0)  # grasp frame z pointing down, fingers along world y
TABLE_HALF_EXTENTS = (0.55, 0.7, 0.02)
TABLE_CENTRE = (0.35, 0.0, -0.02)  # the table top is the plane z = 0
# Arm joint limits, slightly inside the URDF's hard limits (the planner and IK keep to these).
JOINT_LOWER = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
JOINT_UPPER = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
ARM_FORCES = (87.0,) * 4 + (12.0,) * 3
GRIPPER_FORCE = 40.0


@cache
def panda_urdf(low_poly: bool = True) -> str:
    """The Panda URDF from pybullet_data; with ``low_poly`` a copy whose visuals are its collision meshes.

    The stock visual meshes make the tiny renderer ~3x slower; the copy renders the same shapes
    with far fewer triangles (and keeps the stock colours).
    """
    source = Path(pybullet_data.getDataPath()) / "franka_panda" / "panda.urdf"
    if not low_poly:
        return str(source)
    meshes = source.parent / "meshes"
    text = source.read_text()
    text = re.sub(r"package://meshes/(?:visual|collision)/(\w+)\.obj", lambda m: str(meshes / "collision" / f"{m.group(1)}.obj"), text)
    folder = Path(tempfile.gettempdir()) / f"demo_factory_assets_{os.getuid()}"
    folder.mkdir(exist_ok=True)
    target = folder / "panda_low_poly.urdf"
    if not target.exists() or target.read_text() != text:
        partial = folder / f".panda_low_poly.{os.getpid()}.urdf"
        partial.write_text(text)
        os.replace(partial, target)
    return str(target)


_ZEROS, _POSITION_GAINS, _VELOCITY_GAINS = (0.0,) * 7, (0.3,) * 7, (1.0,) * 7


def _floats(values) -> list[float]:
    """Plain floats for PyBullet (the same doubles, converted faster than numpy scalars)."""
    return values.tolist() if isinstance(values, np.ndarray) else list(values)


# Physics clients of closed worlds, emptied by `p.resetSimulation`, for the next world to reuse: connecting
# and disconnecting a client costs ~30 ms, a reset a few ms, and a reset client simulates exactly as a new
# one (the recordings are byte-identical). A forked child makes its own.
_spare_clients: list[int] = []
os.register_at_fork(after_in_child=_spare_clients.clear)


class World:
    """One headless PyBullet simulation: robot, table, task objects and cameras.

    The physics runs at a fixed 240 Hz; ``step_count`` is the simulation clock used for every
    timestamp, so a given episode always produces the same times.
    """

    def __init__(self, cameras: tuple[CameraSpec, ...] = DEFAULT_CAMERAS, image_size: tuple[int, int] = (128, 128)):
        self.client = _spare_clients.pop() if _spare_clients else p.connect(p.DIRECT)
        self.cameras = cameras
        self.image_size = image_size
        self.step_count = 0
        self.grasped: int | None = None  # body held between the fingers
        self.gripper_command = 1.0
        self.step_callbacks = []
        self.light: dict = {}  # the renderer's light settings (PyBullet's getCameraImage keywords); {}: its default
        self.perturbations: dict = {}  # what `rollout.perturbations` changed: {name: the parameters drawn}
        self.scene_changes = 0  # task objects moved mid-episode by a perturbation: the expert looks again
        self.pending_events: list = []  # a perturbation's mid-episode changes, each callable once (to preview it)
        p.setGravity(0, 0, -9.81, physicsClientId=self.client)
        p.setTimeStep(TIME_STEP, physicsClientId=self.client)
        p.setPhysicsEngineParameter(deterministicOverlappingPairs=1, numSolverIterations=100, physicsClientId=self.client)
        self.table = self.add_box(TABLE_HALF_EXTENTS, TABLE_CENTRE, (0.72, 0.6, 0.45, 1.0), mass=0.0)
        self.robot = p.loadURDF(
            panda_urdf(True), basePosition=(0, 0, 0), useFixedBase=True,
            flags=p.URDF_ENABLE_CACHED_GRAPHICS_SHAPES, physicsClientId=self.client,
        )
        # Couple the fingers so they move symmetrically (one command drives both).
        gear = p.createConstraint(
            self.robot, FINGER_JOINTS[0], self.robot, FINGER_JOINTS[1], p.JOINT_GEAR, (1, 0, 0), (0, 0, 0), (0, 0, 0),
            physicsClientId=self.client,
        )
        p.changeConstraint(gear, gearRatio=-1, erp=0.1, maxForce=50, physicsClientId=self.client)
        for link in FINGER_JOINTS:
            p.changeDynamics(self.robot, link, lateralFriction=1.5, spinningFriction=0.01, physicsClientId=self.client)
        self.reset_arm(HOME, gripper_open=1.0)

    def close(self) -> None:
        if self.client is not None:
            p.resetSimulation(physicsClientId=self.client)
            _spare_clients.append(self.client)
            self.client = None

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- scene ----------------------------------------------------------------------------
    def add_box(self, half_extents, position, rgba, mass: float = 0.1, orientation=(0, 0, 0, 1),
                collision: bool = True, friction: float = 1.0) -> int:
        """A box body; ``collision=False`` makes a visual-only marker."""
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=half_extents, physicsClientId=self.client) if collision else -1
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=half_extents, rgbaColor=rgba, physicsClientId=self.client)
        body = p.createMultiBody(mass, col, vis, position, orientation, physicsClientId=self.client)
        if collision:
            p.changeDynamics(body, -1, lateralFriction=friction, physicsClientId=self.client)
        return body

    def body_pose(self, body: int) -> tuple[np.ndarray, np.ndarray]:
        pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=self.client)
        return np.array(pos), np.array(orn)

    def set_body_pose(self, body: int, position, orientation) -> None:
        """Teleport a body (no physics in between)."""
        p.resetBasePositionAndOrientation(body, tuple(position), tuple(orientation), physicsClientId=self.client)

    def obstacle_bodies(self) -> list[int]:
        """Every body the planner must avoid (all but the robot)."""
        n = p.getNumBodies(physicsClientId=self.client)
        ids = [p.getBodyUniqueId(i, physicsClientId=self.client) for i in range(n)]
        return [b for b in ids if b != self.robot]

    # -- robot state ----------------------------------------------------------------------
    def reset_arm(self, q, gripper_open: float = 1.0) -> None:
        """Teleport the arm (no physics), e.g. to the start configuration."""
        for j, v in zip(ARM_JOINTS, q):
            p.resetJointState(self.robot, j, v, physicsClientId=self.client)
        width = FINGER_OPEN * gripper_open
        for j in FINGER_JOINTS:
            p.resetJointState(self.robot, j, width, physicsClientId=self.client)
        self.gripper_command = float(gripper_open)
        self.command_arm(q)
        self._command_gripper()

    def joint_positions(self) -> np.ndarray:
        return self.arm_state()[0]

    def joint_velocities(self) -> np.ndarray:
        return self.arm_state()[1]

    def arm_state(self) -> tuple[np.ndarray, np.ndarray]:
        """The arm's joint positions and velocities, from one query."""
        states = p.getJointStates(self.robot, ARM_JOINTS, physicsClientId=self.client)
        return np.array([s[0] for s in states]), np.array([s[1] for s in states])

    def finger_width(self) -> float:
        states = p.getJointStates(self.robot, FINGER_JOINTS, physicsClientId=self.client)
        return float(states[0][0] + states[1][0])

    def gripper_pose(self) -> np.ndarray:
        """Grasp-frame pose ``[x, y, z, qx, qy, qz, qw]`` (between the fingertips)."""
        state = p.getLinkState(self.robot, GRASP_LINK, computeForwardKinematics=True, physicsClientId=self.client)
        return np.array([*state[4], *state[5]])

    def link_pose(self, link: int) -> tuple[np.ndarray, np.ndarray]:
        state = p.getLinkState(self.robot, link, computeForwardKinematics=True, physicsClientId=self.client)
        return np.array(state[4]), np.array(state[5])

    # -- control and physics --------------------------------------------------------------
    def command_arm(self, q, velocities=None) -> None:
        p.setJointMotorControlArray(
            self.robot, ARM_JOINTS, p.POSITION_CONTROL, targetPositions=_floats(q),
            targetVelocities=_floats(velocities) if velocities is not None else _ZEROS,
            forces=ARM_FORCES, positionGains=_POSITION_GAINS, velocityGains=_VELOCITY_GAINS, physicsClientId=self.client,
        )

    def _command_gripper(self) -> None:
        target = FINGER_OPEN * self.gripper_command
        p.setJointMotorControlArray(
            self.robot, FINGER_JOINTS, p.POSITION_CONTROL, targetPositions=[target, target],
            forces=[GRIPPER_FORCE] * 2, physicsClientId=self.client,
        )

    def step(self, n: int = 1) -> None:
        """Advance the physics ``n`` fixed steps, calling the step callbacks after each."""
        for _ in range(n):
            p.stepSimulation(physicsClientId=self.client)
            self.step_count += 1
            for callback in self.step_callbacks:
                callback(self)

    @property
    def time_ns(self) -> int:
        """Simulation time in integer nanoseconds (exact, from the step count)."""
        return self.step_count * 1_000_000_000 // 240

    def set_gripper(self, gripper_open: float) -> None:
        self.gripper_command = float(gripper_open)
        self._command_gripper()

    def in_contact(self, body_a: int, body_b: int, link_a: int | None = None) -> bool:
        kwargs = {"linkIndexA": link_a} if link_a is not None else {}
        return bool(p.getContactPoints(body_a, body_b, physicsClientId=self.client, **kwargs))

    def held_object(self, candidates) -> int | None:
        """The candidate body touched by both fingers, if any."""
        for body in candidates:
            if all(self.in_contact(self.robot, body, link) for link in FINGER_JOINTS):
                return body
        return None

    # -- observation ----------------------------------------------------------------------
    def render_cameras(self):
        """Render every camera: ``{name: CameraObservation}``."""
        hand = self.link_pose(HAND_LINK)
        return {spec.name: render(self.client, spec, self.image_size, hand, self.light) for spec in self.cameras}

    def fingertip_offset(self) -> float:
        """How far the lowest fingertip point lies below the grasp frame when pointing down over the table.

        Measured on the fingers' collision geometry: their closest points to the table top. (A link's
        ``getAABB`` is padded by 3 mm, which made presses 3 mm shallower than their stated depth.)
        """
        grasp_z = self.gripper_pose()[2]
        points = [point for link in FINGER_JOINTS for point in
                  p.getClosestPoints(self.robot, self.table, 1.0, linkIndexA=link, physicsClientId=self.client)]
        lowest = min(point[5][2] for point in points)  # positionOnA: on the finger
        return float(grasp_z - lowest)
