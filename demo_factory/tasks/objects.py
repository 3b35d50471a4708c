"""Task objects built from primitive shapes, and the simulator-state checks the success tests use.

A body is a list of ``Part``s (boxes, cylinders, spheres) rigidly joined: the first part is the
base, the others are links on fixed joints, so each part keeps its own colour and the whole body
has one id (one segmentation label). Dynamic bodies get each part's mass from its volume.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pybullet as p

from demo_factory.sim.world import FINGER_JOINTS

REST_LINEAR = 0.01  # m/s: slower than this counts as at rest
REST_ANGULAR = 0.1  # rad/s


@dataclass(frozen=True)
class Part:
    """One primitive: "box" (size = half extents), "cylinder" (radius, length along z) or "sphere" (radius,)."""

    shape: str
    size: tuple[float, ...]
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rgba: tuple[float, ...] = (0.5, 0.5, 0.5, 1.0)
    orientation: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0)

    def volume(self) -> float:
        if self.shape == "box":
            return 8.0 * float(np.prod(self.size))
        if self.shape == "cylinder":
            return float(np.pi * self.size[0] ** 2 * self.size[1])
        return float(4.0 / 3.0 * np.pi * self.size[0] ** 3)


def _shapes(client: int, part: Part, collision: bool) -> tuple[int, int]:
    geom = {"box": p.GEOM_BOX, "cylinder": p.GEOM_CYLINDER, "sphere": p.GEOM_SPHERE}[part.shape]
    if part.shape == "box":
        col_kw = vis_kw = {"halfExtents": part.size}
    elif part.shape == "cylinder":
        col_kw, vis_kw = {"radius": part.size[0], "height": part.size[1]}, {"radius": part.size[0], "length": part.size[1]}
    else:
        col_kw = vis_kw = {"radius": part.size[0]}
    col = p.createCollisionShape(geom, physicsClientId=client, **col_kw) if collision else -1
    vis = p.createVisualShape(geom, rgbaColor=part.rgba, physicsClientId=client, **vis_kw)
    return col, vis


def add_body(world, parts: list[Part], position, orientation=(0.0, 0.0, 0.0, 1.0), mass: float = 0.0,
             friction: float = 1.0, collision: bool = True) -> int:
    """A rigid body of ``parts`` at ``position``; ``mass`` 0 makes it fixed, ``collision`` False a marker.

    The first part is the base and sits at the body's origin (its offset is ignored); the others
    are placed at their offsets in the body frame.
    """
    client = world.client
    shapes = [_shapes(client, part, collision) for part in parts]
    volumes = np.array([part.volume() for part in parts])
    masses = mass * volumes / volumes.sum()
    links = parts[1:]
    body = p.createMultiBody(
        baseMass=float(masses[0]), baseCollisionShapeIndex=shapes[0][0], baseVisualShapeIndex=shapes[0][1],
        basePosition=[float(v) for v in position], baseOrientation=[float(v) for v in orientation],
        
        linkMasses=[float(m) for m in masses[1:]],
        linkCollisionShapeIndices=[s[0] for s in shapes[1:]], linkVisualShapeIndices=[s[1] for s in shapes[1:]],
        linkPositions=[part.offset for part in links], linkOrientations=[part.orientation for part in links],
        linkInertialFramePositions=[(0, 0, 0)] * len(links), linkInertialFrameOrientations=[(0, 0, 0, 1)] * len(links),
        linkParentIndices=[0] * len(links), linkJointTypes=[p.JOINT_FIXED] * len(links),
        linkJointAxis=[(0, 0, 1)] * len(links), physicsClientId=client,
    ) if links else p.createMultiBody(
        baseMass=float(masses[0]), baseCollisionShapeIndex=shapes[0][0], baseVisualShapeIndex=shapes[0][1],
        basePosition=[float(v) for v in position], baseOrientation=[float(v) for v in orientation],
         physicsClientId=client,
    )
    if collision:
        for link in range(-1, len(links)):
            p.changeDynamics(body, link, lateralFriction=friction, physicsClientId=client)
    return body


def marker(world, position, radius: float, rgba) -> int:
    """A visual-only sphere (no collision): a target to reach or a height to lift to."""
    return add_body(world, [Part("sphere", (radius,), rgba=tuple(rgba))], position, collision=False)


def hold_where_left(world, body: int, links, torque: float) -> None:
    """Give a jointed body's ``links`` a grippy surface (friction 1.5) and its joint 0 friction: a velocity motor
    at rest with ``torque`` N·m of force keeps the joint where the gripper leaves it."""
    for link in links:
        p.changeDynamics(body, link, lateralFriction=1.5, physicsClientId=world.client)
    p.setJointMotorControl2(body, 0, p.VELOCITY_CONTROL, targetVelocity=0.0, force=torque, physicsClientId=world.client)


# -- state checks ------------------------------------------------------------------------------
def at_rest(world, body: int) -> bool:
    linear, angular = p.getBaseVelocity(body, physicsClientId=world.client)
    return float(np.linalg.norm(linear)) < REST_LINEAR and float(np.linalg.norm(angular)) < REST_ANGULAR


def touching(world, body: int, other: int) -> bool:
    return bool(p.getContactPoints(body, other, physicsClientId=world.client))


def held(world, body: int) -> bool:
    """Both fingers touch the body (it is gripped by friction, no constraint involved)."""
    return all(world.in_contact(world.robot, body, link) for link in FINGER_JOINTS)


def free_of_robot(world, body: int) -> bool:
    return not touching(world, body, world.robot)


def resting_on(world, body: int, support: int) -> bool:
    """At rest, touching ``support`` and not held up by the robot."""
    return at_rest(world, body) and touching(world, body, support) and free_of_robot(world, body)


def upright(world, body: int, tolerance: float = 0.2) -> bool:
    """The body's z axis is within ``tolerance`` rad of the world's."""
    _, orientation = world.body_pose(body)
    z_axis = np.array(p.getMatrixFromQuaternion(orientation)).reshape(3, 3)[:, 2]
    return float(np.arccos(np.clip(z_axis[2], -1.0, 1.0))) < tolerance
