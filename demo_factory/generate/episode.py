"""One expert episode: scene → expert keyframes → planned execution in physics → MCAP.

An episode is fully determined by ``(task, variation, episode_seed)`` (plus the camera settings):
the same inputs give a byte-identical recording, in any process and in any order.
"""

from __future__ import annotations

import dataclasses
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from demo_factory.planning import JointPlanner
from demo_factory.record import FORMAT_VERSION, EpisodeInfo, EpisodeWriter, Keyframe, library_versions
from demo_factory.rollout import SETTLE_AFTER_STEPS, ExpertKeyframes, KeyframeExecutor, observe, start_scene
from demo_factory.sim import DEFAULT_CAMERAS, World
from demo_factory.sim.kinematics import shared_kinematics
from demo_factory.tasks import SPLITS, get_task


@dataclass(frozen=True)
class EpisodeRequest:
    """One episode to generate."""

    task: str
    split: str
    variation_id: int
    episode_seed: int
    image_size: tuple[int, int] = (128, 128)
    dense_fps: float = 0.0
    perturbations: tuple[str, ...] = ()  # the factors of `rollout.perturbations` this episode gets

    @property
    def filename(self) -> str:
        return f"{self.task}_{self.split}_var{self.variation_id:04d}_seed{self.episode_seed:010d}.mcap"


@dataclass
class EpisodeOutcome:
    """What came of one request (kept or failed, why, and how long it took)."""

    request: EpisodeRequest
    kept: bool
    reason: str | None  # failure reason: "planning", "unreachable", "cartesian", "task_failed"
    path: str | None
    keyframes: int
    attempts_per_transition: list[int] = field(default_factory=list)
    planning_seconds: list[float] = field(default_factory=list)  # wall-clock per planned transition
    seconds: float = 0.0
    attempt_log: list[dict] = field(default_factory=list)  # every planner attempt, with its solve time
    resumed: bool = False


def episode_seed(base_seed: int, task: str, split: str, index: int) -> int:
    """The seed of the ``index``-th episode of a job: a pure function of the job's parameters."""
    entropy = [base_seed, zlib.crc32(task.encode()), SPLITS.index(split), index]
    return int(np.random.SeedSequence(entropy).generate_state(1)[0])


def run_episode(request: EpisodeRequest, out_dir: str | Path | None) -> EpisodeOutcome:
    """Generate one episode; with ``out_dir`` record it there (kept only if the task succeeds)."""
    began = time.perf_counter()
    task = get_task(request.task)
    variation = task.variation(request.variation_id)
    instruction = task.instruction(variation, request.episode_seed)
    world = start_scene(task, variation, request.episode_seed, DEFAULT_CAMERAS, request.image_size,
                        request.perturbations)
    kinematics = shared_kinematics()
    writer = None
    try:
        info = EpisodeInfo(
            format_version=FORMAT_VERSION, task=task.name, split=request.split, variation_id=variation.id,
            variation=list(variation.words), episode_seed=request.episode_seed, instruction=instruction,
            cameras=[c.name for c in DEFAULT_CAMERAS], image_size=tuple(request.image_size),
            dense_fps=float(request.dense_fps), extra=task.scene_facts(), perturbations=world.perturbations,
        )
        if out_dir is not None:
            Path(out_dir).mkdir(parents=True, exist_ok=True)
            writer = EpisodeWriter(Path(out_dir) / request.filename, info)
        reached = {"index": 0, "last_step": -1}
        period = int(round(240 / request.dense_fps)) if request.dense_fps > 0 else 0

        def record_dense(w: World) -> None:
            if w.step_count % period == 0 and w.step_count != reached["last_step"]:
                writer.write_frame(observe(w, reached["index"], is_keyframe=False, is_dense=True))
                reached["last_step"] = w.step_count

        def record_keyframe(index: int, target_pose, gripper_open: float, motion: str) -> None:
            reached["index"] = index
            if writer is None:
                return
            dense = period > 0 and world.step_count % period == 0
            frame = observe(world, index, is_keyframe=True, is_dense=dense)
            writer.write_frame(frame)
            writer.write_keyframe(Keyframe(index, world.time_ns, np.asarray(target_pose), gripper_open,
                                           frame.robot.gripper_pose, motion))
            reached["last_step"] = world.step_count

        if writer is not None and period:
            world.step_callbacks.append(record_dense)
        start_pose = world.gripper_pose()
        record_keyframe(0, start_pose, world.gripper_command, "start")
        executor = KeyframeExecutor(world, kinematics, JointPlanner(), request.episode_seed, task.graspable_bodies())
        targets = ExpertKeyframes(task, world)
        attempts_log, attempt_log, attempts_used, planning_seconds = [], [], [], []
        reason = None
        for index, target in enumerate(targets, start=1):  # lazily: a keyframe is planned when it is reached
            outcome = executor.execute(target, transition=index)
            if outcome.plan is not None:
                attempts_log += outcome.plan.attempts
                attempt_log += [{**dataclasses.asdict(a), "solve_seconds": round(t, 4)}
                                for a, t in zip(outcome.plan.attempts, outcome.plan.solve_seconds)]
                attempts_used.append(len(outcome.plan.attempts))
                planning_seconds.append(sum(outcome.plan.solve_seconds))
            if not outcome.ok:
                reason = outcome.reason
                break
            record_keyframe(index, target.pose, target.gripper_open, target.motion)
        if reason is None:
            world.step(SETTLE_AFTER_STEPS)
            if not task.success(world):
                reason = "task_failed"
        path = None
        if writer is not None:
            if reason is None:
                path = str(writer.close(world.time_ns, True, attempts_log, library_versions()))
            else:
                writer.abort()
        return EpisodeOutcome(request, reason is None, reason, path, len(targets) + 1, attempts_used,
                              planning_seconds, time.perf_counter() - began, attempt_log)
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    finally:
        world.close()
