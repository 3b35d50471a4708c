"""Evaluation environments: keyframe policies (HiveFormer) and dense policies (ACT, diffusion, VLAs).

The same classes serve ``demo-factory eval`` and ``lerobot-eval`` (through ``lerobot_env``); both
build each episode's scene from its variation and evaluation seed and end on the task's own success
check.

- ``KeyframeEnv``: one action = one predicted keyframe ``[x, y, z, qx, qy, qz, qw, open]``, executed as
  in the HiveFormer paper: the pose is reached with the seeded OMPL planner (or a straight line for a
  short move into or out of contact), then the gripper is actuated if its command changed.
- ``DenseEnv``: one action per control tick (``fps``), in the action space of a dense export:
  ``joints`` = 7 joint positions + gripper command, ``ee`` = grasp-frame pose + gripper command (inverse
  kinematics gives the joint targets). The joints' position controllers track a straight line from
  the current joint positions to the target over the tick, as the expert's own moves are tracked.

Both observe the scene exactly as the recorder does for a dataset frame.

Failure reasons: every failed episode gets exactly one ``info["failure_reason"]`` (so the counts add up to
the failures), decided when it ends: the task's own (``Task.failure``: "wrong button pressed", "press too
shallow", "grasp missed", "cube dropped", ...) when it reports one, else the execution's (a keyframe that
could not be reached: "unreachable pose", "planning failed", "straight-line move failed"), else "step limit".
``info["failure_subgoal"]`` (the 1-based instructed sub-goal where it went wrong, or None) and
``info["failure_detail"]`` (a sentence) come with the task's reason.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, replace

import gymnasium as gym
import numpy as np

from demo_factory.convert.features import (
    ACTION_SIZE,
    ACTION_SPACES,
    CALIBRATION_SIZE,
    DEFAULT_CONTROL_FPS,
    STATE_SIZE,
    calibration_key,
    image_key,
    observation_item,
    pack_depth,
)
from demo_factory.planning import JointPlanner
from demo_factory.sim import DEFAULT_CAMERAS, Kinematics, World
from demo_factory.sim.world import JOINT_LOWER, JOINT_UPPER, TIME_STEP
from demo_factory.rollout import ExpertKeyframes, KeyframeExecutor, observe, start_scene
from demo_factory.tasks import get_task

DEFAULT_STEP_SLACK = 2
KEYFRAME = "keyframe"  # the action space of keyframe policies; dense ones use ACTION_SPACES
EVAL_ACTION_SPACES = (KEYFRAME, *ACTION_SPACES)
DEFAULT_DENSE_SECONDS = 60.0  # a dense episode's time limit when no dataset tells the experts' durations
SUCCESS_CHECK_STEPS = 60  # physics steps of rest before each success check ("stable for a moment")
EVAL_SEED_TAG = 0xE7A1  # keeps evaluation seeds apart from generation seeds (different entropy)


# The executor's reasons (``TransitionOutcome.reason``) and the step limit, in words.
EXECUTION_REASONS = {
    "unreachable": "unreachable pose",  # no inverse-kinematics solution for the predicted pose
    "planning": "planning failed",  # OMPL found no collision-free path to it
    "cartesian": "straight-line move failed",  # a short contact move with no IK solution or a joint jump on the line
}
STEP_LIMIT = "step limit"


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
    perturbations: tuple[str, ...] = ()  # factors of `rollout.perturbations` applied to the scene


def gym_observation(frame) -> dict:
    """A frame in gym form: RGB and depth as uint8 ``pixels`` (a gym image must be uint8: depth packed,
    ``pack_depth``), ``agent_pos`` (the state) and ``environment_state`` (the cameras' calibration
    vectors, concatenated in camera order)."""
    cameras = list(frame.cameras)
    item = observation_item(frame, cameras)
    pixels = {}
    for camera in cameras:
        pixels[camera] = item[image_key(camera)]
        pixels[f"{camera}_depth"] = pack_depth(frame.cameras[camera].depth)
    return {"pixels": pixels, "agent_pos": item["observation.state"],
            "environment_state": np.concatenate([item[calibration_key(c)] for c in cameras])}


def episode_world(episode: EvalEpisode, image_size) -> tuple[World, object]:
    """The scene of an evaluation episode at rest, its clock at 0, as the generator builds it: (world, task)."""
    task = get_task(episode.task)
    return start_scene(task, task.variation(episode.variation_id), episode.seed, DEFAULT_CAMERAS, image_size,
                       episode.perturbations), task


class _TaskEnv(gym.Env):
    """What both environments share: spaces, episodes chosen at ``reset`` (``options={"episode":
    EvalEpisode}``) or cycled, the scene, the observation."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 1}
    action_space_name = KEYFRAME

    def __init__(self, task: str, episodes: list[EvalEpisode] | None = None, image_size=(128, 128),
                 split: str = "test", base_seed: int = 0):
        self.task_name = task
        self.image_size = tuple(image_size)
        self._episodes = episodes or default_episodes(task, split, 100, base_seed)
        self._next = 0
        self.world: World | None = None
        self.kinematics = Kinematics()
        height, width = self.image_size
        image = gym.spaces.Box(0, 255, (height, width, 3), np.uint8)
        pixels = {c.name: image for c in DEFAULT_CAMERAS} | {f"{c.name}_depth": image for c in DEFAULT_CAMERAS}
        self.observation_space = gym.spaces.Dict({
            "pixels": gym.spaces.Dict(pixels),
            "agent_pos": gym.spaces.Box(-np.inf, np.inf, (STATE_SIZE,), np.float32),
            "environment_state": gym.spaces.Box(-np.inf, np.inf, (CALIBRATION_SIZE * len(DEFAULT_CAMERAS),), np.float32),
        })
        self.action_space = gym.spaces.Box(-np.inf, np.inf, (ACTION_SIZE,), np.float32)
        self.episode: EvalEpisode | None = None
        self.task_description = ""
        self.perturb: tuple[str, ...] = ()  # perturbations for episodes that name none (`make_env`)

    def _start(self, seed, options) -> None:
        super().reset(seed=seed)
        episode = (options or {}).get("episode")
        if episode is None:
            episode = self._episodes[self._next % len(self._episodes)]
            self._next += 1
        if self.perturb and not episode.perturbations:
            episode = replace(episode, perturbations=self.perturb)
        self.episode = episode
        self.task_description = episode.instruction
        self._close_world()
        self.world, self.sim_task = episode_world(episode, self.image_size)
        self.expert_keyframes = ExpertKeyframes(self.sim_task, self.world)
        self.steps = 0

    def render(self):
        return self.frame.cameras[DEFAULT_CAMERAS[0].name].rgb if self.world is not None else None

    def close(self):
        self._close_world()

    def _info(self, success: bool, ended: bool = False, execution_reason: str | None = None) -> dict:
        """The step's info; an episode that ``ended`` without success gets its failure reason (module docstring)."""
        reason, subgoal, detail = "", None, ""
        if ended and not success:
            failure = self.sim_task.failure(self.world)
            if failure is not None:
                reason, subgoal, detail = failure.reason, failure.subgoal, failure.detail
            elif execution_reason is not None:
                reason = EXECUTION_REASONS.get(execution_reason, execution_reason)
            else:
                reason = STEP_LIMIT
        return {"is_success": success, "failure_reason": reason, "failure_subgoal": subgoal,
                "failure_detail": detail, "steps": self.steps}

    def _close_world(self):
        if self.world is not None:
            self.world.close()
            self.world = None


class KeyframeEnv(_TaskEnv):
    """One step = one predicted keyframe, reached by planning (see the module docstring)."""

    def __init__(self, task: str, episodes: list[EvalEpisode] | None = None, image_size=(128, 128),
                 step_slack: int = DEFAULT_STEP_SLACK, split: str = "test", base_seed: int = 0):
        super().__init__(task, episodes, image_size, split, base_seed)
        self.step_slack = step_slack
        self.planner = JointPlanner()
        self._max_episode_steps = 3 * 8 + step_slack  # the longest expert (stack_blocks: 3 blocks x 8) plus slack

    # -- gym API --------------------------------------------------------------------------
    def reset(self, *, seed=None, options=None):
        self._start(seed, options)
        world = self.world
        self.step_limit = len(self.expert_keyframes) + self.step_slack
        self.executor = KeyframeExecutor(world, self.kinematics, self.planner, self.episode.seed,
                                         self.sim_task.graspable_bodies())
        self.frame = observe(world, 0, is_keyframe=True, is_dense=False)
        return gym_observation(self.frame), self._info(False)

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
        self.last_plan = outcome.plan
        info = self._info(success, terminated or truncated, reason)
        return gym_observation(self.frame), float(success), terminated, truncated, info


def control_period(fps: float) -> int:
    """Physics steps (1/240 s) per control tick; the rate must divide 240 as the recorder's does."""
    period = 240 / fps
    if fps <= 0 or abs(period - round(period)) > 1e-6:
        raise ValueError(f"control rate {fps:g} fps does not divide the 240 Hz physics rate; accepted: 240 / k "
                         "fps for a whole k, e.g. 10, 20, 30")
    return int(round(period))


class DenseEnv(_TaskEnv):
    """One step = one control tick of ``1 / fps`` s with a ``joints`` or ``ee`` action (module docstring).

    Success is the task's own check, holding for ``SUCCESS_CHECK_STEPS`` physics steps (as the keyframe
    environment lets the scene rest that long before it checks). An episode ends on success or after
    ``max_seconds`` of simulated time. An ``ee`` target that inverse kinematics cannot reach leaves the
    joint targets as they were (counted in ``info["unreachable_ticks"]``).
    """

    def __init__(self, task: str, episodes: list[EvalEpisode] | None = None, image_size=(128, 128),
                 action_space: str = "joints", fps: float = DEFAULT_CONTROL_FPS,
                 max_seconds: float = DEFAULT_DENSE_SECONDS, split: str = "test", base_seed: int = 0):
        if action_space not in ACTION_SPACES:
            raise ValueError(f"unknown action space {action_space!r}; accepted: {', '.join(ACTION_SPACES)}")
        super().__init__(task, episodes, image_size, split, base_seed)
        self.action_space_name = action_space
        self.fps = fps
        self.period = control_period(fps)
        self.step_limit = max(1, int(np.ceil(max_seconds * fps)))
        self._max_episode_steps = self.step_limit
        self.metadata = {**self.metadata, "render_fps": fps}

    def reset(self, *, seed=None, options=None):
        self._start(seed, options)
        self.target = self.world.joint_positions()
        self.success_steps = 0
        self.unreachable_ticks = 0
        self.frame = observe(self.world, 0, is_keyframe=False, is_dense=True)
        return gym_observation(self.frame), self._info(False)

    def joint_target(self, action: np.ndarray) -> np.ndarray | None:
        """The arm joint target of an action (None: an ``ee`` pose that inverse kinematics cannot reach)."""
        if self.action_space_name == "joints":
            return np.clip(action[:7], JOINT_LOWER, JOINT_UPPER)
        pose = action[:7].copy()
        pose[3:] /= np.linalg.norm(pose[3:]) or 1.0
        return self.kinematics.inverse(pose, seed=self.world.joint_positions())

    def step(self, action):
        action = np.asarray(action, dtype=np.float64).reshape(-1)
        self.steps += 1
        world = self.world
        target = self.joint_target(action)
        if target is None:
            self.unreachable_ticks += 1
            target = self.target
        self.target = target
        gripper_open = float(action[7] >= 0.5)
        if gripper_open != world.gripper_command:
            world.set_gripper(gripper_open)
        start = world.joint_positions()
        velocity = (target - start) / (self.period * TIME_STEP)
        for i in range(1, self.period + 1):
            world.command_arm(start + (target - start) * (i / self.period), velocity)
            world.step()
        self.success_steps = self.success_steps + self.period if self.sim_task.success(world) else 0
        success = self.success_steps >= SUCCESS_CHECK_STEPS
        self.frame = observe(world, 0, is_keyframe=False, is_dense=True)
        truncated = not success and self.steps >= self.step_limit
        return gym_observation(self.frame), float(success), success, truncated, self._info(success, truncated)

    def _info(self, success: bool, ended: bool = False, execution_reason: str | None = None) -> dict:
        return {**super()._info(success, ended, execution_reason),
                "unreachable_ticks": getattr(self, "unreachable_ticks", 0)}


def make_env(task: str, action_space: str = KEYFRAME, fps: float = DEFAULT_CONTROL_FPS,
             max_seconds: float = DEFAULT_DENSE_SECONDS, step_slack: int = DEFAULT_STEP_SLACK, perturb=(),
             **common) -> _TaskEnv:
    """The environment for a policy's action space: ``keyframe`` → ``KeyframeEnv``, ``joints`` / ``ee`` →
    ``DenseEnv`` (``common``: episodes, image_size, split, base_seed); ``perturb``: factors of
    `rollout.perturbations` for every episode that names none."""
    if action_space == KEYFRAME:
        env = KeyframeEnv(task, step_slack=step_slack, **common)
    elif action_space in ACTION_SPACES:
        env = DenseEnv(task, action_space=action_space, fps=fps, max_seconds=max_seconds, **common)
    else:
        raise ValueError(f"unknown action space {action_space!r}; accepted: {', '.join(EVAL_ACTION_SPACES)}")
    env.perturb = tuple(perturb)
    return env


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


