"""``demo-factory eval``: closed-loop success rates per split for a policy checkpoint or a reference."""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from demo_factory.tasks import SPLITS, TASKS

TASK_SPLITS = SPLITS  # without a dataset: the task's own train / test variations, synthetic instructions


class EvalUsageError(Exception):
    """Bad evaluation input: one line, exit code 2, nothing written."""


def add_parser(commands) -> argparse.ArgumentParser:
    from demo_factory.cli import image_size, positive_int

    parser = commands.add_parser(
        "eval", help="evaluate a policy closed-loop, per split",
        description="Roll a keyframe policy out in the tasks it was trained on: each predicted keyframe is "
                    "reached with the seeded OMPL planner, then the gripper is actuated. Writes results.json, "
                    "results.md (paper layout), results.png and episodes.jsonl.",
    )
    who = parser.add_mutually_exclusive_group(required=True)
    who.add_argument("--policy.path", dest="policy_path", help="a LeRobot checkpoint (…/pretrained_model)")
    who.add_argument("--expert", action="store_true", help="the scripted expert as a reference policy (scores 100%%)")
    who.add_argument("--current-pose", action="store_true",
                     help="a floor reference that always predicts the current pose (scores 0%%)")
    parser.add_argument("--dataset", help="a converted dataset folder (holds one folder per split); episodes "
                                          "use each split's variations and instructions")
    parser.add_argument("--splits", help="comma-separated splits (default: every split of the dataset; "
                                         f"without --dataset: {','.join(TASK_SPLITS)})")
    parser.add_argument("--task", choices=list(TASKS), help="task, when no --dataset is given")
    parser.add_argument("--episodes", type=positive_int, default=100, help="episodes per split (default: 100)")
    parser.add_argument("--seed", type=int, default=0, help="base evaluation seed (default: 0)")
    parser.add_argument("--step-slack", type=int, default=2,
                        help="extra steps beyond the expert's keyframe count (default: 2)")
    parser.add_argument("--image-size", type=image_size, help="camera size (default: the dataset's, else 128)")
    parser.add_argument("--device", default="cpu", help="torch device for the policy (default: cpu)")
    parser.add_argument("--record", action="store_true", help="also record every rollout to MCAP under OUT/rollouts")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    parser.set_defaults(run=run)
    return parser


def _plan(args) -> tuple[str, dict[str, list], tuple[int, int]]:
    from demo_factory.evaluate.env import default_episodes
    from demo_factory.evaluate.runner import split_episodes

    if args.dataset is None:
        if args.task is None:
            raise EvalUsageError("give --dataset (a converted dataset) or --task (the task's own variations)")
        splits = (args.splits or ",".join(TASK_SPLITS)).split(",")
        unknown = [s for s in splits if s not in TASK_SPLITS]
        if unknown:
            raise EvalUsageError(f"unknown split {unknown[0]!r} without --dataset; accepted: {', '.join(TASK_SPLITS)}")
        plan = {s: default_episodes(args.task, s, args.episodes, args.seed) for s in splits}
        return args.task, plan, args.image_size or (128, 128)
    root = Path(args.dataset)
    if not root.is_dir():
        raise EvalUsageError(f"--dataset {root}: no such folder")
    available = sorted(p.name for p in root.iterdir() if (p / "meta" / "info.json").is_file())
    if not available:
        raise EvalUsageError(f"--dataset {root}: holds no converted split folders")
    splits = args.splits.split(",") if args.splits else available
    unknown = [s for s in splits if s not in available]
    if unknown:
        raise EvalUsageError(f"--splits: {unknown[0]!r} is not in {root}; accepted: {', '.join(available)}")
    plan = {}
    for split in splits:
        try:
            plan[split] = split_episodes(root / split, split, args.episodes, args.seed)
        except (FileNotFoundError, ValueError, KeyError) as exc:
            raise EvalUsageError(str(exc)) from None
    tasks = {episodes[0].task for episodes in plan.values()}
    if len(tasks) != 1:
        raise EvalUsageError(f"--dataset {root}: splits of several tasks ({', '.join(sorted(tasks))})")
    task = tasks.pop()
    if args.task and args.task != task:
        raise EvalUsageError(f"--task {args.task} does not match the dataset's task {task}")
    info = json.loads((root / splits[0] / "meta" / "info.json").read_text())
    shapes = [f["shape"] for k, f in info["features"].items() if k.startswith("observation.images.")]
    size = args.image_size or (tuple(shapes[0][:2]) if shapes else (128, 128))
    return task, plan, size


def run(args) -> int:
    from tqdm import tqdm

    from demo_factory.evaluate.env import KeyframeEnv
    from demo_factory.evaluate.policies import CurrentPosePolicy, ExpertPolicy, LeRobotKeyframePolicy
    from demo_factory.evaluate.runner import run_episode, summarise, write_results

    try:
        task, plan, size = _plan(args)
        out = Path(args.out)
        if out.exists() and any(out.iterdir()) and not args.overwrite:
            raise EvalUsageError(f"--out {out}: exists and is not empty; pass --overwrite to replace it")
        if args.expert:
            policy = ExpertPolicy()
        elif args.current_pose:
            policy = CurrentPosePolicy()
        else:
            path = Path(args.policy_path)
            if not (path / "config.json").is_file():
                raise EvalUsageError(f"--policy.path {path}: not a LeRobot checkpoint (no config.json)")
            policy = LeRobotKeyframePolicy(path, device=args.device)
    except EvalUsageError as exc:
        print(f"demo-factory eval: error: {exc}", file=sys.stderr)
        return 2
    if out.exists():
        shutil.rmtree(out)
    staging = out.with_name(f".{out.name}.partial")
    shutil.rmtree(staging, ignore_errors=True)
    env = KeyframeEnv(task, image_size=size, step_slack=args.step_slack, episodes=next(iter(plan.values())))
    results, records = {}, []
    try:
        for split, episodes in plan.items():
            rows = []
            bar = tqdm(episodes, desc=f"{policy.name} / {split}", unit="episode", file=sys.stderr)
            for i, episode in enumerate(bar):
                record_path = staging / "rollouts" / split / f"{split}_{i:04d}_var{episode.variation_id:04d}.mcap" \
                    if args.record else None
                rows.append(run_episode(env, policy, episode, record_path))
                bar.set_postfix(success=f"{100 * sum(r['success'] for r in rows) / len(rows):.1f}%")
            bar.close()
            results[split] = summarise(rows)
            records += rows
    finally:
        env.close()
    write_results(staging, policy.name, task, results)
    with open(staging / "episodes.jsonl", "w") as stream:
        for row in records:
            stream.write(json.dumps(row) + "\n")
    staging.rename(out)
    print(f"\n{policy.name} on {task}:")
    for split, summary in results.items():
        reasons = ", ".join(f"{k}: {v}" for k, v in summary["failure_reasons"].items()) or "none"
        print(f"  {split:<24} success {100 * summary['success_rate']:5.1f}%  over {summary['episodes']} episodes, "
              f"mean steps {summary['mean_steps']:.1f}; failures: {reasons}")
    print(f"results: {out / 'results.md'}, {out / 'results.json'}, {out / 'results.png'}")
    return 0
