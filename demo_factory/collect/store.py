"""The human-instruction file a collection session appends to.

Rows are written in the format ``demo_factory.instructions.human`` reads (task, variation_id,
colours, instruction, author, language), one JSON object per line, ASCII-escaped so that no
character inside a row can ever split it into two lines.

Writes are atomic and serialised:
- an append is one ``write`` of the whole line to a file opened with ``O_APPEND``, then ``fsync``;
- an edit rewrites the whole file under a temporary name, ``fsync``s it and renames it into place;
- both happen while holding a thread lock and an exclusive ``flock`` on a hidden lock file beside
  the output, so writers in several threads or several servers (for instance one per task, same
  file) never interleave. Before each operation the file is re-read if another process changed it.

A restart resumes where the file left off: existing rows are validated with the converter's own
``load_human_instructions`` and counted.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import threading
import zlib
from contextlib import contextmanager
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

from demo_factory.instructions.human import FIELDS, HumanInstruction, load_human_instructions
from demo_factory.tasks import Task

INSTRUCTION_MIN_CHARS = 3
INSTRUCTION_MAX_CHARS = 300
WRITER_MAX_CHARS = 32
WRITER_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
LANGUAGE_PATTERN = re.compile(r"[A-Za-z]{2,3}(-[A-Za-z0-9]{2,8})*")
# The row gets a timestamp as soon as the file format accepts one (see instructions.human.FIELDS).
TIMESTAMPED = "timestamp" in FIELDS


class EntryError(ValueError):
    """Input a writer can fix (shown on the page); ``status`` is the HTTP status to answer with."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


def entry_json(entry: HumanInstruction) -> dict:
    """What the page shows of one row."""
    return {"variation_id": entry.variation_id, "instruction": entry.instruction, "author": entry.author}


# -- validation (pure) -----------------------------------------------------------------------------
def check_writer(value) -> str:
    """A writer id: 1-32 letters, digits, '_', '.', '-', starting with a letter or digit."""
    if not isinstance(value, str) or not value.strip():
        raise EntryError("choose a writer id (letters and digits, e.g. w07)")
    value = value.strip()
    if len(value) > WRITER_MAX_CHARS or not WRITER_PATTERN.fullmatch(value):
        raise EntryError(f"writer id must be 1-{WRITER_MAX_CHARS} letters, digits, '_', '.' or '-' "
                         "(starting with a letter or digit)")
    return value


def check_instruction(value) -> str:
    """The instruction as stored: whitespace runs (newlines included) become single spaces."""
    if not isinstance(value, str):
        raise EntryError("instruction must be text")
    if any(ord(ch) < 32 and ch not in "\t\n\r" or ord(ch) == 127 for ch in value):
        raise EntryError("instruction contains control characters")
    text = " ".join(value.split())
    if len(text) < INSTRUCTION_MIN_CHARS:
        raise EntryError(f"write an instruction (at least {INSTRUCTION_MIN_CHARS} characters)")
    if len(text) > INSTRUCTION_MAX_CHARS:
        raise EntryError(f"instruction is {len(text)} characters long; at most {INSTRUCTION_MAX_CHARS} are accepted")
    return text


def check_language(value: str) -> str:
    if not LANGUAGE_PATTERN.fullmatch(value):
        raise ValueError(f"language {value!r} is not a language tag such as en, de or pt-BR")
    return value


def duplicate_key(task: str, instruction: str) -> tuple[str, str]:
    """How ``load_human_instructions`` compares instructions: per task, case- and space-insensitive."""
    return task, " ".join(instruction.lower().split())


def next_variation(order: list[int], counts: dict[int, int], done: set[int], after: int | None,
                   skipped: set[int], start: int = 0) -> int | None:
    """The variation to show a writer next, or None when they have written for every one.

    Among the variations the writer has not written for (and has not skipped, unless only skipped
    ones are left), the one with the fewest instructions; ties go to the first in ``order`` after
    ``after`` (or from position ``start`` when there is no current variation).
    """
    open_ = [v for v in order if v not in done]
    candidates = [v for v in open_ if v not in skipped and v != after] or [v for v in open_ if v != after] or open_
    if not candidates:
        return None
    first = order.index(after) + 1 if after in order else start % len(order)
    rank = {v: (i - first) % len(order) for i, v in enumerate(order)}
    return min(candidates, key=lambda v: (counts.get(v, 0), rank[v]))


# -- the file --------------------------------------------------------------------------------------
class InstructionFile:
    """The JSONL file of one collection session, for one task's test variations.

    Other tasks' rows in the same file are kept untouched (and count for nothing here).
    Raises ``HumanInstructionError`` at construction if the existing file breaks the format.
    """

    def __init__(self, path: str | os.PathLike, task: Task, language: str = "en"):
        self.path = Path(path)
        self.task = task
        self.language = check_language(language)
        self.order = [v.id for v in task.split_variations("test")]
        self._test_ids = set(self.order)
        self._lock_path = self.path.with_name(f".{self.path.name}.lock")
        self._thread_lock = threading.RLock()
        self._signature = ("unread",)  # never a real signature: the first access reads the file
        self._ends_with_newline = True
        self._lines: list[str] = []
        self._entries: list[HumanInstruction] = []  # this task's rows, in file order
        self._keys: dict[tuple[str, str], int] = {}  # duplicate key → 1-based line
        with self._locked():
            pass

    # -- reading -----------------------------------------------------------------------------
    def _stat_signature(self):
        try:
            st = self.path.stat()
        except FileNotFoundError:
            return None
        return (st.st_ino, st.st_size, st.st_mtime_ns)

    def _reload_if_changed(self) -> None:
        signature = self._stat_signature()
        if signature == self._signature:
            return
        text = self.path.read_text(encoding="utf-8") if signature is not None else ""
        rows = load_human_instructions(self.path) if text.strip() else []
        self._lines = text.splitlines()
        self._keys = {duplicate_key(r.task, r.instruction): r.line for r in rows}
        self._entries = [r for r in rows if r.task == self.task.name]
        self._ends_with_newline = not text or text.endswith("\n")
        self._signature = signature

    @contextmanager
    def _locked(self, write: bool = False):
        """Serialise with other threads and other processes, on an up-to-date view of the file.

        Writers hold an exclusive ``flock`` on the lock file (creating it and the folder: only
        writers create anything on disk); a reader takes a shared one only to re-read a file that
        another process changed, so it never reads half of someone else's append.
        """
        with self._thread_lock:
            if write:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                with self._flock(fcntl.LOCK_EX):
                    self._reload_if_changed()
                    yield
                return
            if self._stat_signature() != self._signature and self._lock_path.exists():
                with self._flock(fcntl.LOCK_SH):
                    self._reload_if_changed()
            else:
                self._reload_if_changed()
            yield

    @contextmanager
    def _flock(self, kind: int):
        fd = os.open(self._lock_path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, kind)
            yield
        finally:
            os.close(fd)  # releases the flock

    def entries(self) -> list[HumanInstruction]:
        with self._locked():
            return list(self._entries)

    def counts(self) -> dict[int, int]:
        """Instructions per test variation (0 for those without any)."""
        with self._locked():
            counts = dict.fromkeys(self.order, 0)
            for entry in self._entries:
                counts[entry.variation_id] += 1
            return counts

    def progress(self, writer: str | None = None) -> dict:
        """How many variations have how many instructions, and the writer's own share."""
        with self._locked():
            counts = self.counts()
            histogram: dict[int, int] = {}
            for n in counts.values():
                histogram[n] = histogram.get(n, 0) + 1
            mine = [e for e in self._entries if writer is not None and e.author == writer]
            return {
                "variations": len(self.order),
                "with_instructions": sum(n > 0 for n in counts.values()),
                "instructions": len(self._entries),
                "histogram": [{"instructions": n, "variations": histogram[n]} for n in sorted(histogram)],
                "mine": len(mine),
                "mine_variations": len({e.variation_id for e in mine}),
            }

    def last_entry(self, writer: str) -> HumanInstruction | None:
        with self._locked():
            return next((e for e in reversed(self._entries) if e.author == writer), None)

    def next_for(self, writer: str, after: int | None = None, skipped: set[int] = frozenset()) -> int | None:
        """The next variation to show ``writer`` (see ``next_variation``); writers start at different places."""
        with self._locked():
            done = {e.variation_id for e in self._entries if e.author == writer}
            start = zlib.crc32(writer.encode()) % len(self.order)
            return next_variation(self.order, self.counts(), done, after, set(skipped), start)

    # -- writing -----------------------------------------------------------------------------
    def _row(self, variation_id: int, instruction: str, writer: str) -> dict:
        row = {
            "task": self.task.name,
            "variation_id": variation_id,
            "colours": list(self.task.variation(variation_id).words),
            "instruction": instruction,
            "author": writer,
            "language": self.language,
        }
        if TIMESTAMPED:
            row["timestamp"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        return row

    def _check_new_text(self, instruction: str, replacing: int | None = None) -> None:
        line = self._keys.get(duplicate_key(self.task.name, instruction))
        if line is not None and line != replacing:
            raise EntryError("this instruction is already in the file; please write it in your own words", 409)

    def add(self, writer, variation_id, instruction) -> HumanInstruction:
        """Validate and append one instruction; ``EntryError`` says what to fix."""
        writer, instruction = check_writer(writer), check_instruction(instruction)
        if not isinstance(variation_id, int) or isinstance(variation_id, bool) or variation_id not in self._test_ids:
            raise EntryError(f"variation {variation_id!r} is not a test variation of {self.task.name}")
        with self._locked(write=True):
            self._check_new_text(instruction)
            line = json.dumps(self._row(variation_id, instruction, writer))
            data = ("" if self._ends_with_newline else "\n") + line + "\n"
            created = not self.path.exists()
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            try:
                _write_all(fd, data.encode("ascii"))
                os.fsync(fd)
            finally:
                os.close(fd)
            if created:
                _fsync_folder(self.path.parent)
            # Under the flock nobody else wrote: update the view instead of re-validating the file.
            entry = HumanInstruction(self.task.name, variation_id, self.task.variation(variation_id).words, instruction,
                                     writer, self.language, line=len(self._lines) + 1)
            self._lines.append(line)
            self._entries.append(entry)
            self._keys[duplicate_key(self.task.name, instruction)] = entry.line
            self._ends_with_newline = True
            self._signature = self._stat_signature()
            return entry

    def edit_last(self, writer, instruction) -> HumanInstruction:
        """Replace the text of ``writer``'s most recent entry (the whole file is rewritten atomically)."""
        writer, instruction = check_writer(writer), check_instruction(instruction)
        with self._locked(write=True):
            entry = next((e for e in reversed(self._entries) if e.author == writer), None)
            if entry is None:
                raise EntryError(f"writer {writer} has no entry to edit yet", 404)
            self._check_new_text(instruction, replacing=entry.line)
            row = json.loads(self._lines[entry.line - 1])
            row["instruction"] = instruction
            lines = list(self._lines)
            lines[entry.line - 1] = json.dumps(row)
            partial = self.path.with_name(f".{self.path.name}.{os.getpid()}.partial")
            mode = self.path.stat().st_mode & 0o777
            fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
            try:
                _write_all(fd, ("\n".join(lines) + "\n").encode("utf-8"))
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(partial, self.path)
            _fsync_folder(self.path.parent)
            edited = replace(entry, instruction=instruction)
            self._lines = lines
            self._entries = [edited if e.line == entry.line else e for e in self._entries]
            del self._keys[duplicate_key(self.task.name, entry.instruction)]
            self._keys[duplicate_key(self.task.name, instruction)] = entry.line
            self._ends_with_newline = True
            self._signature = self._stat_signature()
            return edited


def _write_all(fd: int, data: bytes) -> None:
    while data:
        written = os.write(fd, data)
        data = data[written:]


def _fsync_folder(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
