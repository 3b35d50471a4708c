"""Human-written instructions: the file formats, their validation, and how episodes get them.

Two formats are read (``load_human_instructions`` tells them apart by the first character):

1. **The HiveFormer authors' ``annotations.json``** (a JSON array), as it is: the paper's 162
   sentences written by people for the unseen test variations of ``push_buttons3`` and ``tower3``.
   It ships with demo_factory (``data/hiveformer/``, MIT licence) and is the default human set of
   both tasks. A row's ``fields.variation`` is the fork's variation id, which is ours too (see
   ``demo_factory.tasks.variations.hiveformer_sequences``); ``fields.colors``, where present, must
   agree with it; ``fields.instruction`` is kept exactly, typos, line breaks and spaces included.
   One row of the authors' file has an empty sentence (tower3 variation 136): it is read, and
   ``sentence_rows`` leaves it out of the human split.

2. **demo-factory's own JSON Lines** (UTF-8; one JSON object per line; blank lines are ignored),
   written e.g. by ``demo-factory collect-instructions``::

    {"task": "push_buttons", "colours": ["green", "cyan", "rose"], "instruction": "hit green, then cyan, then the pink one", "author": "a", "language": "en"}
    {"task": "tower", "variation_id": 113, "instruction": "put the purple block on the grey mat"}

- ``task`` (required): a registered task name.
- the variation, by ``variation_id`` (its id in the task's enumeration) or ``colours`` (the
  ordered colour sequence, a list or a comma-separated string; case-insensitive, grey = gray),
  or both if they agree. It must be an unseen variation: one of the task's test variations or
  any other sequence that is not a training variation (see `demo-factory generate --variation`).
- ``instruction`` (required): the free text, non-empty, not repeated within a task
  (compared case- and whitespace-insensitively).
- ``author``, ``language`` (optional; language defaults to "en"), ``timestamp`` (optional, when it
  was written: an ISO 8601 string). No other fields.

Any violation raises ``HumanInstructionError`` naming the file, the line (JSONL) or row
(annotations) number and the problem. In both formats a row must describe an unseen variation: a
row for a training variation is refused, naming the leak.

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

from demo_factory.errors import UsageError
from demo_factory.tasks import TASKS, Task, Variation, get_task

FIELDS = ("task", "variation_id", "colours", "instruction", "author", "language", "timestamp")


class HumanInstructionError(UsageError, ValueError):
    """A human-instruction file that breaks the format; the message names the file and line."""


@dataclass(frozen=True)
class HumanInstruction:
    """One validated row of a human-instruction file."""

    task: str
    variation_id: int
    words: tuple[str, ...]
    instruction: str
    author: str | None
    language: str
    line: int  # 1-based line (JSONL) or row (annotations.json) in the file it came from
    record_id: str | None = None  # the row's "id" in the authors' annotations.json


def hiveformer_annotations() -> Path:
    """The HiveFormer authors' ``annotations.json`` shipped with demo_factory (MIT, LICENSE beside it)."""
    return Path(str(resources.files("demo_factory.instructions") / "data" / "hiveformer" / "annotations.json"))


def shipped_human_instructions(task: str) -> Path | None:
    """The human-written instruction file shipped for ``task``: the paper's annotations for the
    tasks numbered as the paper (push_buttons, tower), else None."""
    if task in TASKS and TASKS[task].paper_numbering is not None:
        return hiveformer_annotations()
    return None


def load_human_instructions(path: str | os.PathLike) -> list[HumanInstruction]:
    """Read and validate every row of a human-instruction file (any tasks), in file order:
    the authors' ``annotations.json`` (a JSON array) or demo-factory's JSON Lines."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise HumanInstructionError(f"{path}: cannot read human-instruction file ({exc})") from exc
    if text.lstrip().startswith("["):
        return _load_annotations(path, text)
    return _load_jsonl(path, text.splitlines())


def _load_jsonl(path: Path, lines: list[str]) -> list[HumanInstruction]:
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


def _load_annotations(path: Path, text: str) -> list[HumanInstruction]:
    """The authors' annotations.json: a JSON array of {"id", "fields": {"task", "variation", "instruction", ...}}."""
    try:
        records = json.loads(text)
    except json.JSONDecodeError as exc:
        raise HumanInstructionError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    by_fork_name = {cls.paper_numbering.fork_task: name for name, cls in TASKS.items() if cls.paper_numbering}
    rows = []
    for number, record in enumerate(records, start=1):
        where = f"{path}: row {number}" + (f" ({record['id']})" if isinstance(record, dict) and "id" in record else "")
        fields = record.get("fields") if isinstance(record, dict) else None
        if not isinstance(fields, dict):
            raise HumanInstructionError(f"{where}: expected an object with 'fields' (the authors' annotations format)")
        fork_task = fields.get("task")
        if fork_task not in by_fork_name:
            raise HumanInstructionError(f"{where}: unknown task {fork_task!r}; accepted: {', '.join(by_fork_name)}")
        task = get_task(by_fork_name[fork_task])
        vid = fields.get("variation")
        if not isinstance(vid, int) or isinstance(vid, bool) or not 0 <= vid < task.paper_numbering.total:
            raise HumanInstructionError(f"{where}: variation {vid!r} does not exist; {fork_task} has ids 0 to "
                                        f"{task.paper_numbering.total - 1}")
        variation = task.variation(vid)
        if "colors" in fields and [str(c).lower() for c in fields["colors"] or []] != list(variation.words):
            raise HumanInstructionError(f"{where}: colors {fields['colors']} disagree with {fork_task} variation {vid}, "
                                        f"which is {variation.name}")
        try:
            task.check_split_membership(variation, "test")
        except ValueError as exc:
            raise HumanInstructionError(f"{where}: {exc}; human instructions describe unseen (test) variations") from None
        instruction = fields.get("instruction")
        if not isinstance(instruction, str):  # "" is kept: the authors' file has one blank row (tower3 136)
            raise HumanInstructionError(f"{where}: instruction is missing; expected a string")
        rows.append(HumanInstruction(task.name, vid, variation.words, instruction, None, "en", number,
                                     record.get("id")))
    if not rows:
        raise HumanInstructionError(f"{path}: no instructions in the file")
    return rows


def sentence_rows(rows: list[HumanInstruction]) -> tuple[list[HumanInstruction], list[HumanInstruction]]:
    """The rows with a sentence, and the blank ones (which cannot instruct an episode)."""
    return [r for r in rows if r.instruction.strip()], [r for r in rows if not r.instruction.strip()]


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
            raise error(f"variation_id {vid} is {','.join(task.variation(vid).words)}, "
                        f"but colours say {','.join(variation.words)}")
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
    return HumanInstruction(task_name, variation.id, variation.words, instruction.strip(), author, language, 0)


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
