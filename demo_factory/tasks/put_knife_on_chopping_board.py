"""Put knife on chopping board: grasp the knife by its handle and lay it flat on the board."""

from __future__ import annotations

import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

from demo_factory.tasks import motions
from demo_factory.tasks.base import KeyframeTarget, PlacementTask
from demo_factory.tasks.objects import Part, add_body, resting_on, upright
from demo_factory.tasks.variations import Variation

HANDLE_HALF = (0.045, 0.012, 0.012)
BLADE_HALF = (0.06, 0.012, 0.004)
BLADE_OFFSET = (HANDLE_HALF[0] + BLADE_HALF[0], 0.0, -HANDLE_HALF[2] + BLADE_HALF[2])
KNIFE_SPAN = (-HANDLE_HALF[0], BLADE_OFFSET[0] + BLADE_HALF[0])  # along the knife's x, from the handle centre
BOARD_HALF = (0.13, 0.075, 0.01)
GRIP_LIFT = 0.002  # grasp frame above the handle's centre
PLACE_CLEARANCE = 0.004
# The board on one side of the workspace (|y| range) and the knife on the other, so they never overlap.
KNIFE_REGION = ((0.34, 0.4), (0.1, 0.16))
BOARD_REGION = ((0.5, 0.56), (0.13, 0.17))


def knife_parts() -> list[Part]:
    return [Part("box", HANDLE_HALF, rgba=(0.15, 0.1, 0.08, 1.0)),
            Part("box", BLADE_HALF, BLADE_OFFSET, (0.8, 0.8, 0.85, 1.0))]


def yaw_rotation(yaw: float) -> tuple[float, ...]:
    return tuple(Rotation.from_euler("z", yaw).as_quat())


class PutKnifeOnChoppingBoard(PlacementTask):
    name = "put_knife_on_chopping_board"
    description = "Grasp the knife by its handle and lay it flat on the chopping board."
    categories = ("precision",)

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        return ["put the knife on the chopping board", "place the knife onto the board",
                "pick up the knife and lay it on the chopping board"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        side = rng.choice([-1.0, 1.0])
        (bx0, bx1), (by0, by1) = BOARD_REGION
        self.board_centre = np.array([rng.uniform(bx0, bx1), side * rng.uniform(by0, by1)])
        self.board_yaw = float(rng.uniform(-0.3, 0.3))
        self.board = add_body(world, [Part("box", BOARD_HALF, rgba=(0.76, 0.6, 0.38, 1.0))],
                              (*self.board_centre, BOARD_HALF[2]), yaw_rotation(self.board_yaw), mass=0.0)
        (kx0, kx1), (ky0, ky1) = KNIFE_REGION
        knife_yaw = float(rng.uniform(-0.6, 0.6))
        self.world = world
        self.knife = add_body(world, knife_parts(), (rng.uniform(kx0, kx1), -side * rng.uniform(ky0, ky1), HANDLE_HALF[2]),
                              yaw_rotation(knife_yaw), mass=0.06, friction=1.0)

    def expert(self, world) -> list[KeyframeTarget]:
        position, orientation = world.body_pose(self.knife)
        knife_yaw = float(Rotation.from_quat(orientation).as_euler("xyz")[2])
        handle = position + [0.0, 0.0, GRIP_LIFT]
        # Lay the knife along the board, its span centred on the board's centre.
        along = np.array([np.cos(self.board_yaw), np.sin(self.board_yaw)])
        centre_offset = (KNIFE_SPAN[0] + KNIFE_SPAN[1]) / 2
        place_xy = self.board_centre - centre_offset * along
        place_z = 2 * BOARD_HALF[2] + HANDLE_HALF[2] + GRIP_LIFT + PLACE_CLEARANCE
        return (motions.grasp(handle, motions.top_down(knife_yaw))
                + motions.place([*place_xy, place_z], motions.top_down(self.board_yaw)))

    def graspable_bodies(self) -> list[int]:
        return [self.knife]

    def _on_board(self, point) -> bool:
        local = Rotation.from_euler("z", -self.board_yaw).apply(np.asarray(point) - [*self.board_centre, 0.0])
        return abs(local[0]) < BOARD_HALF[0] and abs(local[1]) < BOARD_HALF[1]

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Put the knife back down where it was."""
        keyframes = self.expert(world)
        put_back = keyframes[1].pose
        return keyframes[:4] + motions.place(put_back[:3], put_back[3:])

    def success(self, world) -> bool:
        position, orientation = world.body_pose(self.knife)
        ends = [p.multiplyTransforms(position, orientation, (x, 0.0, 0.0), (0, 0, 0, 1))[0] for x in KNIFE_SPAN]
        return (all(self._on_board(end) for end in ends) and upright(world, self.knife, 0.1)
                and resting_on(world, self.knife, self.board))

    def scene_facts(self) -> dict:
        return {"board": [round(float(v), 6) for v in self.board_centre], "board_yaw": round(self.board_yaw, 6),
                "knife": [round(float(v), 6) for v in self.world.body_pose(self.knife)[0]]}
