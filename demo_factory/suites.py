"""Named task suites: the tasks a multi-task dataset is generated from.

``ten_tasks`` is the HiveFormer paper's Table 1 multi-task set; ``categories`` takes one task from
each of the paper's nine categories; and each category is a suite of its own (``motion_planner``:
every task of that category), for studying one challenge. ``demo-factory generate --suite`` writes
each task's episodes into its own sub-folder (``OUT/<task>/``), a complete single-task job with its
own manifest and generation summary, so every task resumes, shards and converts alone;
``demo-factory convert --in OUT`` turns the whole folder into one multi-task dataset.
"""

from __future__ import annotations

from demo_factory.tasks import TASKS
from demo_factory.tasks.categories import CATEGORIES, suite_name

SUITES: dict[str, tuple[str, ...]] = {
    "ten_tasks": (
        "reach_target",
        "push_button",
        "pick_and_lift",
        "pick_up_cup",
        "slide_block_to_target",
        "put_knife_on_chopping_board",
        "stack_wine",
        "put_money_in_safe",
        "take_money_out_safe",
        "take_umbrella_out_of_umbrella_stand",
    ),
    # One single-goal task per category, in the order of CATEGORIES.
    "categories": (
        "stack_wine",
        "slide_block_to_target",
        "wipe_desk",
        "reach_target",
        "open_drawer",
        "pick_up_cup",
        "put_knife_on_chopping_board",
        "turn_oven_on",
        "put_money_in_safe",
    ),
    # The tasks neither in ten_tasks nor push_buttons / tower: with ten_tasks' reference run, every task is learned.
    "beyond_ten_tasks": (
        "open_drawer",
        "close_drawer",
        "turn_tap",
        "turn_oven_on",
        "open_wine_bottle",
        "stack_blocks",
        "wipe_desk",
        "reach_and_drag",
    ),
    **{suite_name(category): tuple(name for name, task in TASKS.items() if category in task.categories)
       for category in CATEGORIES},
}

SUITE_DESCRIPTIONS: dict[str, str] = {
    "ten_tasks": "the HiveFormer paper's multi-task set",
    "categories": "one task from each of the HiveFormer paper's nine task categories",
    "beyond_ten_tasks": "the tasks beyond the paper's ten and push_buttons / tower",
    **{suite_name(category): f"every task of the HiveFormer paper's {category} category" for category in CATEGORIES},
}


def suite_tasks(name: str) -> tuple[str, ...]:
    """The tasks of a suite; ``ValueError`` naming the accepted suites for an unknown name."""
    try:
        return SUITES[name]
    except KeyError:
        raise ValueError(f"unknown suite {name!r}; accepted: {', '.join(SUITES)}") from None


def suite_of(tasks) -> str | None:
    """The suite made of exactly these tasks, if any."""
    wanted = set(tasks)
    return next((name for name, members in SUITES.items() if set(members) == wanted), None)
