"""Push buttons: press coloured buttons in the instructed order (HiveFormer's multi-variation task)."""

from __future__ import annotations

import itertools

import numpy as np
import pybullet as p

from demo_factory.sim.world import TOP_DOWN
from demo_factory.tasks import motions
from demo_factory.tasks.base import Failure, KeyframeTarget, Task, spread_positions
from demo_factory.tasks.grammar import Frames, listed, phrasings, pick
from demo_factory.tasks.palette import PUSH_BUTTON_COLOURS, rgba
from demo_factory.tasks.variations import PaperNumbering, Variation

N_BUTTONS = 3
BASE_HALF = (0.035, 0.035, 0.01)  # grey housing on the table
CAP_RADIUS, CAP_HALF_HEIGHT = 0.02, 0.008
TRAVEL = 0.012  # how far the cap can be pushed in
# Cap displacement that counts as a press: 3 mm, as RLBench's push_buttons (JointCondition 0.003 m);
# the expert pushes 9 mm, so a policy's press may land up to 6 mm high.
PRESSED_AT = -0.003
PRESS_DEPTH = 0.009  # how far the expert pushes the cap
TOUCHED_AT = 0.001  # cap travel (m) from which a press that did not count is "too shallow"
APPROACH_HEIGHT = 0.06  # above the cap, before pressing and after
WORKSPACE = ((0.38, 0.62), (-0.22, 0.22))  # x and y ranges of button centres
MIN_SPACING = 0.12
# A pressed cap turns lime and stays lime for the rest of the episode, as in the authors' push_buttons3 (its
# `step` colours a button's top plate and wrap green once its joint condition holds; nothing resets it): the
# scene shows which buttons are done. Without it, only the history tells, and policies press the first
# instructed button again at the third press (docs/reference/unseen.md). Lime is not in the palette, so never a
# button.
PRESSED_RGBA = rgba("lime")
KEYFRAMES_PER_PRESS = 3  # over the cap, pressed, over it again (motions.press)


def _sequence_text(colours: tuple[str, ...], fmt: str, then: str, last_then: str | None = None) -> str:
    parts = [fmt.format(c) for c in colours]
    if len(parts) == 1:
        return parts[0]
    last_then = last_then or then
    return then.join(parts[:-1]) + last_then + parts[-1]


PARAPHRASES = 40  # sentences a variation for training (``Task.paraphrases``), the templates among them
VERBS = ("press", "push", "hit", "tap", "press down", "push down on", "tap on")
VERBS_IT = ("press", "push", "hit", "tap", "push down on", "tap on")  # before "it"


def _button(name: str, rng: np.random.Generator, first: bool = True) -> str:
    """One button, as people name it: "the navy button", "the navy one" (after the first), "the navy", "navy"."""
    return pick(rng, ("the {} button", "the {} button", "the {}", "{}") + (() if first else ("the {} one",))).format(name)


def _frames(colours: tuple[str, ...]) -> Frames:
    """The sentence frames of one variation: ``name`` gives a colour's name in this sentence."""
    head, rest = colours[0], colours[1:]

    def buttons(name, rng):
        return [_button(name(head), rng)] + [_button(name(c), rng, first=False) for c in rest]

    if not rest:
        return [
            lambda name, rng: f"{pick(rng, VERBS)} {_button(name(head), rng)}",
            lambda name, rng: f"{pick(rng, ('just', 'only'))} {pick(rng, VERBS)} {_button(name(head), rng)}",
            lambda name, rng: f"{pick(rng, ('find', 'go to'))} the {name(head)} button and {pick(rng, VERBS_IT)} it",
            lambda name, rng: f"{pick(rng, VERBS)} the button that is {name(head)}",
        ]
    return [
        lambda name, rng: f"{pick(rng, VERBS)} " + ", then ".join(buttons(name, rng)),
        lambda name, rng: f"{pick(rng, VERBS)} " + " and then ".join(buttons(name, rng)),
        lambda name, rng: ", then ".join(f"{pick(rng, VERBS)} {b}" for b in buttons(name, rng)),
        lambda name, rng: (lambda b: f"first {pick(rng, VERBS)} {b[0]}, " + "".join(f"next {x}, " for x in b[1:-1])
                           + f"and finally {b[-1]}")(buttons(name, rng)),
        lambda name, rng: f"{pick(rng, VERBS)} the {listed([name(c) for c in colours])} buttons "
                          + pick(rng, ("in that order", "in this order", "in that exact order", "one after the other")),
        lambda name, rng: (lambda b: f"start with {b[0]}, " + "".join(f"continue with {x}, " for x in b[1:-1])
                           + f"and finish with {b[-1]}")(buttons(name, rng)),
        lambda name, rng: (lambda b: f"{pick(rng, VERBS)} {b[0]} first, " + "".join(f"then {x}, " for x in b[1:-1])
                           + f"and {b[-1]} last")(buttons(name, rng)),
        lambda name, rng: (lambda b: f"{pick(rng, VERBS)} {b[0]} before {b[1]}"
                           + (f", and {b[2]} after that" if len(b) > 2 else ""))(buttons(name, rng)),
        lambda name, rng: (lambda b: f"{pick(rng, VERBS)} {b[0]}. " + ". ".join(
            f"{pick(rng, ('then', 'next', 'after that'))} {pick(rng, VERBS)} {x}" for x in b[1:]))(buttons(name, rng)),
        lambda name, rng: (lambda b: f"{pick(rng, VERBS)} {b[0]}, " + ", ".join(f"after that {x}" for x in b[1:]))(
            buttons(name, rng)),
        lambda name, rng: ", then ".join(f"go to the {name(c)} button and {pick(rng, VERBS_IT)} it" for c in colours),
    ]


# Phrasings no training source holds (`test_unseen_paraphrased`), written for this split: their words and shapes
# are none of the templates' or the grammar's (grammar.HELD_OUT_MARKERS).
HELD_OUT = {
    1: ("Only the {0} button needs to go down.", "Activate the {0} button, nothing more.",
        "The {0} one is the only button that matters here."),
    2: ("The {0} button comes first and the {1} one second.", "Activate {0}, followed by {1}.",
        "Depress the {0} button, and afterwards the {1} one.", "{0} and {1}, in sequence, each pressed once."),
    3: ("The {0} button comes first, the {1} one second and the {2} one third.",
        "Activate {0}, followed by {1}, followed by {2}.",
        "Depress the {0} button, afterwards the {1} one, and lastly the {2} one.",
        "{0}, {1}, {2}: in sequence, each pressed once.",
        "Wrap up with {2}, once {0} and then {1} have gone down."),
}


class PushButtons(Task):
    name = "push_buttons"
    description = "Push 1-3 of three coloured buttons in the instructed order."
    categories = ("planning", "rotation-invariant")
    palette = PUSH_BUTTON_COLOURS
    # The fork's 18 x 17 x 16 + 18 x 17 + 18 = 5220 sequences, every one of them: ids 0-5219.
    paper_numbering = PaperNumbering("push_buttons3", per_length=5220, total=5220)
    gripper_starts_open = False
    resizable = True
    housing_scale = 1.0  # the housings' height times this (the `taller_button` perturbation)

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        c = variation.words
        first, rest = c[0], c[1:]
        texts = [
            "push the " + _sequence_text(c, "{} button", ", then the "),
            "press the " + _sequence_text(c, "{} button", " and then the "),
            f"push the {first} button" + "".join(f", then push the {x} one" for x in rest),
        ]
        if len(c) > 1:
            texts.append("press the " + ", ".join(c[:-1]) + f" and {c[-1]} buttons in that order")
        else:
            texts.append(f"press down the {first} button")
        return texts

    def paraphrases(self, variation: Variation) -> list[str]:
        return phrasings(self.name, variation.words, _frames(variation.words), PARAPHRASES,
                         first=self.synthetic_instructions(variation))

    def held_out_phrasings(self, variation: Variation) -> list[str]:
        return [text[0].upper() + text[1:] for text in
                (frame.format(*variation.words) for frame in HELD_OUT[len(variation.words)])]

    def instruction_relabels(self, variation: Variation, scene: dict) -> list[tuple[Variation, int]]:
        """Every other order of 1-3 of the scene's buttons that starts as the instructed one: its expert
        presses the same buttons first, so the episode's keyframes of the presses they share (3 a press)
        demonstrate it too. For (green, rose) with a black button: (green), (green, black), (green, black,
        rose) for one press, (green, rose, black) for two."""
        words = variation.words
        relabels = []
        for length in range(1, min(N_BUTTONS, self.max_sequence) + 1):
            for sequence in itertools.permutations(scene.get("buttons", ()), length):
                shared = next((k for k, (a, b) in enumerate(zip(sequence, words)) if a != b), min(length, len(words)))
                if sequence != words and shared:
                    relabels.append((self.variation_of(sequence), KEYFRAMES_PER_PRESS * shared))
        return relabels

    # -- scene ----------------------------------------------------------------------------
    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        distractors = [x for x in self.palette if x not in variation.words]
        colours = list(variation.words) + list(rng.choice(distractors, N_BUTTONS - len(variation.words), replace=False))
        colours = [colours[i] for i in rng.permutation(N_BUTTONS)]
        positions = spread_positions(rng, N_BUTTONS, WORKSPACE, MIN_SPACING)
        self.world = world
        self.instructed = variation
        s = self.object_scale
        self.base_half = (BASE_HALF[0] * s, BASE_HALF[1] * s, BASE_HALF[2] * s * self.housing_scale)
        self.cap_size = (CAP_RADIUS * s, CAP_HALF_HEIGHT * s)
        self.buttons = {colour: _make_button(world, pos, colour, self.base_half, self.cap_size)
                        for colour, pos in zip(colours, positions)}
        self.positions = {colour: pos for colour, pos in zip(colours, positions)}
        self.pressed_order: list[str] = []
        self._down = {colour: False for colour in colours}
        self.deepest = {colour: 0.0 for colour in colours}  # each cap's deepest travel (m, >= 0)

    def cap_top(self, colour: str) -> np.ndarray:
        x, y = self.positions[colour]
        return np.array([x, y, 2 * self.base_half[2] + 2 * self.cap_size[1]])

    # -- the paper's real-robot situations (rollout.perturbations) --------------------------
    def free_button_place(self, rng: np.random.Generator, tries: int = 200) -> np.ndarray | None:
        """A point of the workspace at least MIN_SPACING from every button (where a button can move to)."""
        (x0, x1), (y0, y1) = WORKSPACE
        for _ in range(tries):
            point = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
            if all(np.linalg.norm(point - np.asarray(xy)) >= MIN_SPACING for xy in self.positions.values()):
                return point
        return None

    def move_button(self, world, colour: str, xy) -> None:
        """Put a button elsewhere on the table mid-episode; the expert's later presses follow it."""
        p.resetBasePositionAndOrientation(self.buttons[colour], (float(xy[0]), float(xy[1]), self.base_half[2]),
                                          (0, 0, 0, 1), physicsClientId=world.client)
        self.positions[colour] = np.asarray(xy, dtype=float)
        world.scene_changes += 1

    def paint_button(self, world, colour: str, as_colour: str) -> None:
        """Give a button's cap another button's colour (its name in the task stays ``colour``)."""
        p.changeVisualShape(self.buttons[colour], 0, rgbaColor=rgba(as_colour), physicsClientId=world.client)

    def expert(self, world) -> list[KeyframeTarget]:
        tip = world.fingertip_offset()
        keyframes = []
        for colour in self.instructed.words:
            keyframes += motions.press(self.cap_top(colour), TOP_DOWN, approach=APPROACH_HEIGHT + tip,
                                       depth=PRESS_DEPTH - tip)
        return keyframes

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Press a button the instruction does not start with."""
        tip = world.fingertip_offset()
        other = next(c for c in self.buttons if c != self.instructed.words[0])
        return motions.press(self.cap_top(other), TOP_DOWN, approach=APPROACH_HEIGHT + tip, depth=PRESS_DEPTH - tip)

    def on_step(self, world) -> None:
        for colour, body in self.buttons.items():
            position = p.getJointState(body, 0, physicsClientId=world.client)[0]
            down = position < PRESSED_AT
            if down and not self._down[colour]:
                if colour not in self.pressed_order:
                    p.changeVisualShape(body, 0, rgbaColor=PRESSED_RGBA, physicsClientId=world.client)
                self.pressed_order.append(colour)
            self._down[colour] = down
            self.deepest[colour] = max(self.deepest[colour], -position)

    def success(self, world) -> bool:
        return tuple(self.pressed_order) == self.instructed.words

    def failure(self, world) -> Failure | None:
        """"wrong button pressed" at the first press that leaves the instructed order; else "press too shallow"
        when the next instructed cap moved at least 1 mm without reaching the 3 mm of a press; else None."""
        words = self.instructed.words
        for k, colour in enumerate(self.pressed_order):
            if k >= len(words):
                return Failure("wrong button pressed", k + 1,
                               f"pressed {colour} after the instructed {len(words)} button(s)")
            if colour != words[k]:
                again = " again" if colour in self.pressed_order[:k] else ""
                return Failure("wrong button pressed", k + 1, f"pressed {colour}{again} where {words[k]} was next")
        k = len(self.pressed_order)
        if k < len(words):
            travel = self.deepest[words[k]]
            if TOUCHED_AT <= travel < -PRESSED_AT:
                return Failure("press too shallow", k + 1,
                               f"the {words[k]} cap moved {1000 * travel:.1f} mm, a press counts from "
                               f"{-1000 * PRESSED_AT:.0f} mm")
        return None

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        return [self.cap_top(colour) for colour in variation.words]

    def scene_facts(self) -> dict:
        return {
            "buttons": {c: [round(float(v), 6) for v in pos] for c, pos in self.positions.items()},
            "pressed_order": list(self.pressed_order),
        }



def _make_button(world, xy, colour: str, base_half=BASE_HALF, cap_size=(CAP_RADIUS, CAP_HALF_HEIGHT)) -> int:
    """A fixed housing with a sprung cap on a prismatic joint; the cap is pressed when pushed in.
    ``base_half``: the housing's half extents; ``cap_size``: the cap's radius and half height."""
    client = world.client
    (radius, half_height) = cap_size
    base_col = p.createCollisionShape(p.GEOM_BOX, halfExtents=base_half, physicsClientId=client)
    base_vis = p.createVisualShape(p.GEOM_BOX, halfExtents=base_half, rgbaColor=(0.25, 0.25, 0.25, 1),
                                   physicsClientId=client)
    cap_col = p.createCollisionShape(p.GEOM_CYLINDER, radius=radius, height=2 * half_height, physicsClientId=client)
    cap_vis = p.createVisualShape(p.GEOM_CYLINDER, radius=radius, length=2 * half_height, rgbaColor=rgba(colour),
                                  physicsClientId=client)
    body = p.createMultiBody(
        baseMass=0, baseCollisionShapeIndex=base_col, baseVisualShapeIndex=base_vis,
        basePosition=(float(xy[0]), float(xy[1]), base_half[2]),
        linkMasses=[0.05], linkCollisionShapeIndices=[cap_col], linkVisualShapeIndices=[cap_vis],
        linkPositions=[(0, 0, base_half[2] + half_height)], linkOrientations=[(0, 0, 0, 1)],
        linkInertialFramePositions=[(0, 0, 0)], linkInertialFrameOrientations=[(0, 0, 0, 1)],
        linkParentIndices=[0], linkJointTypes=[p.JOINT_PRISMATIC], linkJointAxis=[(0, 0, 1)],
        physicsClientId=client,
    )
    p.changeDynamics(body, 0, jointLowerLimit=-TRAVEL, jointUpperLimit=0.0, physicsClientId=client)
    # The spring: a weak position motor pulling the cap back up.
    p.setJointMotorControl2(body, 0, p.POSITION_CONTROL, targetPosition=0.0, force=4.0, positionGain=0.2, physicsClientId=client)
    return body
