"""A new multi-variation task is one class and one registry entry: generation, the instruction-collection
pictures and the expert's closed-loop evaluation run on it with no task-specific code elsewhere."""

import numpy as np
import pytest

from demo_factory.collect.pictures import pictures_for, render_variation
from demo_factory.evaluate.env import KeyframeEnv, default_episodes
from demo_factory.evaluate.policies import ExpertPolicy
from demo_factory.evaluate.runner import evaluate_episode
from demo_factory.generate import GenerationJob, run_job
from demo_factory.record import read_episode
from demo_factory.tasks import TASKS, get_task, motions
from demo_factory.tasks.base import KeyframeTarget, Task, spread_positions
from demo_factory.tasks.objects import marker
from demo_factory.tasks.palette import TOWER_COLOURS, rgba
from demo_factory.tasks.variations import Variation

RADIUS = 0.025


class TouchSpheresInOrder(Task):
    """Throw-away task: touch coloured spheres in the instructed order (1 or 2 of 4 colours)."""

    name = "touch_spheres_in_order"
    description = "Touch the instructed coloured spheres in order."
    categories = ("rotation-invariant",)
    palette = TOWER_COLOURS[:4]
    max_sequence = 2
    n_train = n_test = 4
    split_seed = 7

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        names = " then the ".join(variation.words)
        return [f"touch the {names} sphere", f"reach the {names} ball", f"go to the {names} target"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        self.spheres = {}
        for colour, xy in zip(self.palette, spread_positions(rng, len(self.palette), ((0.35, 0.62), (-0.22, 0.22)), 0.12)):
            self.spheres[colour] = np.array([*xy, 0.15])
            marker(world, self.spheres[colour], RADIUS, rgba(colour))
        self.instructed = variation
        self.touched: list[str] = []

    def expert(self, world) -> list[KeyframeTarget]:
        return [k for colour in self.instructed.words for k in motions.reach(self.spheres[colour], motions.top_down(0.0))]

    def on_step(self, world) -> None:
        hand = world.gripper_pose()[:3]
        for colour, centre in self.spheres.items():
            if np.linalg.norm(hand - centre) < RADIUS and self.touched[-1:] != [colour]:
                self.touched.append(colour)

    def success(self, world) -> bool:
        return tuple(self.touched) == self.instructed.words

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        return [self.spheres[colour] for colour in variation.words]


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setitem(TASKS, TouchSpheresInOrder.name, TouchSpheresInOrder)
    return get_task(TouchSpheresInOrder.name)


@pytest.mark.slow
def test_a_registered_task_generates_shows_its_pictures_and_is_evaluated(registered, tmp_path):
    task = registered
    assert {len(v.words) for v in task.split_variations("train") + task.split_variations("test")} <= {1, 2}

    summary = run_job(GenerationJob(task=task.name, split="train", episodes=2, out=tmp_path / "raw", image_size=(32, 32)))
    assert summary["kept"] == 2, summary["failed"]
    recordings = sorted((tmp_path / "raw").glob("*.mcap"))
    assert len(recordings) == 2 and read_episode(recordings[0]).info.task == task.name

    variation = task.split_variations("test")[0]
    pictures = render_variation(task.name, variation.id)
    assert set(pictures) == {p.name for p in pictures_for(task)} and all(img.ndim == 3 for img in pictures.values())

    episodes = default_episodes(task.name, "test", 2)
    env = KeyframeEnv(task.name, episodes, image_size=(32, 32))
    records = [evaluate_episode(env, ExpertPolicy(), episode) for episode in episodes]
    env.close()
    assert [r["success"] for r in records] == [True, True]
