"""Named, seeded perturbations of a scene and its sensors: how robust a policy is, and varied training data.

Each perturbation is one documented change of what the cameras see, drawn from the episode seed (its own
random stream, so the scene's layout is the unperturbed episode's) and applied to a built scene before it
settles (``start_scene(..., perturbations=...)``). It returns the parameters it drew, which the recorder keeps
in the episode's metadata (``EpisodeInfo.perturbations``). A factor is of one of three kinds:

- ``visual``: it changes what the cameras see and nothing of a task object's physics; the expert's keyframes and
  its success are the unperturbed episode's.
- ``shape``: it sets a task's object size or shape before the scene is built (``Task.object_scale``,
  ``PushButtons.housing_scale``); the expert's keyframes follow the objects.
- ``event``: it changes the scene mid-episode, after the first press (a button moved or repainted); a move bumps
  ``world.scene_changes``, and the expert looks again (``rollout.ExpertKeyframes``).

tests/test_perturbations.py checks that the expert succeeds under every factor. The factors are Colosseum's and
the HiveFormer paper's real-robot situations (its Figure 4):

| name | what changes |
|---|---|
| ``lighting`` | the light's direction, colour and ambient / diffuse / specular strength |
| ``table_colour`` | the table top's colour |
| ``table_texture`` | a procedural texture (checks, stripes or blotches) on the table top |
| ``object_shade`` | every task object's colours, lightened or darkened by 8-18 % (same colour names) |
| ``distractors`` | 2-4 objects of other shapes and colours on free places of the table (visual only) |
| ``camera_pose`` | the two shoulder cameras moved by up to 4 cm and re-aimed by up to 3 cm (calibration follows) |
| ``occluder`` | a hand-sized object between one shoulder camera and the workspace (the paper's occluded gripper) |
| ``lookalike`` | a copy of the first object the instruction names on a free place (the paper's second object that looks like the target); not for placements and fixtures |
| ``object_size`` | the task objects 12-25 % smaller or larger (Colosseum's object size); resizable tasks only |
| ``taller_button`` | the buttons' housings 2.5-4 times as tall (the paper's changed object shape) |
| ``moved_target`` | after the first press, the next instructed button moves elsewhere (the paper's moved target) |
| ``same_colour`` | after the first press, an uninstructed button takes the pressed one's colour (two of one colour) |

Objects added by a perturbation have no collision shape: they cannot block the robot or the expert, and what
they test is the policy's vision. Perturbations compose (``lighting,distractors``); each draws from its own
stream, so a factor's draw does not depend on which others are on.
"""

from __future__ import annotations

import colorsys
import os
import tempfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cache
from pathlib import Path

import numpy as np
import pybullet as p

from demo_factory.sim.world import World
from demo_factory.tasks import Task, Variation
from demo_factory.tasks.push_buttons import PushButtons

# Where perturbations may put objects: the part of the table the shoulder cameras see.
FREE_AREA = ((0.25, 0.72), (-0.32, 0.32))
CLEARANCE = 0.05  # metres between an added object and any other body's bounding box
SHADE_RANGE = (0.08, 0.18)
CAMERA_SHIFT, CAMERA_AIM_SHIFT = 0.04, 0.03
PERTURBATION_STREAM = 0x9E27  # keeps the perturbations' random streams apart from the scene's


@dataclass(frozen=True)
class Perturbation:
    """A named change of the scene or its sensors: ``apply(world, task, variation, rng)`` returns the drawn
    parameters (JSON-ready); ``refusal(task)`` says why it cannot apply to a task, or None; ``kind``: "visual",
    "shape" (applied before the scene is built) or "event" (module docstring)."""

    name: str
    description: str
    apply: Callable[[World, Task, Variation, np.random.Generator], dict]
    refusal: Callable[[Task], str | None] = lambda task: None
    kind: str = "visual"


def _rgb(values) -> list[float]:
    return [round(float(v), 4) for v in values]


def _task_bodies(world: World) -> list[int]:
    return [b for b in world.obstacle_bodies() if b != world.table]


# -- lighting and the table --------------------------------------------------------------------
def _lighting(world, task, variation, rng) -> dict:
    azimuth, elevation = rng.uniform(0, 2 * np.pi), rng.uniform(np.radians(25), np.radians(80))
    direction = [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
    colour = rng.uniform(0.7, 1.0, 3)
    options = {"lightDirection": _rgb(direction), "lightColor": _rgb(colour / colour.max()),
               "lightAmbientCoeff": round(float(rng.uniform(0.3, 0.8)), 4),
               "lightDiffuseCoeff": round(float(rng.uniform(0.2, 0.7)), 4),
               "lightSpecularCoeff": round(float(rng.uniform(0.0, 0.15)), 4)}
    world.light = options
    return options


def _table_rgb(rng) -> np.ndarray:
    hue, saturation, value = rng.uniform(0, 1), rng.uniform(0.05, 0.5), rng.uniform(0.3, 0.9)
    return np.array(colorsys.hsv_to_rgb(hue, saturation, value))


def _table_colour(world, task, variation, rng) -> dict:
    colour = _table_rgb(rng)
    p.changeVisualShape(world.table, -1, rgbaColor=(*colour, 1.0), physicsClientId=world.client)
    return {"rgb": _rgb(colour)}


TEXTURES = ("checks", "stripes", "blotches")


def texture_image(pattern: str, first: np.ndarray, second: np.ndarray, period: int, size: int = 256) -> np.ndarray:
    """A ``size`` x ``size`` RGB uint8 texture of two colours: checks or stripes of ``period`` pixels, or blotches
    (smoothed noise of that scale, from a fixed seed)."""
    v, u = np.mgrid[0:size, 0:size]
    if pattern == "checks":
        mix = ((u // period + v // period) % 2).astype(float)
    elif pattern == "stripes":
        mix = ((u + v) // period % 2).astype(float)
    else:
        coarse = np.random.default_rng(period).random((size // period + 2,) * 2)
        mix = (np.kron(coarse, np.ones((period, period)))[:size, :size] > 0.5).astype(float)
    image = first[None, None] * (1 - mix[..., None]) + second[None, None] * mix[..., None]
    return (255 * image).round().astype(np.uint8)


def _table_texture(world, task, variation, rng) -> dict:
    import cv2

    pattern = TEXTURES[rng.integers(len(TEXTURES))]
    first, second = _table_rgb(rng), _table_rgb(rng)
    period = int(rng.choice((8, 16, 32)))
    image = texture_image(pattern, first, second, period)
    folder = Path(tempfile.gettempdir()) / f"demo_factory_textures_{os.getuid()}"
    folder.mkdir(exist_ok=True)
    path = folder / f"{pattern}_{zlib.crc32(image.tobytes()):08x}.png"
    if not path.exists():
        partial = folder / f".{path.stem}.{os.getpid()}.png"
        cv2.imwrite(str(partial), image[:, :, ::-1])
        os.replace(partial, path)
    texture = p.loadTexture(str(path), physicsClientId=world.client)
    p.changeVisualShape(world.table, -1, textureUniqueId=texture, rgbaColor=(1, 1, 1, 1), physicsClientId=world.client)
    return {"pattern": pattern, "rgb": [_rgb(first), _rgb(second)], "period_px": period}


# -- the task's objects ------------------------------------------------------------------------
def _object_shade(world, task, variation, rng) -> dict:
    shades = {}
    for body in _task_bodies(world):
        towards = "white" if rng.random() < 0.5 else "black"
        amount = float(rng.uniform(*SHADE_RANGE))
        target = 1.0 if towards == "white" else 0.0
        for shape in p.getVisualShapeData(body, physicsClientId=world.client):
            link, rgba = shape[1], np.array(shape[7])
            rgb = rgba[:3] + amount * (target - rgba[:3])
            p.changeVisualShape(body, link, rgbaColor=(*rgb, rgba[3]), physicsClientId=world.client)
        shades[str(body)] = {"towards": towards, "amount": round(amount, 4)}
    return {"bodies": shades}


def _link_boxes(world: World, body: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The (low, high) corners of the bounding box of each of a body's links, the base first."""
    return [tuple(np.array(corner) for corner in p.getAABB(body, link, physicsClientId=world.client))
            for link in range(-1, p.getNumJoints(body, physicsClientId=world.client))]


def _footprints(world: World) -> list[tuple[np.ndarray, np.ndarray]]:
    """The xy bounding boxes of every link of every body but the table (the robot's too)."""
    return [(low[:2], high[:2]) for body in _task_bodies(world) + [world.robot] for low, high in _link_boxes(world, body)]


def free_place(world: World, rng: np.random.Generator, radius: float, taken: list, tries: int = 200) -> np.ndarray | None:
    """An xy point of ``FREE_AREA`` whose disc of ``radius`` keeps ``CLEARANCE`` from every body and from the
    ``taken`` discs ((centre, radius) pairs); None when ``tries`` draws find none."""
    boxes = _footprints(world)
    (x0, x1), (y0, y1) = FREE_AREA
    gap = radius + CLEARANCE
    for _ in range(tries):
        point = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        if any(np.all(point > low - gap) and np.all(point < high + gap) for low, high in boxes):
            continue
        if any(np.linalg.norm(point - centre) < r + radius + CLEARANCE for centre, r in taken):
            continue
        return point
    return None


def _visual_body(world: World, shape: int, position, orientation=(0, 0, 0, 1)) -> int:
    return p.createMultiBody(0, -1, shape, [float(v) for v in position], [float(v) for v in orientation],
                             physicsClientId=world.client)


DISTRACTOR_SHAPES = ("sphere", "cylinder", "box")


def _distractors(world, task, variation, rng) -> dict:
    placed, taken = [], []
    for _ in range(int(rng.integers(2, 5))):
        kind = DISTRACTOR_SHAPES[rng.integers(len(DISTRACTOR_SHAPES))]
        size = float(rng.uniform(0.015, 0.03))
        colour = np.array(colorsys.hsv_to_rgb(rng.uniform(0, 1), rng.uniform(0.3, 1.0), rng.uniform(0.3, 1.0)))
        point = free_place(world, rng, size, taken)
        if point is None:
            break
        rgba = (*colour, 1.0)
        if kind == "sphere":
            shape = p.createVisualShape(p.GEOM_SPHERE, radius=size, rgbaColor=rgba, physicsClientId=world.client)
            height = size
        elif kind == "cylinder":
            shape = p.createVisualShape(p.GEOM_CYLINDER, radius=size, length=3 * size, rgbaColor=rgba,
                                        physicsClientId=world.client)
            height = 1.5 * size
        else:
            shape = p.createVisualShape(p.GEOM_BOX, halfExtents=(size, size, size), rgbaColor=rgba,
                                        physicsClientId=world.client)
            height = size
        _visual_body(world, shape, (*point, height))
        taken.append((point, size * 1.5))
        placed.append({"shape": kind, "size": round(size, 4), "rgb": _rgb(colour), "xy": _rgb(point)})
    return {"objects": placed}


def _occluder(world, task, variation, rng) -> dict:
    cameras = [c for c in world.cameras if not c.on_hand]
    camera = cameras[rng.integers(len(cameras))]
    aim = np.array([rng.uniform(0.4, 0.6), rng.uniform(-0.15, 0.15), 0.05])
    fraction = float(rng.uniform(0.3, 0.45))
    centre = np.array(camera.eye) + fraction * (aim - np.array(camera.eye))
    radius = float(rng.uniform(0.03, 0.045))
    skin = np.array([0.87, 0.68, 0.55]) * rng.uniform(0.6, 1.0)
    shape = p.createVisualShape(p.GEOM_SPHERE, radius=radius, rgbaColor=(*skin, 1.0), physicsClientId=world.client)
    _visual_body(world, shape, centre)
    return {"camera": camera.name, "centre": _rgb(centre), "radius": round(radius, 4), "rgb": _rgb(skin)}


def _camera_pose(world, task, variation, rng) -> dict:
    moved, cameras = {}, []
    for camera in world.cameras:
        if camera.on_hand:
            cameras.append(camera)
            continue
        eye = np.array(camera.eye) + rng.uniform(-CAMERA_SHIFT, CAMERA_SHIFT, 3)
        target = np.array(camera.target) + rng.uniform(-CAMERA_AIM_SHIFT, CAMERA_AIM_SHIFT, 3)
        cameras.append(replace(camera, eye=tuple(eye.tolist()), target=tuple(target.tolist())))
        moved[camera.name] = {"eye": _rgb(eye), "target": _rgb(target)}
    world.cameras = tuple(cameras)
    return moved


def _instructed_body(world: World, point: np.ndarray) -> int | None:
    """The task body whose bounding box holds ``point`` (within 1 cm)."""
    return next((body for body in _task_bodies(world) for low, high in _link_boxes(world, body)
                 if np.all(point > low - 0.01) and np.all(point < high + 0.01)), None)


LOOKALIKE_MAX_RADIUS = 0.1  # metres: objects larger than this (a chest of drawers, an oven) are not copied


def _lookalike_refusal(task: Task) -> str | None:
    if type(task).goal_points is Task.goal_points:
        return f"{task.name} has no goal object to copy (its goal is a placement)"
    return _copyable(task.name)


@cache
def _copyable(task_name: str) -> str | None:
    """Why a task's first instructed object cannot be copied (part of a fixture, or too large), or None."""
    from demo_factory.tasks import get_task

    task = get_task(task_name)
    variation = task.split_variations("train")[0]
    world = World(image_size=(8, 8))
    try:
        task.build_scene(world, variation, np.random.default_rng(0))
        body = _instructed_body(world, np.asarray(task.goal_points(world, variation)[0]))
        if body is None or _footprint_radius(world, body)[0] > LOOKALIKE_MAX_RADIUS:
            return (f"the first object {task_name}'s instructions name is part of a fixture or wider than "
                    f"{2 * LOOKALIKE_MAX_RADIUS:g} m")
        return None
    finally:
        world.close()


def _footprint_radius(world: World, body: int) -> tuple[float, np.ndarray]:
    """Half the diagonal of a body's xy bounding box (all links) and the box's centre."""
    boxes = _link_boxes(world, body)
    low = np.min([b[0] for b in boxes], axis=0)[:2]
    high = np.max([b[1] for b in boxes], axis=0)[:2]
    return float(np.linalg.norm(high - low)) / 2, (low + high) / 2


def _lookalike(world, task, variation, rng) -> dict:
    points = task.goal_points(world, variation)
    body = _instructed_body(world, np.asarray(points[0])) if points else None
    if body is None:
        return {"copied": None}
    radius, origin = _footprint_radius(world, body)
    point = free_place(world, rng, radius, [])
    if point is None:
        return {"copied": None}
    shift = np.array([*(point - origin), 0.0])
    for shape in p.getVisualShapeData(body, physicsClientId=world.client):
        link, geometry, dims, mesh, local_position, local_orientation, rgba = (
            shape[1], shape[2], shape[3], shape[4], shape[5], shape[6], shape[7])
        if link == -1:
            frame = p.getBasePositionAndOrientation(body, physicsClientId=world.client)
        else:
            state = p.getLinkState(body, link, physicsClientId=world.client)
            frame = (state[4], state[5])
        position, orientation = p.multiplyTransforms(frame[0], frame[1], local_position, local_orientation)
        kwargs = {"rgbaColor": rgba, "physicsClientId": world.client}
        if geometry == p.GEOM_BOX:
            visual = p.createVisualShape(p.GEOM_BOX, halfExtents=[d / 2 for d in dims], **kwargs)
        elif geometry == p.GEOM_SPHERE:
            visual = p.createVisualShape(p.GEOM_SPHERE, radius=dims[0], **kwargs)
        elif geometry in (p.GEOM_CYLINDER, p.GEOM_CAPSULE):
            visual = p.createVisualShape(geometry, radius=dims[1], length=dims[0], **kwargs)
        elif geometry == p.GEOM_MESH:
            visual = p.createVisualShape(p.GEOM_MESH, fileName=mesh.decode(), meshScale=dims, **kwargs)
        else:
            continue
        _visual_body(world, visual, np.array(position) + shift, orientation)
    return {"copied": int(body), "xy": _rgb(point)}


# -- object size and shape, and mid-episode changes ----------------------------------------------
OBJECT_SCALE_CHANGE = (0.12, 0.25)  # smaller or larger by this fraction
HOUSING_SCALE = (2.5, 4.0)


def _resizable_refusal(task: Task) -> str | None:
    if task.resizable:
        return None
    return f"{task.name}'s objects have fixed sizes (resizable tasks: {', '.join(_resizable())})"


@cache
def _resizable() -> tuple[str, ...]:
    from demo_factory.tasks import TASKS

    return tuple(name for name, cls in TASKS.items() if cls.resizable)


def _object_size(world, task, variation, rng) -> dict:
    task.object_scale = float(1 + rng.choice((-1, 1)) * rng.uniform(*OBJECT_SCALE_CHANGE))
    return {"scale": round(task.object_scale, 4)}


def _buttons_refusal(task: Task) -> str | None:
    return None if isinstance(task, PushButtons) else f"{task.name} has no buttons"


def _presses_refusal(task: Task) -> str | None:
    if isinstance(task, PushButtons) and task.max_sequence > 1:
        return None
    return f"{task.name} has no sequence of presses (push_buttons has)"


def _taller_button(world, task, variation, rng) -> dict:
    task.housing_scale = float(rng.uniform(*HOUSING_SCALE))
    return {"housing_scale": round(task.housing_scale, 4)}


def after_first_press(world: World, task: PushButtons, change: Callable[[], None]) -> None:
    """Make ``change`` once, at the physics step after the task's first press; ``world.pending_events`` holds it
    too, so that a preview of the scene (``start_views``) can show it."""
    made = []

    def make() -> None:
        if not made:
            made.append(True)
            change()

    world.step_callbacks.append(lambda w: make() if task.pressed_order else None)
    world.pending_events.append(make)


def _moved_target(world, task, variation, rng) -> dict:
    point = task.free_button_place(rng) if len(variation.words) > 1 else None
    if point is None:
        return {"moved": None}
    colour = variation.words[1]
    after_first_press(world, task, lambda: task.move_button(world, colour, point))
    return {"moved": colour, "to": _rgb(point)}


def _same_colour(world, task, variation, rng) -> dict:
    others = [c for c in task.buttons if c not in variation.words]
    if len(variation.words) < 2 or not others:
        return {"repainted": None}
    colour, pressed = others[rng.integers(len(others))], variation.words[0]
    after_first_press(world, task, lambda: task.paint_button(world, colour, pressed))
    return {"repainted": colour, "as": pressed}


PERTURBATIONS: dict[str, Perturbation] = {perturbation.name: perturbation for perturbation in (
    Perturbation("lighting", "the light's direction, colour and strength", _lighting),
    Perturbation("table_colour", "the table top's colour", _table_colour),
    Perturbation("table_texture", "a procedural texture on the table top", _table_texture),
    Perturbation("object_shade", "the task objects' colours lightened or darkened by 8-18 %", _object_shade),
    Perturbation("distractors", "2-4 other objects on free places of the table", _distractors),
    Perturbation("camera_pose", "the shoulder cameras moved by up to 4 cm and re-aimed", _camera_pose),
    Perturbation("occluder", "a hand-sized object between a shoulder camera and the workspace", _occluder),
    Perturbation("lookalike", "a copy of the first instructed object's look elsewhere on the table", _lookalike,
                 _lookalike_refusal),
    Perturbation("object_size", "the task objects 12-25 % smaller or larger", _object_size, _resizable_refusal,
                 "shape"),
    Perturbation("taller_button", "the buttons' housings 2.5-4 times as tall", _taller_button, _buttons_refusal,
                 "shape"),
    Perturbation("moved_target", "after the first press, the next instructed button moves", _moved_target,
                 _presses_refusal, "event"),
    Perturbation("same_colour", "after the first press, an uninstructed button takes the pressed one's colour",
                 _same_colour, _presses_refusal, "event"),
)}


GROUPS = ("all", "visual", "shape", "event")  # names for several factors: every one, or those of a kind


def parse_perturbations(text: str | None, task: Task | None = None) -> tuple[str, ...]:
    """``"lighting,distractors"`` → ``("lighting", "distractors")``; a group alone (``all``, or a kind: ``visual``,
    ``shape``, ``event``) names its factors that apply to ``task``. Raises ``ValueError`` naming an unknown factor,
    a repeated one, or one the task refuses."""
    if not text:
        return ()
    names = [n.strip() for n in text.split(",") if n.strip()]
    if len(names) == 1 and names[0] in GROUPS:
        group = [n for n, f in PERTURBATIONS.items() if names[0] in ("all", f.kind)]
        accepted = tuple(n for n in group if task is None or PERTURBATIONS[n].refusal(task) is None)
        if not accepted:
            raise ValueError(f"no {names[0]} perturbation ({', '.join(group)}) applies to {task.name}")
        return accepted
    for name in names:
        if name not in PERTURBATIONS:
            raise ValueError(f"unknown perturbation {name!r}; accepted: {', '.join(PERTURBATIONS)}, "
                             f"or one of {', '.join(GROUPS)} alone")
        if names.count(name) > 1:
            raise ValueError(f"perturbation {name!r} is named twice")
        reason = PERTURBATIONS[name].refusal(task) if task is not None else None
        if reason:
            raise ValueError(f"perturbation {name!r} does not apply to {task.name}: {reason}")
    return tuple(names)


def apply_perturbations(world: World, task: Task, variation: Variation, seed: int, names,
                        before_build: bool = False) -> dict:
    """Apply the named perturbations, each from its own stream of ``seed``: ``{name: the parameters drawn}``, in
    the order given. ``before_build``: the "shape" factors among them, to the task before its scene is built;
    else the others, to the built scene."""
    drawn = {}
    for name in names:
        if (PERTURBATIONS[name].kind == "shape") == before_build:
            rng = np.random.default_rng([PERTURBATION_STREAM, seed, zlib.crc32(name.encode())])
            drawn[name] = PERTURBATIONS[name].apply(world, task, variation, rng)
    return drawn


DEFAULT_PROBABILITY = 0.5


def parse_perturb_option(text: str, task: Task | None = None) -> dict[str, float]:
    """``generate --perturb``: ``"lighting=0.3,distractors"`` → ``{"lighting": 0.3, "distractors": 0.5}`` (each
    factor's probability, ``DEFAULT_PROBABILITY`` when not given; a group, e.g. ``all`` or ``visual=P``: its
    factors that apply to ``task``). Raises ``ValueError`` as ``parse_perturbations`` does, or for a probability
    outside 0-1."""
    probabilities = {}
    for item in (i.strip() for i in text.split(",") if i.strip()):
        name, _, value = item.partition("=")
        try:
            probability = float(value) if value else DEFAULT_PROBABILITY
        except ValueError:
            raise ValueError(f"perturbation probability {value!r} of {name!r} is not a number; accepted: 0 to 1") from None
        if not 0 <= probability <= 1:
            raise ValueError(f"perturbation probability {value} of {name!r} is out of range; accepted: 0 to 1")
        for factor in parse_perturbations(name.strip(), task):
            if factor in probabilities:
                raise ValueError(f"perturbation {factor!r} is named twice")
            probabilities[factor] = probability
    return probabilities


def perturbation_option(probabilities: dict[str, float]) -> str:
    """The ``--perturb`` text of ``{factor: probability}`` (``parse_perturb_option``'s inverse)."""
    return ",".join(f"{name}={probability:g}" for name, probability in probabilities.items())


def drawn_perturbations(probabilities: dict[str, float], seed: int) -> tuple[str, ...]:
    """The factors one generated episode gets (domain randomisation): each independently with its probability,
    drawn from the episode seed (one draw per known factor, so a factor's draw does not depend on the others)."""
    draws = dict(zip(PERTURBATIONS, np.random.default_rng([PERTURBATION_STREAM, seed, 1]).random(len(PERTURBATIONS))))
    return tuple(name for name, probability in probabilities.items() if draws[name] < probability)

