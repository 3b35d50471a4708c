"""The ``demo-factory`` command: tasks, generate, inspect, convert, eval, collect-instructions."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from demo_factory.cli_common import (
    UsageError,
    check_output_folder,
    image_size,
    non_negative_float,
    positive_int,
    run_command,
    shard,
)
from demo_factory.collect.cli import add_parser as add_collect_parser
from demo_factory.convert.cli import add_parser as add_convert_parser
from demo_factory.evaluate.cli import add_parser as add_eval_parser
from demo_factory.publish.cli import add_parser as add_publish_parser
from demo_factory.generate import EXECUTORS, MANIFEST_FILE
from demo_factory.report import REPORT_FILES, write_report
from demo_factory.tasks import SPLITS, TASKS, get_task


def _is_generation_file(name: str) -> bool:
    return (name.endswith(".mcap") or name.endswith(".mcap.partial") or name in (MANIFEST_FILE, *REPORT_FILES)
            or (name.startswith("generation_summary") and name.endswith(".json"))
            or (name.startswith("generation_log") and name.endswith(".jsonl")))


# -- commands ---------------------------------------------------------------------------------
def cmd_tasks(args) -> int:
    from demo_factory.suites import SUITES

    rows = [("task", "category", "variations", "train", "test", "description")]
    for name in sorted(TASKS):
        task = get_task(name)
        rows.append((name, task.category, str(len(task.variations)), str(len(task.split_variations("train"))),
                     str(len(task.split_variations("test"))), task.description))
    widths = [max(len(r[i]) for r in rows) for i in range(5)]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths)) + "  " + row[5])
    print("\nvariation ids and splits:")
    for name in TASKS:
        print(f"  {name.ljust(widths[0])}  {get_task(name).variation_scheme}")
    for suite, members in SUITES.items():
        print(f"\nsuite {suite}: {', '.join(members)}")
    return 0


def cmd_generate(args) -> int:
    if args.suite is None:
        if args.episodes_per_task:
            raise UsageError("--episodes-per-task needs --suite (with --task use --episodes)")
        return generate_job(args)
    return generate_suite(args)


def generate_suite(args) -> int:
    """Every task of the suite as its own job in ``OUT/<task>/`` (resumable and shardable alike)."""
    from demo_factory.suites import suite_tasks

    if args.variation or args.variations_from or args.episodes_per_variation:
        raise UsageError("--suite generates each task's own split variations; --variation, --variations-from and "
                         "--episodes-per-variation need --task")
    tasks = suite_tasks(args.suite)
    out = Path(args.out)
    check_output_folder(out, lambda name: name in tasks or name in REPORT_FILES)
    for task in tasks:
        check_output_folder(out / task, _is_generation_file)
    codes = []
    for task in tasks:
        job = argparse.Namespace(**{**vars(args), "task": task, "out": str(out / task),
                                    "episodes": args.episodes_per_task or args.episodes})
        codes.append(generate_job(job))
    if write_report(out) is not None:
        print(f"\ngeneration report of the suite: {out / 'report.md'} (also report.json, report.png)")
    return max(codes)


def generate_job(args) -> int:
    """One task's job: the requests, the manifest, the episodes and the generation summary."""
    from tqdm import tqdm

    from demo_factory.generate import job_requests, record_job, remove_stale_partials, run_requests, shard_requests

    out = Path(args.out)
    named = named_variations(args)
    args.split = args.split or ("test" if named else "train")
    for variation in named:
        try:
            get_task(args.task).check_split_membership(variation, args.split)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    check_output_folder(out, _is_generation_file)
    episodes = args.episodes_per_variation * len(named) if args.episodes_per_variation else args.episodes
    requests = job_requests(args.task, args.split, episodes, args.seed, variations=named or None,
                            image_size=args.image_size, dense_fps=args.dense_fps)
    parameters = {"task": args.task, "split": args.split, "episodes": episodes, "seed": args.seed,
                  "image_size": list(args.image_size), "dense_fps": args.dense_fps,
                  "variations": [v.id for v in named] or None}
    requests = shard_requests(requests, args.shard)
    try:
        out.mkdir(parents=True, exist_ok=True)
        record_job(out, parameters)  # a ManifestMismatch is a UsageError
    except OSError as exc:
        raise UsageError(f"--out {out}: cannot write there ({exc.strerror})") from None
    remove_stale_partials(out, requests)
    began = time.perf_counter()
    outcomes = []
    bar = tqdm(total=len(requests), desc=f"{args.task}/{args.split}", unit="episode", file=sys.stderr)
    try:
        for outcome in run_requests(requests, out, workers=args.workers, executor=args.executor,
                                    address=args.address):
            outcomes.append(outcome)
            bar.update(1)
            bar.set_postfix(kept=sum(o.kept for o in outcomes), failed=sum(not o.kept for o in outcomes))
    except OSError as exc:
        bar.close()
        kept = sum(o.kept for o in outcomes)
        print(f"demo-factory generate: error: writing to {out} failed ({exc.strerror}); episodes finished "
              f"before it: {kept}, all complete and valid; fix the cause and re-run the same command to resume",
              file=sys.stderr)
        return 1
    bar.close()
    summary = generation_summary(args, outcomes, time.perf_counter() - began)
    (out / f"generation_summary_{args.task}_{args.split}.json").write_text(json.dumps(summary, indent=2) + "\n")
    with open(out / f"generation_log_{args.task}_{args.split}.jsonl", "a") as log:  # every attempt, every run
        for o in outcomes:
            if not o.resumed:
                log.write(json.dumps({"variation_id": o.request.variation_id, "episode_seed": o.request.episode_seed,
                                      "kept": o.kept, "reason": o.reason, "seconds": round(o.seconds, 3),
                                      "keyframes": o.keyframes, "planner_attempts": o.attempt_log}) + "\n")
    print_generation_summary(summary, out)
    write_report(out)
    return 0 if summary["kept"] > 0 else 1


def named_variations(args) -> list:
    """The variations named with --variation / --variations-from, in order, without repeats."""
    task = get_task(args.task)
    named = []
    try:
        for text in args.variation or []:
            named.append(task.parse_variation(text))
        if args.variations_from:
            from demo_factory.instructions.human import variations_in_file

            named += variations_in_file(args.variations_from, task)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.episodes_per_variation and not named:
        raise UsageError("--episodes-per-variation needs --variation or --variations-from")
    return list(dict.fromkeys(named))


def generation_summary(args, outcomes, total_seconds: float = 0.0) -> dict:
    """The figures a user wants after a generation run (also written to ``generation_summary_<task>_<split>.json``)."""
    fresh = [o for o in outcomes if not o.resumed]
    planning = [s for o in fresh for s in o.planning_seconds]
    attempts = Counter(a for o in fresh for a in o.attempts_per_transition)
    return {
        "command": " ".join(["demo-factory", "generate", "--task", args.task, "--split", args.split, "--episodes",
                             str(args.episodes), "--seed", str(args.seed), "--out", str(args.out)]
                            + [f"--variation={v}" for v in args.variation or []]
                            + (["--variations-from", args.variations_from] if args.variations_from else [])
                            + (["--episodes-per-variation", str(args.episodes_per_variation)]
                               if args.episodes_per_variation else [])
                            + (["--image-size", "x".join(map(str, args.image_size))]
                               if tuple(args.image_size) != (128, 128) else [])
                            + (["--dense-fps", f"{args.dense_fps:g}"] if args.dense_fps else [])),
        "task": args.task,
        "split": args.split,
        "requested": len(outcomes),
        "kept": sum(o.kept for o in outcomes),
        "already_present": sum(o.resumed for o in outcomes),
        "failed": [
            {"variation_id": o.request.variation_id, "episode_seed": o.request.episode_seed, "reason": o.reason}
            for o in outcomes if not o.kept
        ],
        "failure_reasons": dict(Counter(o.reason for o in outcomes if not o.kept)),
        "planner_attempts_histogram": {str(k): attempts[k] for k in sorted(attempts)},
        "planning_seconds_median": float(np.median(planning)) if planning else None,
        "planning_seconds_p95": float(np.percentile(planning, 95)) if planning else None,
        "seconds_per_episode": float(np.mean([o.seconds for o in fresh])) if fresh else None,
        "total_seconds": total_seconds,
    }


def print_generation_summary(summary: dict, out: Path) -> None:
    print(f"\n{summary['task']}/{summary['split']}: kept {summary['kept']} of {summary['requested']} episodes "
          f"({summary['already_present']} already present) in {out}")
    if summary["failed"]:
        reasons = ", ".join(f"{k}: {v}" for k, v in summary["failure_reasons"].items())
        print(f"  failed: {len(summary['failed'])} ({reasons})")
        for f in summary["failed"]:
            print(f"    variation {f['variation_id']} seed {f['episode_seed']}: {f['reason']}")
    hist = ", ".join(f"{k}: {v}" for k, v in summary["planner_attempts_histogram"].items())
    if hist:
        print(f"  planner attempts per planned transition: {hist}")
        print(f"  planning time per transition: median {summary['planning_seconds_median']:.3f} s, "
              f"p95 {summary['planning_seconds_p95']:.3f} s")
    if summary["seconds_per_episode"] is not None:
        print(f"  seconds per episode: {summary['seconds_per_episode']:.2f}")


def cmd_inspect(args) -> int:
    from demo_factory.record import read_episode
    from demo_factory.record.inspect import describe

    path = Path(args.recording)
    if not path.is_file():
        raise UsageError(f"{path}: no such recording file")
    print(describe(path, read_episode(path)))  # a RecordingError is a UsageError
    return 0


# -- parser -----------------------------------------------------------------------------------
def suite_names() -> list[str]:
    from demo_factory.suites import SUITES

    return list(SUITES)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="demo-factory",
        description="Manufacture instruction-conditioned robot demonstrations: simulate → MCAP → LeRobot.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    tasks = commands.add_parser("tasks", help="list the tasks, their categories, variation counts and split sizes",
                                description="List the tasks, their categories, variation counts and train/test split "
                                            "sizes, and the suites.")
    tasks.set_defaults(run=cmd_tasks)

    gen = commands.add_parser(
        "generate", help="generate expert episodes into MCAP recordings",
        description="Run the scripted expert with the OMPL planner in PyBullet and record each successful "
                    "episode to one MCAP file. Episode i uses the split's variation i mod n. Re-running the "
                    "same command skips episodes already recorded.",
    )
    which = gen.add_mutually_exclusive_group(required=True)
    which.add_argument("--task", choices=list(TASKS), help="task name (see `demo-factory tasks`)")
    which.add_argument("--suite", choices=sorted(suite_names()),
                       help="every task of a suite (e.g. ten_tasks), each into OUT/<task>/ as its own job")
    gen.add_argument("--split", choices=SPLITS,
                     help="variation split (default: train; test when variations are named)")
    gen.add_argument("--episodes", type=positive_int, default=10,
                     help="episodes to attempt, cycling over the variations (default: 10)")
    gen.add_argument("--variation", action="append", metavar="SEQUENCE_OR_ID",
                     help="generate this variation only: a colour sequence such as maroon,navy,teal or a variation "
                          "id (repeatable)")
    gen.add_argument("--variations-from", metavar="FILE",
                     help="generate every distinct variation of --task named in a human-instruction file: the "
                          "HiveFormer authors' annotations.json as it is, or demo-factory JSONL")
    gen.add_argument("--episodes-per-task", type=positive_int,
                     help="with --suite: episodes of each task (default: --episodes)")
    gen.add_argument("--episodes-per-variation", type=positive_int,
                     help="with named variations: this many episodes of each (instead of --episodes in all)")
    gen.add_argument("--seed", type=int, default=0, help="base seed; episode seeds derive from it (default: 0)")
    gen.add_argument("--out", required=True, help="output folder for the .mcap files")
    gen.add_argument("--image-size", type=image_size, default=(128, 128), help="camera size, N or HxW (default: 128)")
    gen.add_argument("--dense-fps", type=non_negative_float, default=0.0,
                     help="also record dense frames at this rate between keyframes (default: 0 = keyframes only)")
    gen.add_argument("--workers", type=positive_int, default=os.cpu_count() or 1,
                     help="parallel processes; files are identical for any number (default: the number of cores)")
    gen.add_argument("--shard", type=shard, help="run only shard i/N of the job (the shards' union is the job)")
    gen.add_argument("--executor", choices=EXECUTORS, default="process",
                     help="process: --workers local processes (default); ray: the same episodes on a Ray cluster "
                          "(pip install -e '.[ray]')")
    gen.add_argument("--address", help="with --executor ray: the cluster to join (default: start a local one)")
    gen.set_defaults(run=cmd_generate)

    ins = commands.add_parser("inspect", help="summarise one episode recording",
                              description="Print an episode's topics, keyframes, instruction and outcome.")
    ins.add_argument("recording", help="path to an episode .mcap file")
    ins.set_defaults(run=cmd_inspect)

    add_convert_parser(commands)
    add_eval_parser(commands)
    add_publish_parser(commands)
    add_collect_parser(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_command(args)


if __name__ == "__main__":
    sys.exit(main())
