"""demo-factory eval: closed-loop success rates per split for a policy checkpoint or a reference.

Roll a policy out in the tasks it was trained on. A keyframe policy's predicted keyframe is reached with the
seeded OMPL planner, then the gripper is actuated; a dense policy (a dataset converted with --granularity
dense) acts at every control tick through the joints' position controllers (inverse kinematics for ee
actions). Writes results.json, results.md (paper layout), results.png and episodes.jsonl.

Keyframe policies (HiveFormer) and dense policies (ACT, diffusion, …) alike: the action space comes
from ``--dataset`` (how its splits were exported), else from ``--action-space``, else from the
dataset the checkpoint was trained on (its ``train_config.json``), else keyframes.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from demo_factory.cli_common import UsageError, image_size, positive_int
from demo_factory.tasks import SPLITS, TASKS

TASK_SPLITS = SPLITS  # without a dataset: the task's own train / test variations, synthetic instructions


@dataclass
class Control:
    """How the policy acts: its action space, and for dense policies the control rate and time limit."""

    action_space: str = "keyframe"
    fps: float = 20
    max_seconds: float = 60.0


def add_parser(commands) -> argparse.ArgumentParser:
    parser = commands.add_parser(
        "eval", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
        help="evaluate a policy closed-loop, per split")
    who = parser.add_mutually_exclusive_group(required=True)
    who.add_argument("--policy.path", dest="policy_path", help="a LeRobot checkpoint (…/pretrained_model)")
    who.add_argument("--expert", action="store_true", help="the scripted expert as a reference policy (scores 100%%)")
    who.add_argument("--current-pose", action="store_true",
                     help="a floor reference that always predicts the current pose (scores 0%%)")
    parser.add_argument("--dataset", help="a converted dataset folder (holds one folder per split); episodes "
                                          "use each split's variations and instructions")
    parser.add_argument("--splits", help="comma-separated splits (default: every split of the dataset; "
                                         f"without --dataset: {','.join(TASK_SPLITS)})")
    parser.add_argument("--task", choices=list(TASKS),
                        help="task, when no --dataset is given; with a multi-task --dataset, evaluate that task only")
    parser.add_argument("--episodes", type=positive_int, default=100,
                        help="episodes per split, of each task in a multi-task dataset (default: 100)")
    parser.add_argument("--seed", type=int, default=0, help="base evaluation seed (default: 0)")
    parser.add_argument("--step-slack", type=int, default=2,
                        help="extra steps beyond the expert's keyframe count (default: 2)")
    parser.add_argument("--image-size", type=image_size, help="camera size (default: the dataset's, else 128)")
    parser.add_argument("--action-space", metavar="SPACE",
                        help="what the policy's 8-d action means: keyframe (the next keyframe's pose + open), joints "
                             "or ee (the next control tick's joint positions or grasp-frame pose, + gripper command); "
                             "default: the --dataset's export, else the dataset the checkpoint was trained on, else "
                             "keyframe")
    parser.add_argument("--fps", type=float, metavar="N",
                        help="dense policies: control ticks per second (default: the dataset's rate, else 20)")
    parser.add_argument("--max-seconds", type=float, metavar="S",
                        help="dense policies: simulated seconds before an episode counts as failed (default: 1.5x "
                             "the dataset's longest expert episode, else 60)")
    parser.add_argument("--device", default="cpu", help="torch device for the policy (default: cpu)")
    parser.add_argument("--perturb", metavar="NAME,...",
                        help="also evaluate every split under each named perturbation, one at a time, on the same "
                             "scenes: a robustness table beside the unperturbed figures and a contact sheet per "
                             "factor; `all`: every one that applies; `visual`, `shape`, `event`: those of a kind "
                             "(docs/robustness.md)")
    parser.add_argument("--record", action="store_true", help="also record every rollout to MCAP under OUT/rollouts")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    parser.set_defaults(run=run)
    return parser


DENSE_TIME_FACTOR = 1.5  # a dense episode may take this much longer than the longest expert episode


def trained_export(checkpoint: Path) -> dict | None:
    """How the dataset a checkpoint was trained on was exported (``runner.dataset_export``), when its
    ``train_config.json`` names a local converted dataset that still exists; else None."""
    from demo_factory.evaluate.runner import dataset_export

    try:
        root = json.loads((checkpoint / "train_config.json").read_text())["dataset"]["root"]
        return dataset_export(Path(root)) if root else None
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _control(args, export: dict | None, source: str) -> Control:
    """The action space, rate and time limit: options first, then the export (``source`` names it)."""
    from demo_factory.evaluate.env import DEFAULT_CONTROL_FPS, EVAL_ACTION_SPACES, KEYFRAME, control_period

    space = args.action_space or (export or {}).get("action_space") or KEYFRAME
    if space not in EVAL_ACTION_SPACES:
        raise UsageError(f"unknown --action-space {space!r}; accepted: {', '.join(EVAL_ACTION_SPACES)}")
    if export is not None and args.action_space and args.action_space != export["action_space"]:
        raise UsageError(f"--action-space {args.action_space} does not match {source}, exported with action space "
                             f"{export['action_space']}")
    dense_export = export if export and export["action_space"] != KEYFRAME else {}
    fps = args.fps or dense_export.get("fps") or DEFAULT_CONTROL_FPS
    try:
        control_period(fps)
    except ValueError as exc:
        raise UsageError(f"--fps: {exc}") from None
    longest = dense_export.get("longest_seconds")
    max_seconds = args.max_seconds or (round(DENSE_TIME_FACTOR * longest, 1) if longest else 60.0)
    if max_seconds <= 0:
        raise UsageError(f"--max-seconds {max_seconds:g} is out of range; accepted: a number of seconds > 0")
    return Control(space, fps, max_seconds)


def _plan(args) -> tuple[str, dict[str, list], tuple[int, int], Control]:
    from demo_factory.convert.converter import read_dataset_provenance
    from demo_factory.evaluate.env import default_episodes
    from demo_factory.evaluate.runner import dataset_export, split_episodes

    checkpoint = Path(args.policy_path) if args.policy_path else None

    if args.dataset is None:
        if args.task is None:
            raise UsageError("give --dataset (a converted dataset) or --task (the task's own variations)")
        splits = (args.splits or ",".join(TASK_SPLITS)).split(",")
        unknown = [s for s in splits if s not in TASK_SPLITS]
        if unknown:
            raise UsageError(f"unknown split {unknown[0]!r} without --dataset; accepted: {', '.join(TASK_SPLITS)}")
        plan = {s: default_episodes(args.task, s, args.episodes, args.seed) for s in splits}
        export = trained_export(checkpoint) if checkpoint is not None and not args.action_space else None
        control = _control(args, export, "the checkpoint's training dataset")
        return args.task, plan, args.image_size or (128, 128), control
    root = Path(args.dataset)
    if not root.is_dir():
        raise UsageError(f"--dataset {root}: no such folder")
    available = sorted(p.name for p in root.iterdir() if (p / "meta" / "info.json").is_file())
    if not available:
        raise UsageError(f"--dataset {root}: holds no converted split folders")
    splits = args.splits.split(",") if args.splits else available
    unknown = [s for s in splits if s not in available]
    if unknown:
        raise UsageError(f"--splits: {unknown[0]!r} is not in {root}; accepted: {', '.join(available)}")
    plan = {}
    for split in splits:
        try:
            plan[split] = split_episodes(root / split, split, args.episodes, args.seed)
        except (FileNotFoundError, ValueError, KeyError) as exc:
            raise UsageError(str(exc)) from None
    tasks = sorted({episode.task for episodes in plan.values() for episode in episodes})
    if args.task and args.task not in tasks:
        raise UsageError(f"--task {args.task} is not in --dataset {root}; accepted: {', '.join(tasks)}")
    if args.task:  # one task of a multi-task dataset
        plan = {split: [e for e in episodes if e.task == args.task] for split, episodes in plan.items()}
        tasks = [args.task]
    task = tasks[0] if len(tasks) == 1 else read_dataset_provenance(root / splits[0])[1]["task"]
    info = json.loads((root / splits[0] / "meta" / "info.json").read_text())
    shapes = [f["shape"] for k, f in info["features"].items() if k.startswith("observation.images.")]
    size = args.image_size or (tuple(shapes[0][:2]) if shapes else (128, 128))
    exports = {split: dataset_export(root / split) for split in splits}
    spaces = sorted({e["action_space"] for e in exports.values()})
    if len(spaces) != 1:
        raise UsageError(f"--dataset {root}: splits of several action spaces ({', '.join(spaces)})")
    export = exports[splits[0]]
    longest = [e["longest_seconds"] for e in exports.values() if e["longest_seconds"]]
    export = {**export, "longest_seconds": max(longest) if longest else None}
    return task, plan, size, _control(args, export, f"--dataset {root}")


def _factors(text: str | None, plan: dict[str, list]) -> tuple[str, ...]:
    """``--perturb`` checked against every task evaluated (``all``: the factors every one of them accepts)."""
    from demo_factory.rollout.perturbations import parse_perturbations
    from demo_factory.tasks import get_task

    if not text:
        return ()
    tasks = sorted({e.task for episodes in plan.values() for e in episodes})
    try:
        accepted = [parse_perturbations(text, get_task(t)) for t in tasks]
    except ValueError as exc:
        raise UsageError(f"--perturb: {exc}") from None
    return tuple(f for f in accepted[0] if all(f in a for a in accepted)) if accepted else ()


def run(args) -> int:
    from tqdm import tqdm

    from demo_factory.evaluate.env import make_env
    from demo_factory.evaluate.policies import CurrentPosePolicy, ExpertPolicy, LeRobotPolicy
    from demo_factory.evaluate.runner import (
        PER_SENTENCE_SPLITS,
        contact_sheets,
        evaluate_episode,
        per_sentence,
        summarise,
        write_results,
    )

    if args.policy_path is not None and not (Path(args.policy_path) / "config.json").is_file():
        raise UsageError(f"--policy.path {args.policy_path}: not a LeRobot checkpoint (no config.json)")
    task, plan, size, control = _plan(args)
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise UsageError(f"--out {out}: exists and is not empty; pass --overwrite to replace it")
    if args.expert:
        policy = ExpertPolicy()
    elif args.current_pose:
        policy = CurrentPosePolicy()
    else:
        path = Path(args.policy_path)
        trained = trained_export(path)
        if trained is not None and trained["action_space"] != control.action_space:
            raise UsageError(f"--policy.path {path}: trained on a {trained['action_space']} export, but the "
                             f"evaluation's action space is {control.action_space}")
        try:
            policy = LeRobotPolicy(path, device=args.device)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    if out.exists():
        shutil.rmtree(out)
    staging = out.with_name(f".{out.name}.partial")
    shutil.rmtree(staging, ignore_errors=True)
    factors = _factors(args.perturb, plan)
    conditions = {"": plan} | {f: {s: [replace(e, perturbations=(f,)) for e in es] for s, es in plan.items()}
                               for f in factors}
    by_condition: dict[str, dict[str, list[dict]]] = {c: {split: [] for split in plan} for c in conditions}
    for each_task in sorted({e.task for episodes in plan.values() for e in episodes}):  # one scene at a time
        env = make_env(each_task, control.action_space, fps=control.fps, max_seconds=control.max_seconds,
                       step_slack=args.step_slack, image_size=size,
                       episodes=[e for episodes in plan.values() for e in episodes if e.task == each_task])
        try:
            for condition, condition_plan in conditions.items():
                for split, episodes in condition_plan.items():
                    mine: list[dict] = []  # this task's rows of the split
                    done = by_condition[condition][split]
                    bar = tqdm([e for e in episodes if e.task == each_task], unit="episode", file=sys.stderr,
                               desc=f"{policy.name} / {split}" + (f" / {each_task}" if each_task != task else "")
                               + (f" / {condition}" if condition else ""))
                    for episode in bar:
                        name = (f"{split}_{len(done) + len(mine):04d}_{episode.task}_var{episode.variation_id:04d}"
                                + (f"_{condition}" if condition else "") + ".mcap")
                        record_path = staging / "rollouts" / split / name if args.record else None
                        mine.append(evaluate_episode(env, policy, episode, record_path))
                        bar.set_postfix(success=f"{100 * sum(r['success'] for r in mine) / len(mine):.1f}%")
                    bar.close()
                    done += mine
        finally:
            env.close()
    robustness = {f: {split: summarise(split_rows) for split, split_rows in by_condition[f].items()} for f in factors}
    rows = by_condition[""]
    results = {split: summarise(split_rows) for split, split_rows in rows.items()}
    for split in PER_SENTENCE_SPLITS:
        if rows.get(split):
            results[split]["per_sentence"] = per_sentence(rows[split])
    records = [row for condition in by_condition.values() for split_rows in condition.values() for row in split_rows]
    write_results(staging, policy.name, task, results, asdict(control), robustness)
    contact_sheets(staging, plan, factors, size)
    with open(staging / "episodes.jsonl", "w") as stream:
        for row in records:
            stream.write(json.dumps(row) + "\n")
    staging.rename(out)
    acting = ("one predicted keyframe per step" if control.action_space == "keyframe" else
              f"{control.action_space} actions at {control.fps:g} fps, at most {control.max_seconds:g} s per episode")
    print(f"\n{policy.name} on {task} ({acting}):")
    for split, summary in results.items():
        reasons = ", ".join(f"{k}: {v}" for k, v in summary["failure_reasons"].items()) or "none"
        print(f"  {split:<24} success {100 * summary['success_rate']:5.1f}%  over {summary['episodes']} episodes, "
              f"mean steps {summary['mean_steps']:.1f}; failures: {reasons}")
        for name, figures in summary.get("per_task", {}).items():
            reasons = ", ".join(f"{k}: {v}" for k, v in figures["failure_reasons"].items()) or "none"
            print(f"    {name:<36} {100 * figures['success_rate']:5.1f}%  over {figures['episodes']}; failures: {reasons}")
        if "per_sentence" in summary:
            never = sum(not row["successes"] for row in summary["per_sentence"])
            print(f"    {len(summary['per_sentence'])} sentences, {never} never followed (each in results.md)")
        if "task_average" in summary:
            print(f"    {'average over the tasks':<36} {100 * summary['task_average']:5.1f}%")
    if robustness:
        print("  under perturbation (success %, split by split):")
        for factor, summaries in robustness.items():
            figures = "  ".join(f"{split} {100 * summary['success_rate']:5.1f}" for split, summary in summaries.items())
            print(f"    {factor:<22} {figures}")
        print(f"  contact sheets: {out}/contact_<factor>.png")
    print(f"results: {out / 'results.md'}, {out / 'results.json'}, {out / 'results.png'}")
    return 0
