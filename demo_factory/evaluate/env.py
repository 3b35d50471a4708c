"""A keyframe environment: one action = one predicted keyframe, executed as in the HiveFormer paper.

The same class serves ``demo-factory eval`` and ``lerobot-eval`` (through ``lerobot_env``). Each
step takes ``[x, y, z, qx, qy, qz, qw, open]``, reaches the pose with the seeded OMPL planner (or a
straight line for a short move into or out of contact), actuates the gripper if its command
changed, and observes the scene exactly as the recorder does for a dataset keyframe.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from demo_factory.convert.features import calibration_key, depth_key, image_key, observation_item
from demo_factory.execution import KeyframeExecutor
from demo_factory.generate import SETTLE_BEFORE_STEPS, observe
from demo_factory.planning import JointPlanner
from demo_factory.sim import DEFAULT_CAMERAS, Kinematics, World
from demo_factory.sim.world import HOME
from demo_factory.tasks import get_task

DEFAULT_STEP_SLACK = 2
SUCCESS_CHECK_STEPS = 60  # physics steps of rest before each success check ("stable for a moment")
EVAL_SEED_TAG = 0xE7A1  # keeps evaluation seeds apart from generation seeds (different entropy)


def evaluation_seed(base_seed: int, task: str, split: str, index: int) -> int:
    """The scene seed of the ``index``-th evaluation episode of a split (never a generation seed)."""
    entropy = [EVAL_SEED_TAG, base_seed, zlib.crc32(task.encode()), zlib.crc32(split.encode()), index]
    return int(np.random.SeedSequence(entropy).generate_state(1)[0])


@dataclass(frozen=True)
class EvalEpisode:
    """What one evaluation rollout is: a variation, its instruction and a fresh scene seed."""

    task: str
    split: str
    variation_id: int
    instruction: str
    seed: int


def gym_observation(frame) -> dict:
    """A frame in gym form: RGB and packed depth as uint8 ``pixels``, ``agent_pos`` (the state) and
    ``environment_state`` (the cameras' calibration vectors, concatenated in camera order)."""
    cameras = list(frame.cameras)
    item = observation_item(frame, cameras)
    pixels = {}
    for camera in cameras:
        pixels[camera] = item[image_key(camera)]
        pixels[f"{camera}_depth"] = item[depth_key(camera)]
    return {"pixels": pixels, "agent_pos": item["observation.state"],
            "environment_state": np.concatenate([item[calibration_key(c)] for c in cameras])}


class KeyframeEnv(gym.Env):
    """One task, episodes chosen at ``reset`` (``options={"episode": EvalEpisode}``) or cycled."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 1}

    def __init__(self, task: str, episodes: list[EvalEpisode] | None = None, image_size=(128, 128),
                 step_slack: int = DEFAULT_STEP_SLACK, split: str = "test", base_seed: int = 0):
        self.task_name = task
        self.image_size = tuple(image_size)
        self.step_slack = step_slack
        self._episodes = episodes or default_episodes(task, split, 100, base_seed)
        self._next = 0
        self.world: World | None = None
        self.kinematics = Kinematics()
        self.planner = JointPlanner()
        height, width = self.image_size
        image = gym.spaces.Box(0, 255, (height, width, 3), np.uint8)
        pixels = {c.name: image for c in DEFAULT_CAMERAS} | {f"{c.name}_depth": image for c in DEFAULT_CAMERAS}
        self.observation_space = gym.spaces.Dict({
            "pixels": gym.spaces.Dict(pixels),
            "agent_pos": gym.spaces.Box(-np.inf, np.inf, (15,), np.float32),
            "environment_state": gym.spaces.Box(-np.inf, np.inf, (20 * len(DEFAULT_CAMERAS),), np.float32),
        })
        self.action_space = gym.spaces.Box(-np.inf, np.inf, (8,), np.float32)
        self._max_episode_steps = 3 * 8 + step_slack  # the longest expert (tower x3) plus slack
        self.episode: EvalEpisode | None = None
        self.task_description = ""

    # -- gym API --------------------------------------------------------------------------
    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        options = options or {}
        episode = options.get("episode")
        if episode is None:
            episode = self._episodes[self._next % len(self._episodes)]
            self._next += 1
        self.episode = episode
        self.task_description = episode.instruction
        self._close_world()
        task = get_task(episode.task)
        world = World(DEFAULT_CAMERAS, self.image_size)
        world.reset_arm(HOME, gripper_open=1.0 if task.gripper_starts_open else 0.0)
        task.build_scene(world, task.variation(episode.variation_id), np.random.default_rng(episode.seed))
        world.step(SETTLE_BEFORE_STEPS)
        world.step_count = 0
        world.step_callbacks.append(task.on_step)
        self.world, self.sim_task = world, task
        self.expert_keyframes = task.expert(world)
        self.step_limit = len(self.expert_keyframes) + self.step_slack
        self.steps = 0
        self.executor = KeyframeExecutor(world, self.kinematics, self.planner, episode.seed, task.graspable_bodies())
        self.frame = observe(world, 0, is_keyframe=True, is_dense=False)
        return gym_observation(self.frame), self._info(False, None)

    def step(self, action):
        action = np.asarray(action, dtype=np.float64).reshape(-1)
        self.steps += 1
        outcome = self.executor.execute_predicted(action[:7], action[7], transition=self.steps)
        reason = None if outcome.ok else outcome.reason
        success = False
        if outcome.ok:
            self.world.step(SUCCESS_CHECK_STEPS)
            success = self.sim_task.success(self.world)
        self.frame = observe(self.world, self.steps, is_keyframe=True, is_dense=False)
        terminated = success or reason is not None
        truncated = not terminated and self.steps >= self.step_limit
        if truncated:
            reason = "step_limit"
        self.last_plan = outcome.plan
        return gym_observation(self.frame), float(success), terminated, truncated, self._info(success, reason)

    def render(self):
        return self.frame.cameras[DEFAULT_CAMERAS[0].name].rgb if self.world is not None else None

    def close(self):
        self._close_world()

    # -- helpers --------------------------------------------------------------------------
    def _info(self, success: bool, reason: str | None) -> dict:
        return {"is_success": success, "failure_reason": reason or "", "steps": self.steps}

    def _close_world(self):
        if self.world is not None:
            self.world.close()
            self.world = None


def default_episodes(task: str, split: str, count: int, base_seed: int = 0) -> list[EvalEpisode]:
    """Episodes over a task split's variations with their synthetic instructions (cycling)."""
    task_ = get_task(task)
    variations = task_.split_variations(split)
    episodes = []
    for i in range(count):
        variation = variations[i % len(variations)]
        seed = evaluation_seed(base_seed, task, split, i)
        episodes.append(EvalEpisode(task, split, variation.id, task_.instruction(variation, seed), seed))
    return episodes


