"""Rollouts: starting a task's scene, observing it and executing keyframes in it.

Owns the one sequence every episode starts with (`start_scene`), the recorded observation (`observe`)
and keyframe execution (`KeyframeExecutor`: planned moves with the seeded OMPL planner, straight moves,
the gripper), so that generation, evaluation, the instruction-collection pictures and the tests run
episodes the same way. Reads tasks (`demo_factory.tasks`), drives the simulator (`demo_factory.sim`) and
the planner (`demo_factory.planning`); writes nothing (recording is the caller's).
"""

from demo_factory.rollout.execution import KeyframeExecutor, TransitionOutcome
from demo_factory.rollout.scene import (
    SETTLE_AFTER_STEPS,
    SETTLE_BEFORE_STEPS,
    ExpertKeyframes,
    observe,
    start_scene,
    start_views,
)

__all__ = ["SETTLE_AFTER_STEPS", "SETTLE_BEFORE_STEPS", "ExpertKeyframes", "KeyframeExecutor", "TransitionOutcome",
           "observe", "start_scene", "start_views"]
