"""Task names → task classes. Adding a task: one module and one line here."""

from __future__ import annotations

from demo_factory.tasks.base import Task
from demo_factory.tasks.push_buttons import PushButtons
from demo_factory.tasks.tower import Tower

TASKS: dict[str, type[Task]] = {
    PushButtons.name: PushButtons,
    Tower.name: Tower,
}


def get_task(name: str) -> Task:
    """A fresh task instance; ``ValueError`` naming the accepted tasks for an unknown name."""
    try:
        return TASKS[name]()
    except KeyError:
        raise ValueError(f"unknown task {name!r}; accepted: {', '.join(sorted(TASKS))}") from None
