"""Joint-space motion planning: OMPL RRTConnect with up to 10 attempts, each with its own seed.

Owns collision checking against a PyBullet world and the seeded attempts (`planner`). Reads the world's
robot and bodies (in a forked copy, never moving the caller's robot); writes nothing.
"""

from demo_factory.planning.planner import MAX_ATTEMPTS, CollisionChecker, JointPlanner, PlanResult, attempt_seed

__all__ = ["MAX_ATTEMPTS", "CollisionChecker", "JointPlanner", "PlanResult", "attempt_seed"]
