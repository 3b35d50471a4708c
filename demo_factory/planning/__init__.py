"""Joint-space motion planning (OMPL) with per-attempt seeds."""

from demo_factory.planning.planner import MAX_ATTEMPTS, CollisionChecker, JointPlanner, PlanResult, attempt_seed

__all__ = ["MAX_ATTEMPTS", "CollisionChecker", "JointPlanner", "PlanResult", "attempt_seed"]
