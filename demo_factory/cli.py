"""The ``demo-factory`` command: tasks, generate, inspect, convert, eval, collect-instructions."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

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
from demo_factory.generate import (
    EXECUTORS,
    REPORT_FILES,
    GenerationJob,
    is_generation_file,
    run_job,
    summary_text,
    write_report,
)
from demo_factory.publish.cli import add_parser as add_publish_parser
from demo_factory.tasks import SPLITS, TASKS, get_task


# -- commands ---------------------------------------------------------------------------------
def cmd_tasks(args) -> int:
    from demo_factory.suites import SUITE_DESCRIPTIONS, SUITES

    rows = [("task", "categories", "variations", "train", "test", "description")]
    for name in sorted(TASKS):
        task = get_task(name)
        rows.append((name, ", ".join(task.categories), str(len(task.variations)),
                     str(len(task.split_variations("train"))), str(len(task.split_variations("test"))), task.description))
    widths = [max(len(r[i]) for r in rows) for i in range(5)]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths)) + "  " + row[5])
    print("\nvariation ids and splits:")
    for name in TASKS:
        print(f"  {name.ljust(widths[0])}  {get_task(name).variation_scheme}")
    print("\nsuites (`generate --suite NAME`):")
    width = max(map(len, SUITES))
    for suite, members in SUITES.items():
        print(f"  {suite.ljust(width)}  {SUITE_DESCRIPTIONS[suite]}: {', '.join(members)}")
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
        check_output_folder(out / task, is_generation_file)
        perturb_probabilities(argparse.Namespace(**{**vars(args), "task": task}))  # every task accepts --perturb
    codes = []
    for task in tasks:
        job = argparse.Namespace(**{**vars(args), "task": task, "out": str(out / task),
                                    "episodes": args.episodes_per_task or args.episodes})
        codes.append(generate_job(job))
    if write_report(out) is not None:
        print(f"\ngeneration report of the suite: {out / 'report.md'} (also report.json, report.png)")
    return max(codes)


def generate_job(args) -> int:
    """One task's job from the command line: checked, run with a progress bar, summarised."""
    from tqdm import tqdm

    job = generation_job(args)
    check_output_folder(job.out, is_generation_file)
    bar = tqdm(total=len(job.requests()), desc=f"{job.task}/{job.split}", unit="episode", file=sys.stderr)
    outcomes = []

    def progress(outcome) -> None:
        outcomes.append(outcome)
        bar.update(1)
        bar.set_postfix(kept=sum(o.kept for o in outcomes), failed=sum(not o.kept for o in outcomes))

    try:
        summary = run_job(job, progress)
    except OSError as exc:
        bar.close()
        if not outcomes:
            raise UsageError(f"--out {job.out}: cannot write there ({exc.strerror})") from None
        kept = sum(o.kept for o in outcomes)
        print(f"demo-factory generate: error: writing to {job.out} failed ({exc.strerror}); episodes finished "
              f"before it: {kept}, all complete and valid; fix the cause and re-run the same command to resume",
              file=sys.stderr)
        return 1
    bar.close()
    print(summary_text(summary, job.out))
    write_report(job.out)
    return 0 if summary["kept"] > 0 else 1


def generation_job(args) -> GenerationJob:
    """The job the ``generate`` arguments describe (named variations checked against the split)."""
    named = named_variations(args)
    split = args.split or ("test" if named else "train")
    for variation in named:
        try:
            get_task(args.task).check_split_membership(variation, split)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    episodes = args.episodes_per_variation * len(named) if args.episodes_per_variation else args.episodes
    job = GenerationJob(task=args.task, split=split, episodes=episodes, out=Path(args.out), seed=args.seed,
                        variations=named, image_size=tuple(args.image_size), dense_fps=args.dense_fps,
                        workers=args.workers, shard=args.shard, executor=args.executor, address=args.address,
                        perturb=perturb_probabilities(args))
    job.command = job.command_line([f"--variation={v}" for v in args.variation or []]
                                   + (["--variations-from", args.variations_from] if args.variations_from else [])
                                   + (["--episodes-per-variation", str(args.episodes_per_variation)]
                                      if args.episodes_per_variation else []))
    return job


def perturb_probabilities(args) -> dict[str, float]:
    """``--perturb`` for the job's task: {factor: probability}."""
    if not args.perturb:
        return {}
    from demo_factory.rollout.perturbations import parse_perturb_option

    try:
        return parse_perturb_option(args.perturb, get_task(args.task))
    except ValueError as exc:
        raise UsageError(f"--perturb: {exc}") from None


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
                                description="List the tasks, their categories (the HiveFormer paper's nine, a task may be "
                                            "in several), variation counts and train/test split sizes, and the "
                                            "suites (one per category among them).")
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
                       help="every task of a suite, each into OUT/<task>/ as its own job: ten_tasks, categories (one task "
                            "per category of the HiveFormer paper) or a category (e.g. motion_planner); "
                            "`demo-factory tasks` lists them")
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
    gen.add_argument("--perturb", metavar="NAME[=P],...",
                     help="domain randomisation: each episode gets each named perturbation with probability P "
                          "(default 0.5), drawn from its seed and recorded in its metadata; `all` names every one "
                          "that applies to the task, `visual`, `shape` or `event` those of a kind (docs/robustness.md "
                          "lists them)")
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
