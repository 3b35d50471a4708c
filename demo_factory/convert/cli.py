"""demo-factory convert: MCAP recordings → LeRobot datasets, one per split, with a card.

Writes OUT/{train,val,test_unseen_synthetic,test_unseen_corrupted,test_unseen_paraphrased,test_unseen_human}/,
each a LeRobot v3.0 dataset with repo id REPO_ID_<split>, plus OUT/README.md (the dataset card). Splits
without episodes are skipped.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from demo_factory.cli_common import positive_int
from demo_factory.convert.converter import ConvertOptions, convert
from demo_factory.convert.features import ACTION_SPACES, DEFAULT_ACTION_SPACE, DEFAULT_CONTROL_FPS, GRANULARITIES
from demo_factory.convert.result import ConvertResult
from demo_factory.convert.usage import act_chunk, gate_command, load_command, quote, train_args, train_policy


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register the ``convert`` sub-command on an argparse ``subparsers`` object."""
    parser = subparsers.add_parser(
        "convert", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
        help="convert MCAP episode recordings to LeRobot v3.0 datasets (one per split) with a dataset card")
    parser.add_argument("--in", dest="inputs", type=Path, nargs="+", required=True, metavar="PATH",
                        help="folders of .mcap recordings (searched recursively) or .mcap files")
    parser.add_argument("--out", type=Path, required=True, help="output folder (must not exist unless --overwrite)")
    parser.add_argument("--repo-id", help="Hub repo id owner/name; each split gets owner/name_<split> "
                                          "(default: local/<name of --out>)")
    parser.add_argument("--granularity", default="keyframe", choices=GRANULARITIES,
                        help="one frame per keyframe (default; for HiveFormer), or the recorded dense frames at a "
                             "fixed control rate (for ACT, diffusion, VLAs; generate with --dense-fps "
                             f"{DEFAULT_CONTROL_FPS})")
    parser.add_argument("--action-space", metavar="SPACE",
                        help=f"dense exports only: the action of each frame, {' or '.join(ACTION_SPACES)}; joints = the 7 "
                             "joint positions + gripper command at the next control tick, ee = the grasp-frame pose "
                             f"(x, y, z, quaternion) + gripper command at the next tick (default: {DEFAULT_ACTION_SPACE})")
    parser.add_argument("--fps", type=int, metavar="N",
                        help="dense exports only: the control rate, a whole divisor of the recorded dense rate "
                             "(every k-th dense frame is kept; default: the recorded rate)")
    parser.add_argument("--val-ratio", type=float, default=0.1,
                        help="fraction of train-variation episodes held out for val (default 0.1)")
    parser.add_argument("--human-instructions", type=Path, metavar="FILE",
                        help="human-written instructions for test variations: the HiveFormer authors' "
                             "annotations.json or demo-factory JSONL (default for push_buttons and tower: the "
                             "paper's annotations.json shipped with demo_factory)")
    parser.add_argument("--task", help="convert only this task's recordings (default: all; several tasks make one "
                                       "multi-task dataset)")
    parser.add_argument("--skip-invalid", action="store_true",
                        help="leave out truncated, corrupt or inconsistent recordings (listed in the summary and card)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    parser.add_argument("--workers", type=positive_int, metavar="N",
                        help="processes writing each split's episode batches, merged in order with LeRobot's "
                             "aggregate_datasets into the dataset one process writes (default: one per CPU core)")
    parser.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    """Run the sub-command."""
    options = ConvertOptions(
        inputs=list(args.inputs), out=args.out, repo_id=args.repo_id or f"local/{args.out.resolve().name}",
        granularity=args.granularity, action_space=args.action_space, fps=args.fps, val_ratio=args.val_ratio, human_instructions=args.human_instructions,
        task=args.task, skip_invalid=args.skip_invalid, overwrite=args.overwrite, progress=args.progress,
        workers=args.workers,
    )
    result = convert(options)  # a ConvertError is a UsageError: one line, exit 2 (cli_common.run_command)
    print(summary(result))
    return 0


def summary(result: ConvertResult) -> str:
    """What was written, what was left out, and how to load and train on it."""
    export = ("keyframes" if result.granularity == "keyframe"
              else f"dense frames at {result.fps} fps, action space {result.action_space}")
    lines = [f"\n{result.task} ({export}): {result.frames_written} frames written to {result.out} in {result.seconds:.1f} s "
             f"({result.frames_written / max(result.seconds, 1e-9):.1f} frames/s)", ""]
    lines.append(f"  {'split':<24}{'episodes':>9}{'frames':>8}{'shortest':>9}  instructions  repo id")
    for s in result.splits:
        lines.append(f"  {s.name:<24}{s.episodes:>9}{s.frames:>8}{s.shortest_episode:>9}  {s.instruction_source:<12}  "
                     f"{s.repo_id}")
    for name, why in result.skipped_splits:
        lines.append(f"  {name:<24}  skipped: {why}")
    if result.human_assignment is not None:
        a = result.human_assignment
        if a.rows_without_episodes:
            lines.append(f"  human instructions: {len(a.rows_without_episodes)} rows of {result.human_file} name "
                         "test variations without recordings (unused)")
        if a.episodes_without_rows:
            lines.append(f"  human instructions: {len(a.episodes_without_rows)} test episodes have no row for their "
                         "variation (not in test_unseen_human)")
    if result.other_tasks:
        lines.append("  other tasks' recordings ignored: " + ", ".join(f"{t} ({n})" for t, n in result.other_tasks.items()))
    if result.invalid:
        lines.append(f"  recordings left out ({len(result.invalid)}):")
        lines += [f"    {p}: {why}" for p, why in result.invalid]
    train = next((s for s in result.splits if s.name == "train"), result.splits[0])
    root = result.out / train.name
    lines += ["", f"Dataset card: {result.out / 'README.md'}", "Load a split:", "  " + load_command(train.repo_id, root)]
    lines += training_lines(result, train, root)
    return "\n".join(lines)


def training_lines(result: ConvertResult, train, root: Path) -> list[str]:
    """The suggested ``lerobot-train`` command for this export, and for dense exports its gate check."""
    policy = train_policy(result.granularity)
    args = train_args(result.granularity, train.repo_id, root, result.cameras, result.image_size, result.fps,
                      train.shortest_episode, Path(f"outputs/train/{policy}_{result.task}"), result.unseen_splits,
                      result.multi_task)
    if result.granularity == "keyframe":
        encoder = ("MiniLM instruction features, which carry to the unseen splits' new instructions"
                   if result.unseen_splits else "one-hot instruction codes")
        recipe = "; make reference-suite's recipe for several tasks" if result.multi_task else ""
        return [f"Train HiveFormer on it (CPU, offline, {encoder}{recipe}; ACT and diffusion need a dense export: "
                "--granularity dense):", "  " + quote(args)]
    chunk, steps = act_chunk(train.shortest_episode, result.fps)
    return [f"Train ACT on it (CPU, offline): chunks of {chunk} actions ({chunk / result.fps:g} s at {result.fps} fps; "
            f"the shortest train episode has {train.shortest_episode} frames), {steps} executed per prediction:",
            "  " + quote(args),
            "Check it first with the third-party gate (pip install lerobot-doctor):",
            "  " + gate_command(root, chunk)]
