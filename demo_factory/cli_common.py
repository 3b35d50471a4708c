"""What every `demo-factory` sub-command shares: argument types, the output-folder check, and the
mapping from errors to exit codes (`run_command`).

Reads and writes nothing itself; each sub-command's parser (`cli.py` for generate/tasks/inspect,
`convert/cli.py`, `evaluate/cli.py`, `publish/cli.py`, `collect/cli.py`) imports it, and `cli.py`
imports them to dispatch, so the imports only go one way.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from demo_factory.errors import UsageError

__all__ = ["UsageError", "check_output_folder", "image_size", "non_negative_float", "positive_int", "run_command",
           "shard"]

EXIT_INTERRUPTED = 130


# -- argument types ---------------------------------------------------------------------------
def positive_int(text: str) -> int:
    return _number(text, int, "a whole number", 1, "at least 1")


def non_negative_float(text: str) -> float:
    return _number(text, float, "a number", 0, "0 or more")


def _number(text: str, kind, what: str, minimum, rule: str):
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"{value} is not allowed; must be {rule}")
    return value


def shard(text: str) -> tuple[int, int]:
    """``i/N`` with 0 <= i < N."""
    try:
        index, count = (int(v) for v in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a shard; use i/N, e.g. 0/4") from None
    if not 0 <= index < count:
        raise argparse.ArgumentTypeError(f"{text!r} is not a shard; i/N needs 0 <= i < N")
    return index, count


def image_size(text: str) -> tuple[int, int]:
    """``128`` or ``96x128`` (height x width)."""
    parts = text.lower().split("x")
    try:
        values = [int(v) for v in parts]
    except ValueError:
        values = []
    if len(values) not in (1, 2) or min(values) < 16 or max(values) > 1024:
        raise argparse.ArgumentTypeError(f"{text!r} is not an image size; use N or HxW with 16..1024 pixels")
    return (values[0], values[-1])


# -- output folders ---------------------------------------------------------------------------
def check_output_folder(out: Path, own_file) -> None:
    """Refuse a path that is a file, holds files we did not write (``own_file(name)`` False), or cannot be
    written."""
    if out.exists():
        if not out.is_dir():
            raise UsageError(f"--out {out}: exists and is not a folder")
        foreign = sorted(p.name for p in out.iterdir() if not own_file(p.name))
        if foreign:
            shown = ", ".join(foreign[:3]) + (" ..." if len(foreign) > 3 else "")
            raise UsageError(f"--out {out}: the folder holds other files ({shown}); use an empty or new folder")
        if not os.access(out, os.W_OK | os.X_OK):
            raise UsageError(f"--out {out}: the folder is not writable")
        return
    parent = out.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise UsageError(f"--out {out}: cannot create it ({parent} is not a writable folder)")


# -- running a sub-command --------------------------------------------------------------------
def run_command(args: argparse.Namespace) -> int:
    """Run the parsed sub-command (``args.run``) and turn a `UsageError` into one line on stderr and its exit
    code, an interrupt into 130 with how to resume."""
    try:
        return args.run(args)
    except UsageError as exc:
        print(f"demo-factory {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("interrupted; re-run the same command to finish (completed work is kept)", file=sys.stderr)
        return EXIT_INTERRUPTED
