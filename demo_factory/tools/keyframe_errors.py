"""How far a policy's predicted keyframes land from the expert's, keyframe by keyframe, in its evaluation episodes.

    python -m demo_factory.tools.keyframe_errors outputs/reference_tower/eval/episodes.jsonl [--split train]

`demo-factory eval` records each episode's `predicted_keyframes` and scene seed. Each scene is rebuilt from its
seed and the task's expert plans it from the start; the k-th predicted keyframe is compared with the plan's k-th
(xy and z distance of the gripper position, angle between the orientations). The first keyframes carry no earlier
error: where the policy first points is measured alone, without replaying anything. Later keyframes are compared
with the plan of the untouched scene, so where the policy moved objects their errors include the scene's.
The last two columns are the medians of a constant prediction, the expert's mean keyframe: a keyframe whose error is
no smaller has not been learnt from what the policy sees. In a multi-task evaluation, pick one task with --task.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from demo_factory.rollout.scene import start_scene
from demo_factory.sim.kinematics import pose_error
from demo_factory.tasks import get_task

IMAGE_SIZE = (16, 16)  # the scene is only planned on, not recorded


def _errors(predicted: np.ndarray, expert: np.ndarray) -> tuple[float, float, float]:
    """xy cm, z cm and rotation degrees between two [x, y, z, qx, qy, qz, qw] poses."""
    return (100 * float(np.linalg.norm(predicted[:2] - expert[:2])), 100 * float(abs(predicted[2] - expert[2])),
            float(np.degrees(pose_error(predicted, expert)[1])))


def _percentiles(errors) -> dict:
    return {name: {q: round(float(np.percentile(column, p)), 2) for q, p in (("median", 50), ("p75", 75), ("p90", 90))}
            for name, column in zip(("xy_cm", "z_cm", "rotation_deg"), np.array(errors).T, strict=True)}


def keyframe_errors(episodes: list[dict]) -> list[dict]:
    """Per keyframe index: the errors of every episode that predicted it -> [{keyframe, episodes, xy_cm, z_cm,
    rotation_deg, constant}]. `constant` holds the same figures for the expert's mean keyframe (mean position, mean
    orientation) predicted in every scene: where the policy's error is no smaller, it has not learnt to place that
    keyframe from what it sees."""
    per_index: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    for episode in episodes:
        task = get_task(episode["task"])
        world = start_scene(task, task.variation(episode["variation_id"]), episode["seed"], image_size=IMAGE_SIZE)
        try:
            plan = [np.asarray(k.pose) for k in task.expert(world)]
        finally:
            world.close()
        for k, (predicted, expert) in enumerate(zip(episode["predicted_keyframes"], plan)):
            per_index.setdefault(k, []).append((np.asarray(predicted[:7]), expert))
    rows = []
    for k, pairs in sorted(per_index.items()):
        experts = np.array([expert for _, expert in pairs])
        mean = np.concatenate([experts[:, :3].mean(0), Rotation.from_quat(experts[:, 3:7]).mean().as_quat()])
        rows.append({"keyframe": k, "episodes": len(pairs),
                     **_percentiles([_errors(predicted, expert) for predicted, expert in pairs]),
                     "constant": _percentiles([_errors(mean, expert) for expert in experts])})
    return rows


def read_episodes(path: Path, split: str, task: str | None = None) -> list[dict]:
    """The evaluation episodes of `split` (and `task`, when given) in `path` (episodes.jsonl); a clear error for
    anything else."""
    try:
        rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise SystemExit(f"keyframe_errors: {path}: not a readable episodes.jsonl of `demo-factory eval` ({error})")
    if not all(isinstance(r, dict) and {"task", "split", "variation_id", "seed", "predicted_keyframes"} <= r.keys()
               for r in rows):
        raise SystemExit(f"keyframe_errors: {path}: not an episodes.jsonl of `demo-factory eval` (each line needs task, "
                         "split, variation_id, seed and predicted_keyframes)")
    splits = sorted({r["split"] for r in rows})
    chosen = [r for r in rows if r["split"] == split]
    if not chosen:
        raise SystemExit(f"keyframe_errors: --split {split!r}: no episode of it in {path} (it holds: {', '.join(splits) or 'none'})")
    if task is not None:
        tasks = sorted({r["task"] for r in chosen})
        chosen = [r for r in chosen if r["task"] == task]
        if not chosen:
            raise SystemExit(f"keyframe_errors: --task {task!r}: no {split} episode of it in {path} (it holds: "
                             f"{', '.join(tasks)})")
    return chosen


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 2)[2],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("episodes", type=Path, help="an evaluation's episodes.jsonl")
    parser.add_argument("--split", default="train", help="which split's episodes (default: train, the seen variations)")
    parser.add_argument("--task", help="only this task's episodes (of a multi-task evaluation; default: all)")
    parser.add_argument("--keyframes", type=int, default=6, help="report the first N keyframe indices (default: 6)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON instead of a table")
    args = parser.parse_args(argv)
    if args.keyframes < 1:
        parser.error(f"--keyframes {args.keyframes}: must be at least 1")
    rows = keyframe_errors(read_episodes(args.episodes, args.split, args.task))[: args.keyframes]
    if args.json:
        json.dump(rows, sys.stdout, indent=1)
        print()
        return
    print(f"{'keyframe':>8} {'episodes':>8}  xy cm (median / p75 / p90)  z cm (median)  rotation deg (median / p90)"
          "  constant: xy cm  rotation deg (medians)")
    for row in rows:
        xy, z, rotation, constant = row["xy_cm"], row["z_cm"], row["rotation_deg"], row["constant"]
        print(f"{row['keyframe']:>8} {row['episodes']:>8}  {xy['median']:6.2f} / {xy['p75']:6.2f} / {xy['p90']:6.2f}"
              f"        {z['median']:6.2f}        {rotation['median']:6.1f} / {rotation['p90']:6.1f}"
              f"            {constant['xy_cm']['median']:6.2f}  {constant['rotation_deg']['median']:6.1f}")


if __name__ == "__main__":
    main()
