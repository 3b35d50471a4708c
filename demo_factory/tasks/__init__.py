"""Tasks: one module each, registered by name in ``registry`` (a new task is one module and one line).

A task owns its variations and splits (`variations`, the HiveFormer paper's numbering where it has one),
its instructions, its scene, its scripted expert (keyframes), its success check, and what the other stages
show of it (the goal for the collection pictures, a wrong action for the tests). Reads nothing; writes nothing.
"""

from demo_factory.tasks.base import KeyframeTarget, Task
from demo_factory.tasks.registry import INSTRUCTED_TASKS, MULTI_VARIATION_TASKS, TASKS, get_task
from demo_factory.tasks.variations import SPLITS, Variation

__all__ = ["INSTRUCTED_TASKS", "MULTI_VARIATION_TASKS", "SPLITS", "TASKS", "KeyframeTarget", "Task", "Variation", "get_task"]
