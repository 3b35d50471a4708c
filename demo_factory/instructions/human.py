"""Human-written instructions: the file format, its validation, and how episodes get them.

File format (JSON Lines, UTF-8; one JSON object per line; blank lines are ignored)::

    {"task": "push_buttons", "colours": ["green", "cyan", "rose"], "instruction": "hit green, then cyan, then the pink one", "author": "a", "language": "en"}
    {"task": "tower", "variation_id": 13, "instruction": "put the purple block on the grey mat"}

- ``task`` (required): a registered task name.
- the variation, by ``variation_id`` (its id in the task's enumeration) or ``colours`` (the
  ordered colour sequence, a list or a comma-separated string; case-insensitive, grey = gray),
  or both if they agree. It must be an unseen variation: one of the task's test variations or
  any other sequence that is not a training variation (see `demo-factory generate --variation`).
- ``instruction`` (required): the free text, non-empty, not repeated within a task
  (compared case- and whitespace-insensitively).
- ``author``, ``language`` (optional; language defaults to "en"), ``timestamp`` (optional, when it
  was written: an ISO 8601 string). No other fields.

Any violation raises ``HumanInstructionError`` naming the file, the line number and the problem.

Assignment (``assign_human_instructions``): per variation, with its episodes e_0..e_{n-1} and
its rows r_0..r_{m-1} (both in a fixed order), the human split gets max(n, m) episodes; the j-th
pairs e_{j mod n} with r_{j mod m}. So every row is used (episodes are repeated when a variation
has more rows than episodes) and every episode is used (rows cycle when it has more episodes).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Generic, TypeVar

from demo_factory.tasks import TASKS, Task, Variation, get_task

FIELDS = ("task", "variation_id", "colours", "instruction", "author", "language", "timestamp")


class HumanInstructionError(ValueError):
    """A human-instruction file that breaks the format; the message names the file and line."""


@dataclass(frozen=True)
class HumanInstruction:
    """One validated row of a human-instruction file."""

    task: str
    variation_id: int
    colours: tuple[str, ...]
    instruction: str
    author: str | None
    language: str
    line: int  # 1-based line in the file it came from


def shipped_human_instructions(task: str) -> Path | None:
    """The hand-written instruction file shipped with demo_factory for ``task``, if there is one."""
    path = Path(str(resources.files("demo_factory.instructions") / "data" / f"{task}_human.jsonl"))
    return path if path.is_file() else None


def load_human_instructions(path: str | os.PathLike) -> list[HumanInstruction]:
    """Read and validate every row of a human-instruction file (any tasks), in file order."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise HumanInstructionError(f"{path}: cannot read human-instruction file ({exc})") from exc
    rows: list[HumanInstruction] = []
    seen: dict[tuple[str, str], int] = {}
    for number, text in enumerate(lines, start=1):
        if not text.strip():
            continue
        row = _parse_row(text, lambda problem, n=number: HumanInstructionError(f"{path}:{n}: {problem}"))
        key = (row.task, " ".join(row.instruction.lower().split()))
        if key in seen:
            raise HumanInstructionError(f"{path}:{number}: duplicate instruction {row.instruction!r} (same as line {seen[key]})")
        seen[key] = number
        rows.append(HumanInstruction(**{**row.__dict__, "line": number}))
    if not rows:
        raise HumanInstructionError(f"{path}: no instructions in the file")
    return rows


def _parse_row(text: str, error) -> HumanInstruction:
    try:
        row = json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(f"not valid JSON ({exc.msg} at column {exc.colno})") from None
    if not isinstance(row, dict):
        raise error("expected a JSON object")
    unknown = sorted(set(row) - set(FIELDS))
    if unknown:
        raise error(f"unknown field {unknown[0]!r}; accepted: {', '.join(FIELDS)}")
    task_name = row.get("task")
    if task_name not in TASKS:
        raise error(f"unknown task {task_name!r}; accepted: {', '.join(TASKS)}")
    task = get_task(task_name)
    variation = None
    if "colours" in row:
        colours = row["colours"]
        words = colours.split(",") if isinstance(colours, str) else colours
        if not isinstance(words, list) or not words or not all(isinstance(w, str) for w in words):
            raise error(f"colours must be a list of colour names or a comma-separated string, got {colours!r}")
        try:
            variation = task.variation_of(words)
        except ValueError as exc:
            raise error(str(exc)) from None
    if "variation_id" in row:
        vid = row["variation_id"]
        if not isinstance(vid, int) or isinstance(vid, bool) or not 0 <= vid < len(task.variations):
            raise error(f"variation_id {vid!r} does not exist; {task_name} has ids 0 to {len(task.variations) - 1}")
        if variation is not None and variation.id != vid:
            raise error(f"variation_id {vid} is {','.join(task.variation(vid).colours)}, "
                        f"but colours say {','.join(variation.colours)}")
        variation = task.variation(vid)
    if variation is not None:
        try:
            task.check_split_membership(variation, "test")
        except ValueError as exc:
            raise error(f"{exc}; human instructions describe unseen (test) variations") from None
    if variation is None:
        raise error("no variation: give variation_id or colours")
    instruction = row.get("instruction")
    if not isinstance(instruction, str) or not instruction.strip():
        raise error("instruction is missing or empty")
    author, language = row.get("author"), row.get("language", "en")
    for name, value in (("author", author), ("language", language), ("timestamp", row.get("timestamp"))):
        if value is not None and (not isinstance(value, str) or not value.strip()):
            raise error(f"{name} must be a non-empty string, got {value!r}")
    return HumanInstruction(task_name, variation.id, variation.colours, instruction.strip(), author, language, 0)


def variations_in_file(path: str | os.PathLike, task: Task) -> list[Variation]:
    """The variations of ``task`` that a human-instruction file names, in file order, without repeats."""
    rows = [r for r in load_human_instructions(path) if r.task == task.name]
    return [task.variation(vid) for vid in dict.fromkeys(r.variation_id for r in rows)]


E = TypeVar("E")


@dataclass
class HumanAssignment(Generic[E]):
    """Episodes paired with human instructions, plus what could not be paired."""

    pairs: list[tuple[E, HumanInstruction]]
    rows_without_episodes: list[HumanInstruction]  # their variation has no episode in the input
    episodes_without_rows: list[E]  # their variation has no row in the file


def assign_human_instructions(
    episodes_by_variation: dict[int, list[E]], rows: list[HumanInstruction]
) -> HumanAssignment[E]:
    """Pair episodes with rows deterministically (see the module docstring), variation by variation."""
    rows_by_variation: dict[int, list[HumanInstruction]] = {}
    for row in rows:
        rows_by_variation.setdefault(row.variation_id, []).append(row)
    pairs: list[tuple[E, HumanInstruction]] = []
    for variation_id in sorted(set(episodes_by_variation) & set(rows_by_variation)):
        episodes, its_rows = episodes_by_variation[variation_id], rows_by_variation[variation_id]
        if not episodes:
            continue
        pairs += [(episodes[j % len(episodes)], its_rows[j % len(its_rows)]) for j in range(max(len(episodes), len(its_rows)))]
    return HumanAssignment(
        pairs=pairs,
        rows_without_episodes=[r for r in rows if not episodes_by_variation.get(r.variation_id)],
        episodes_without_rows=[e for vid in sorted(episodes_by_variation) if vid not in rows_by_variation
                               for e in episodes_by_variation[vid]],
    )
