"""demo-factory collect-instructions: serve the instruction-collection page until Ctrl+C.

Serve a small web page that shows each unseen (test) variation of a task as pictures - the scene with the goal
order marked - and appends the instructions people type to a JSONL file in the format `convert --human-
instructions` reads. Several people can write at once; re-running the same command resumes with the file's
rows.
"""

from __future__ import annotations

import argparse
import errno
import os
import socket
from pathlib import Path

from demo_factory.cli_common import UsageError
from demo_factory.collect.pictures import PictureCache, default_cache_folder
from demo_factory.collect.server import CollectApp, CollectServer
from demo_factory.collect.store import InstructionFile, check_language
from demo_factory.instructions.human import HumanInstructionError
from demo_factory.tasks import INSTRUCTED_TASKS, SPLITS, get_task


def port_number(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"{value} is not a port number; accepted: 1-65535, or 0 for any free port")
    return value


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``collect-instructions`` on the ``demo-factory`` sub-command parsers."""
    parser = subparsers.add_parser(
        "collect-instructions", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
        help="serve a local web page where people write instructions for test variations")
    parser.add_argument("--task", required=True, choices=INSTRUCTED_TASKS, help="task name (see `demo-factory tasks`)")
    parser.add_argument("--split", default="test", choices=SPLITS,
                        help="variation split; human instructions are for test variations only (default: test)")
    parser.add_argument("--out", required=True, help="the .jsonl file to append to (created if missing)")
    parser.add_argument("--port", type=port_number, default=8000, help="port to serve on (default: 8000; 0: any free)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to bind (default: 127.0.0.1, this machine only; 0.0.0.0 opens it to the network)")
    parser.add_argument("--language", default="en", help="language tag stored with each instruction (default: en)")
    parser.add_argument("--cache", default=None,
                        help=f"folder for the rendered pictures (default: {default_cache_folder()})")
    parser.set_defaults(run=run)
    return parser


def open_instruction_file(out: Path, task_name: str, language: str) -> InstructionFile:
    """The output file, checked: a writable .jsonl path whose existing rows (if any) are valid."""
    if out.suffix != ".jsonl":
        raise UsageError(f"--out {out}: expected a file name ending in .jsonl")
    if out.is_dir():
        raise UsageError(f"--out {out}: is a folder; expected a .jsonl file path")
    if out.exists() and not os.access(out, os.R_OK | os.W_OK):
        raise UsageError(f"--out {out}: the file is not readable and writable")
    parent = out.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise UsageError(f"--out {out}: cannot write there ({parent} is not a writable folder)")
    try:
        language = check_language(language)
    except ValueError as exc:
        raise UsageError(f"--language: {exc}") from None
    try:
        return InstructionFile(out, get_task(task_name), language)
    except HumanInstructionError as exc:
        raise UsageError(f"--out: {exc} (fix or move the file, then re-run)") from None


def run(args) -> int:
    if args.split != "test":
        raise UsageError(f"--split {args.split}: human instructions are collected for unseen variations only; "
                         "accepted: test")
    instructions = open_instruction_file(Path(args.out), args.task, args.language)
    cache = Path(args.cache) if args.cache else default_cache_folder()
    if cache.exists() and not cache.is_dir():
        raise UsageError(f"--cache {cache}: is not a folder")
    app = CollectApp(instructions, PictureCache(instructions.task, cache))
    try:
        server = CollectServer(app, args.host, args.port)
    except socket.gaierror as exc:
        raise UsageError(f"--host {args.host}: not an address of this machine ({exc.strerror})") from None
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise UsageError(f"--port {args.port}: already in use; choose another (or --port 0 for any free one)") from None
        raise UsageError(f"--host {args.host} --port {args.port}: cannot serve there ({exc.strerror})") from None
    progress = instructions.progress()
    print(f"collecting instructions for {args.task} ({progress['variations']} test variations, "
          f"{_count(progress['instructions'], 'instruction')} so far) into {args.out}", flush=True)
    print(f"open {server.url} in a browser; Ctrl+C stops", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    progress = instructions.progress()
    print(f"stopped: {_count(progress['instructions'], 'instruction')} for {progress['with_instructions']} of "
          f"{progress['variations']} variations in {args.out}")
    return 0


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")
