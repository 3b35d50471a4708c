"""Wipe desk: grasp the sponge and wipe every dirt spot off the table with it."""

from __future__ import annotations

import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

from demo_factory.tasks import motions
from demo_factory.tasks.base import KeyframeTarget, PlacementTask
from demo_factory.tasks.objects import Part, add_body
from demo_factory.tasks.variations import Variation

SPONGE_HALF = (0.045, 0.025, 0.02)  # long side across the strokes, gripped across its 5 cm width
SPONGE_RGBA = (0.95, 0.82, 0.2, 1.0)
SPONGE_MASS = 0.03
SPONGE_FRICTION = 0.8
SPONGE_YAW = np.pi / 4  # the sponge lies turned up to this much either way
SPONGE_REGION = ((0.34, 0.6), (-0.25, 0.25))
SPONGE_CLEARANCE = 0.08  # sponge centre to any spot centre at the start: the resting sponge covers none
GRASP_ABOVE_CENTRE = 0.008  # grasp frame above the sponge's centre; the fingertips stay 2 cm above the table
ABOVE = 0.10  # approach height above the grasp and the first stroke
STROKE_GAP = 0.002  # the sponge's bottom this far above the table on a stroke: touching, never dragging
HOP = 0.03  # how far the sponge rises between strokes
WIPE_HEIGHT = 0.01  # a spot under the sponge is wiped while its bottom is this close to the table
# Dirt: two rows of spots across the robot's view, one stroke each, far enough apart that a stroke
# over one row never reaches the other (the wrong action relies on it).
PATCH_REGION = ((0.42, 0.54), (-0.12, 0.12))  # the centre between the two rows
ROW_GAP = 0.075  # x distance between the rows; a row's stroke covers x within SPONGE_HALF[0] of it
ROW_JITTER = 0.012  # a spot's x offset from its row (m)
ROW_HALF_LENGTH = 0.07  # a row's spots lie within this y distance of the patch centre
SPOTS_PER_ROW = (2, 3)
SPOT_SPACING = 0.035  # between spots of a row
SPOT_RADIUS = (0.009, 0.014)
SPOT_RGBA = (0.3, 0.2, 0.1, 1.0)
SPOT_Z = 0.0006  # a flat disc just above the table top
STROKE_LEAD = 0.045  # a stroke starts this far (sponge centre) before its first spot: the lowered sponge covers none
STROKE_RUN_ON = 0.015  # and ends this far past its last spot


class WipeDesk(PlacementTask):
    name = "wipe_desk"
    description = "Grasp the sponge and wipe every dirt spot off the table with it; a wiped spot disappears."
    categories = ("long term",)

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        return ["wipe dirt off the desk", "use the sponge to clean up the desk", "remove the dirt from the desk",
                "grip the sponge and wipe it back and forth over any dirt you find"]

    # -- scene ----------------------------------------------------------------------------
    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        (x0, x1), (y0, y1) = PATCH_REGION
        centre = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        self.rows: list[list[np.ndarray]] = []
        for row_x in (centre[0] - ROW_GAP / 2, centre[0] + ROW_GAP / 2):
            n = int(rng.integers(SPOTS_PER_ROW[0], SPOTS_PER_ROW[1] + 1))
            while True:
                ys = np.sort(rng.uniform(centre[1] - ROW_HALF_LENGTH, centre[1] + ROW_HALF_LENGTH, n))
                if np.all(np.diff(ys) >= SPOT_SPACING):
                    break
            self.rows.append([np.array([row_x + rng.uniform(-ROW_JITTER, ROW_JITTER), y]) for y in ys])
        self.row_x = [centre[0] - ROW_GAP / 2, centre[0] + ROW_GAP / 2]
        spots = [xy for row in self.rows for xy in row]
        (sx0, sx1), (sy0, sy1) = SPONGE_REGION
        while True:
            sponge_xy = np.array([rng.uniform(sx0, sx1), rng.uniform(sy0, sy1)])
            if min(np.linalg.norm(sponge_xy - xy) for xy in spots) >= SPONGE_CLEARANCE:
                break
        yaw = rng.uniform(-SPONGE_YAW, SPONGE_YAW)
        self.world = world
        self.spots = [add_body(world, [Part("cylinder", (float(rng.uniform(*SPOT_RADIUS)), 0.001), rgba=SPOT_RGBA)],
                               (*xy, SPOT_Z), collision=False) for xy in spots]
        self.spot_xy = {spot: xy for spot, xy in zip(self.spots, spots)}
        self.sponge = add_body(world, [Part("box", SPONGE_HALF, rgba=SPONGE_RGBA)], (*sponge_xy, SPONGE_HALF[2]),
                               Rotation.from_euler("z", yaw).as_quat(), mass=SPONGE_MASS, friction=SPONGE_FRICTION)
        self.wiped: set[int] = set()

    def on_step(self, world) -> None:
        """Wipe (hide) every spot under the sponge's bottom face while that face is on or just above the table."""
        position, orientation = world.body_pose(self.sponge)
        rotation = np.array(p.getMatrixFromQuaternion(orientation)).reshape(3, 3)
        lowest = float(position[2]) - float(np.abs(rotation[2]) @ SPONGE_HALF)
        if lowest > WIPE_HEIGHT or len(self.wiped) == len(self.spots):
            return
        for spot, xy in self.spot_xy.items():
            if spot in self.wiped:
                continue
            local = rotation.T @ np.array([xy[0] - position[0], xy[1] - position[1], 0.0])
            if abs(local[0]) <= SPONGE_HALF[0] and abs(local[1]) <= SPONGE_HALF[1]:
                self.wiped.add(spot)
                # Hidden, not removed: removing a body would renumber the others.
                p.changeVisualShape(spot, -1, rgbaColor=(*SPOT_RGBA[:3], 0.0), physicsClientId=world.client)

    # -- expert ---------------------------------------------------------------------------
    def expert(self, world) -> list[KeyframeTarget]:
        return self._wipe(world, rows=len(self.rows))

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Wipe the first row of spots only: about half of the dirt stays."""
        return self._wipe(world, rows=1)

    def _wipe(self, world, rows: int) -> list[KeyframeTarget]:
        """Grasp the sponge, then one stroke along y over each of the first ``rows`` rows, back and forth."""
        position, orientation = world.body_pose(self.sponge)
        yaw = Rotation.from_quat(orientation).as_euler("xyz")[2]
        grip_yaw = float((yaw + np.pi / 2) % np.pi - np.pi / 2)  # the fingers close across the sponge's width
        grip = motions.raised(position, GRASP_ABOVE_CENTRE)
        keyframes = motions.grasp(grip, motions.top_down(grip_yaw), ABOVE)
        # Held with yaw 0, the sponge's long side lies along x, across the strokes along y.
        down = motions.top_down(0.0)
        stroke_z = SPONGE_HALF[2] + GRASP_ABOVE_CENTRE + STROKE_GAP  # the grasp frame's height on a stroke
        for index in range(rows):
            ys = [float(xy[1]) for xy in self.rows[index]]
            start, end = min(ys) - STROKE_LEAD, max(ys) + STROKE_RUN_ON
            if index % 2:  # back the other way
                start, end = max(ys) + STROKE_LEAD, min(ys) - STROKE_RUN_ON
            x = self.row_x[index]
            at_start, at_end = [x, start, stroke_z], [x, end, stroke_z]
            if index == 0:
                keyframes += motions.reach(motions.raised(at_start, ABOVE), down, motions.CLOSED)
            else:
                keyframes += motions.lift(motions.raised(at_start, HOP), down)
            keyframes += motions.lift(at_start, down) + motions.lift(at_end, down)
            keyframes += motions.lift(motions.raised(at_end, HOP if index + 1 < rows else ABOVE), down)
        return keyframes

    def graspable_bodies(self) -> list[int]:
        return [self.sponge]

    def success(self, world) -> bool:
        return len(self.wiped) == len(self.spots)

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        return [np.array([*self.spot_xy[spot], 0.0]) for spot in self.spots]

    def scene_facts(self) -> dict:
        return {
            "sponge": [round(float(v), 6) for v in self.world.body_pose(self.sponge)[0]],
            "spots": [[round(float(v), 6) for v in self.spot_xy[spot]] for spot in self.spots],
            "wiped": [index for index, spot in enumerate(self.spots) if spot in self.wiped],
        }
