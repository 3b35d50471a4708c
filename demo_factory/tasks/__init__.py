"""Tabletop tasks: one module each, registered by name in ``registry``."""

from demo_factory.tasks.base import KeyframeTarget, Task
from demo_factory.tasks.registry import MULTI_VARIATION_TASKS, TASKS, get_task
from demo_factory.tasks.variations import SPLITS, Variation

__all__ = ["MULTI_VARIATION_TASKS", "SPLITS", "TASKS", "KeyframeTarget", "Task", "Variation", "get_task"]
