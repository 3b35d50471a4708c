"""demo-factory's environments for ``lerobot-eval``: gym ids and a LeRobot ``EnvConfig``.

    lerobot-eval --env.discover_packages_path=demo_factory.evaluate.lerobot_env \\
        --env.type=demo_factory --env.task=push_buttons --policy.path=... --eval.n_episodes=10 --eval.batch_size=1

``--env.action_space`` picks the environment: ``keyframe`` (default; one step = one predicted
keyframe, reached by planning) or, for policies trained on a dense export, ``joints`` / ``ee`` (one
step = one control tick at ``--env.fps``, at most ``--env.max_seconds`` of simulated time).

Importing this package (``--env.discover_packages_path`` needs a package) registers ``gym_demo_factory/<task>`` for every task and the ``demo_factory``
env type. Observations reach the policy the way ``lerobot-eval`` passes any gym observation:
``pixels`` → ``observation.images.<cam>`` (RGB) and ``observation.images.<cam>_depth`` (packed
depth), ``agent_pos`` → ``observation.state``, ``environment_state`` → the cameras' calibration
vectors concatenated in camera order. The env's pre-processor (``get_env_processors``:
``gym_layout.GymObservationLayoutStep``) maps that layout back to the dataset's (``observation.depth.<cam>``,
``observation.calibration.<cam>``) before the policy's pre-processor sees it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.processor import PolicyProcessorPipeline

from demo_factory.evaluate.env import DEFAULT_CONTROL_FPS, DEFAULT_DENSE_SECONDS, DEFAULT_STEP_SLACK, EVAL_ACTION_SPACES, control_period
from demo_factory.evaluate.gym_layout import GymObservationLayoutStep
from demo_factory.rollout.perturbations import parse_perturbations
from demo_factory.sim import CAMERA_NAMES
from demo_factory.tasks import TASKS, get_task

ENV_TYPE = "demo_factory"

for _task in TASKS:
    _id = f"gym_{ENV_TYPE}/{_task}"
    if _id not in gym.registry:
        gym.register(id=_id, entry_point="demo_factory.evaluate.env:make_env", kwargs={"task": _task})


def _features(height: int, width: int) -> dict[str, PolicyFeature]:
    features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(8,)),
                "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(15,)),
                "environment_state": PolicyFeature(type=FeatureType.ENV, shape=(20 * len(CAMERA_NAMES),))}
    for camera in CAMERA_NAMES:
        for key in (camera, f"{camera}_depth"):
            features[f"pixels/{key}"] = PolicyFeature(type=FeatureType.VISUAL, shape=(height, width, 3))
    return features


def _features_map() -> dict[str, str]:
    mapping = {"action": "action", "agent_pos": "observation.state", "environment_state": "observation.environment_state"}
    for camera in CAMERA_NAMES:
        mapping[f"pixels/{camera}"] = f"observation.images.{camera}"
        # lerobot-eval delivers it as observation.images.<cam>_depth; the env's processor maps it here.
        mapping[f"pixels/{camera}_depth"] = f"observation.depth.{camera}"
    return mapping


@EnvConfig.register_subclass(ENV_TYPE)
@dataclass
class DemoFactoryEnv(EnvConfig):
    """demo-factory's tasks: one step = one predicted keyframe ``[x, y, z, quat, open]`` (``action_space``
    keyframe) or one control tick of a dense policy (``joints`` or ``ee``, at ``fps``)."""

    task: str | None = "push_buttons"
    # keyframe: the next keyframe's pose + open; joints / ee: the next control tick's 7 joint positions or
    # grasp-frame pose, + gripper command (as in a dataset converted with --granularity dense --action-space)
    action_space: str = "keyframe"
    fps: int = DEFAULT_CONTROL_FPS  # dense: control ticks per second (the dense export's fps)
    max_seconds: float = DEFAULT_DENSE_SECONDS  # dense: simulated seconds before an episode counts as failed
    split: str = "test"  # variations: "train" (seen) or "test" (unseen), with synthetic instructions
    image_height: int = 128
    image_width: int = 128
    step_slack: int = DEFAULT_STEP_SLACK  # steps allowed beyond the expert's keyframe count
    base_seed: int = 0  # evaluation scene seeds derive from it (never a generation seed)
    # A converted dataset (its folder of splits): the episodes are its `split`'s variations and instructions of
    # `task`, as `demo-factory eval --dataset` draws them; a multi-task checkpoint is evaluated on the variations
    # it trained on. Empty: every variation of the task's split.
    dataset: str = ""
    # Perturbations of every episode's scene, comma-separated (`demo_factory.rollout.perturbations`; "": none).
    perturb: str = ""
    features: dict[str, PolicyFeature] = field(default_factory=lambda: _features(128, 128))
    features_map: dict[str, str] = field(default_factory=_features_map)

    def __post_init__(self):
        if self.task not in TASKS:
            raise ValueError(f"unknown task {self.task!r}; accepted: {', '.join(TASKS)}")
        if self.action_space not in EVAL_ACTION_SPACES:
            raise ValueError(f"unknown action_space {self.action_space!r}; accepted: {', '.join(EVAL_ACTION_SPACES)}")
        control_period(self.fps)
        self.features = _features(self.image_height, self.image_width)
        self._perturb = parse_perturbations(self.perturb, get_task(self.task))
        self._dataset_episodes = self.dataset_episodes()  # read once: gym_kwargs hands them to every env made
        if self.dataset and not self._dataset_episodes:
            raise ValueError(f"dataset {self.dataset!r} holds no {self.task} episode in its {self.split!r} split")

    def dataset_episodes(self) -> list:
        """The dataset's evaluation episodes of this task (100, cycling its variations), or [] without a dataset."""
        if not self.dataset:
            return []
        from demo_factory.evaluate.runner import split_episodes

        split = Path(self.dataset) / self.split
        if not (split / "meta" / "info.json").is_file():
            raise ValueError(f"dataset {self.dataset!r} has no converted {self.split!r} split")
        return [e for e in split_episodes(split, self.split, 100, self.base_seed) if e.task == self.task]

    @property
    def gym_kwargs(self) -> dict:
        return {"split": self.split, "image_size": (self.image_height, self.image_width),
                "step_slack": self.step_slack, "base_seed": self.base_seed, "action_space": self.action_space,
                "fps": self.fps, "max_seconds": self.max_seconds, "perturb": self._perturb,
                **({"episodes": self._dataset_episodes} if self.dataset else {})}

    def get_env_processors(self):
        """(pre-processor, post-processor) of this env's observations and actions: the gym layout decoded back to
        the dataset's features; actions unchanged."""
        return (PolicyProcessorPipeline(steps=[GymObservationLayoutStep(cameras=list(CAMERA_NAMES))]),
                PolicyProcessorPipeline(steps=[]))
