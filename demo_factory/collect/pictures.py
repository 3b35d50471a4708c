"""Pictures of a variation's goal, for people who write instructions without being shown words.

Per variation: the scene seen from the two shoulder cameras with the goal order marked (numbered
badges on the buttons to press, or on the cubes to stack with a ring around the target spot), and
a drawn goal (push_buttons: the buttons in pressing order; tower: the finished tower). For tower,
also the scene rendered with the instructed cubes already stacked on the target.

The scene is the one ``demo-factory generate --split test --seed 0`` records first for the
variation (same episode seed), so pictures are deterministic: the same PNG bytes on every machine.
Rendering is lazy (on first request) and cached as PNG files under a cache folder.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from demo_factory.generate import episode_seed
from demo_factory.rollout import start_scene
from demo_factory.sim import DEFAULT_CAMERAS, CameraSpec, World
from demo_factory.sim.camera import render
from demo_factory.sim.world import HAND_LINK
from demo_factory.tasks import Task, Variation, get_task
from demo_factory.tasks.palette import COLOURS

# Bump when the pictures change, so old cache entries are not served.
RENDER_VERSION = "v2"
PICTURE_SIZE = 320  # pixels, square
SCENE_CAMERAS = ("left_shoulder", "right_shoulder")
# The dataset's shoulder cameras, zoomed in so the objects are large enough to see.
ZOOMED_FOV_DEG = 44.0
WIDEN_DEG, MAX_WIDENINGS = 8.0, 4  # wider views for goals the zoomed one cuts off
# The finished tower seen from close by; eye and target are relative to the tower's target spot.
CLOSE_UP = CameraSpec("close_up", eye=(0.32, 0.3, 0.32), target=(0.0, 0.0, 0.0), fov_deg=40.0)
BADGE_RADIUS = 13
BADGE_LIFT = 0.05  # metres above the marked object where its badge floats
INK = (30, 30, 30)
PAPER = (250, 250, 250)


@dataclass(frozen=True)
class Picture:
    """One picture of a variation: its file name (without .png) and a short caption for the page."""

    name: str
    caption: str


def pictures_for(task: Task) -> tuple[Picture, ...]:
    """The pictures shown for every variation of ``task``, in page order."""
    scene = tuple(Picture(camera, f"scene, {camera.replace('_', ' ')} camera") for camera in SCENE_CAMERAS)
    if task.goal_sketch == "stack":
        return (*scene, Picture("goal_render", "when done, close up"), Picture("goal", "when done"))
    if task.variation_kind != "colour":  # a drawer, a shelf, a placement: the scene's badges show the goal
        return scene
    return (*scene, Picture("goal", "order"))


def picture_seed(task: Task, variation: Variation) -> int:
    """The episode seed of the variation's first episode in ``generate --split test --seed 0``."""
    index = [v.id for v in task.split_variations("test")].index(variation.id)
    return episode_seed(0, task.name, "test", index)


# -- drawing --------------------------------------------------------------------------------------
def _bgr(colour: str) -> tuple[int, int, int]:
    r, g, b = COLOURS[colour]
    return (int(round(255 * b)), int(round(255 * g)), int(round(255 * r)))


def draw_badge(image: np.ndarray, centre: tuple[int, int], number: int, radius: int = BADGE_RADIUS) -> None:
    """A white disc with a dark rim and a dark number, drawn on a BGR image in place."""
    cv2.circle(image, centre, radius, PAPER, -1, cv2.LINE_AA)
    cv2.circle(image, centre, radius, INK, 2, cv2.LINE_AA)
    text = str(number)
    scale = radius / 18
    (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 2)
    cv2.putText(image, text, (centre[0] - w // 2, centre[1] + h // 2), cv2.FONT_HERSHEY_SIMPLEX, scale, INK, 2,
                cv2.LINE_AA)


def project(point: np.ndarray, camera) -> tuple[int, int]:
    """Pixel (u, v) of a world point in a ``CameraObservation`` (OpenCV pinhole)."""
    fx, fy, cx, cy = camera.intrinsics
    x, y, z = (np.linalg.inv(camera.extrinsics) @ np.array([*point, 1.0]))[:3]
    return int(round(fx * x / z + cx)), int(round(fy * y / z + cy))


def mark_order(image: np.ndarray, camera, points: list[np.ndarray]) -> None:
    """Numbered badges 1..n floating above the world ``points``, each with a stem down to its point."""
    for number, point in enumerate(points, start=1):
        foot = project(point, camera)
        head = project(point + np.array([0.0, 0.0, BADGE_LIFT]), camera)
        cv2.line(image, foot, head, PAPER, 4, cv2.LINE_AA)
        cv2.line(image, foot, head, INK, 2, cv2.LINE_AA)
        draw_badge(image, head, number)


def mark_target(image: np.ndarray, camera, centre: np.ndarray, radius: float = 0.045) -> None:
    """A light ring with a dark core on the table around a world point (the tower's target spot)."""
    angles = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    ring = [centre + radius * np.array([np.cos(a), np.sin(a), 0.0]) for a in angles]
    pixels = np.array([project(q, camera) for q in ring], dtype=np.int32)
    cv2.polylines(image, [pixels], True, PAPER, 5, cv2.LINE_AA)
    cv2.polylines(image, [pixels], True, INK, 2, cv2.LINE_AA)


def draw_button_order(colours: tuple[str, ...], size: int = PICTURE_SIZE) -> np.ndarray:
    """The buttons to press as coloured discs from left to right, numbered, with arrows between."""
    image = np.full((size, size, 3), PAPER, np.uint8)
    step = size // 3
    radius = step // 3
    y = size // 2
    for i, colour in enumerate(colours):
        x = step // 2 + i * step
        cv2.circle(image, (x, y), radius + 6, (64, 64, 64), -1, cv2.LINE_AA)
        cv2.circle(image, (x, y), radius, _bgr(colour), -1, cv2.LINE_AA)
        draw_badge(image, (x, y - radius - 26), i + 1)
        if i + 1 < len(colours):
            cv2.arrowedLine(image, (x + radius + 12, y), (x + step - radius - 12, y), INK, 3, cv2.LINE_AA,
                            tipLength=0.35)
    return image


def draw_tower(colours: tuple[str, ...], size: int = PICTURE_SIZE) -> np.ndarray:
    """The finished tower: coloured squares stacked bottom-up on a grey mat, numbered in order."""
    image = np.full((size, size, 3), PAPER, np.uint8)
    cube = size // 5
    base_y = size - size // 6
    x0 = (size - cube) // 2
    cv2.rectangle(image, (x0 - cube // 2, base_y), (x0 + cube + cube // 2, base_y + 12), (153, 153, 153), -1)
    for level, colour in enumerate(colours):
        top = base_y - (level + 1) * cube
        cv2.rectangle(image, (x0, top), (x0 + cube, top + cube), _bgr(colour), -1)
        cv2.rectangle(image, (x0, top), (x0 + cube, top + cube), INK, 2)
        draw_badge(image, (x0 + cube + 32, top + cube // 2), level + 1)
    return image


# -- rendering ------------------------------------------------------------------------------------
def render_variation(task_name: str, variation_id: int) -> dict[str, np.ndarray]:
    """Every picture of ``pictures_for(task)`` for one variation, as RGB arrays (deterministic)."""
    task = get_task(task_name)  # a fresh instance: building a scene stores state on the task
    variation = task.variation(variation_id)
    cameras = tuple(replace(c, fov_deg=ZOOMED_FOV_DEG) for c in DEFAULT_CAMERAS if c.name in SCENE_CAMERAS)
    world = start_scene(task, variation, picture_seed(task, variation), cameras, (PICTURE_SIZE, PICTURE_SIZE))
    try:
        points = task.goal_points(world, variation)
        views = framed_views(world, points)
        pictures = {}
        place = task.goal_place()
        for name, camera in views.items():
            image = cv2.cvtColor(camera.rgb, cv2.COLOR_RGB2BGR)
            if place is not None:
                mark_target(image, camera, place)
            mark_order(image, camera, points)
            pictures[name] = image
        names = {picture.name for picture in pictures_for(task)}
        if "goal_render" in names:
            pictures["goal_render"] = _render_goal(world, task, variation)
            pictures["goal"] = draw_tower(variation.words)
        elif "goal" in names:
            pictures["goal"] = draw_button_order(variation.words)
    finally:
        world.close()
    return {name: cv2.cvtColor(image, cv2.COLOR_BGR2RGB) for name, image in pictures.items()}


def framed_views(world: World, points: list[np.ndarray]) -> dict:
    """The scene cameras' views, each widened from ``ZOOMED_FOV_DEG`` in steps of ``WIDEN_DEG`` until every goal
    point and its badge is inside the picture (a reach_target sphere floats up to 35 cm above the table)."""
    views = world.render_cameras()
    for _ in range(MAX_WIDENINGS):
        cut = {name for name, camera in views.items() for point in points for lift in (0.0, BADGE_LIFT + 0.02)
               if not _inside(project(point + np.array([0.0, 0.0, lift]), camera), camera.rgb.shape)}
        if not cut:
            break
        world.cameras = tuple(replace(c, fov_deg=c.fov_deg + WIDEN_DEG) if c.name in cut else c for c in world.cameras)
        views = world.render_cameras()
    return views


def _inside(pixel: tuple[int, int], shape, margin: int = BADGE_RADIUS) -> bool:
    return margin <= pixel[0] < shape[1] - margin and margin <= pixel[1] < shape[0] - margin


def _render_goal(world: World, task: Task, variation: Variation) -> np.ndarray:
    """A close-up of the goal place with the instructed objects teleported into the finished goal."""
    top = task.show_goal(world, variation)
    target = task.goal_place()
    close_up = replace(CLOSE_UP, eye=tuple(target + CLOSE_UP.eye), target=tuple(target + CLOSE_UP.target))
    camera = render(world.client, close_up, (PICTURE_SIZE, PICTURE_SIZE), world.link_pose(HAND_LINK))
    image = cv2.cvtColor(camera.rgb, cv2.COLOR_RGB2BGR)
    head = project(top + np.array([0.0, 0.0, BADGE_LIFT]), camera)
    cv2.arrowedLine(image, head, project(top, camera), INK, 3, cv2.LINE_AA, tipLength=0.3)
    return image


def encode_png(rgb: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return data.tobytes()


class PictureCache:
    """Renders a variation's pictures on first request and keeps them as PNG files in ``folder``.

    Thread-safe: one render at a time (PyBullet clients are not meant to be driven from several
    threads), and each file is written under a temporary name then renamed, so a reader never
    sees half a PNG, even with several servers sharing the folder.
    """

    def __init__(self, task: Task, folder: Path):
        self.task = task
        self.folder = Path(folder) / RENDER_VERSION / task.name
        self.names = {picture.name for picture in pictures_for(task)}
        self._lock = threading.Lock()

    def path(self, variation_id: int, name: str) -> Path:
        return self.folder / f"var{variation_id:04d}" / f"{name}.png"

    def png(self, variation_id: int, name: str) -> bytes:
        """The PNG bytes of one picture, rendering the variation's pictures if not cached yet."""
        if name not in self.names:
            raise KeyError(name)
        path = self.path(variation_id, name)
        if not path.is_file():
            with self._lock:
                if not path.is_file():
                    self._render(variation_id)
        return path.read_bytes()

    def _render(self, variation_id: int) -> None:
        pictures = render_variation(self.task.name, variation_id)
        for name, rgb in pictures.items():
            path = self.path(variation_id, name)
            path.parent.mkdir(parents=True, exist_ok=True)
            partial = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.partial")
            partial.write_bytes(encode_png(rgb))
            os.replace(partial, path)


def default_cache_folder() -> Path:
    """``$XDG_CACHE_HOME/demo_factory/collect_pictures`` (``~/.cache`` when unset)."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "demo_factory" / "collect_pictures"
