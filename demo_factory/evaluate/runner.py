"""Closed-loop evaluation: rollouts per split, results as JSON, a paper-style table and a chart."""

from __future__ import annotations

import json
from collections import Counter, defaultdict
from dataclasses import asdict
from pathlib import Path

import numpy as np

from demo_factory.convert.converter import read_dataset_provenance
from demo_factory.evaluate.env import KEYFRAME, EvalEpisode, KeyframeEnv, evaluation_seed
from demo_factory.record import FORMAT_VERSION, EpisodeInfo, EpisodeWriter, Keyframe, library_versions
from demo_factory.rollout.scene import start_views

# The HiveFormer paper's success rates (%) for its multi-variation tasks, for the results table.
PAPER_RESULTS = {
    "push_buttons": {"train": 100.0, "test_unseen_synthetic": 86.3, "test_unseen_corrupted": 85.6,
                     "test_unseen_human": 74.2},
    "tower": {"train": 77.4, "test_unseen_synthetic": 56.2, "test_unseen_corrupted": 53.6,
              "test_unseen_human": 24.1},
}

# The paper's Table 1 (the ten tasks of the `ten_tasks` suite, ~100 demonstrations a task): averages over the tasks.
PAPER_TASK_AVERAGES = {
    "ten_tasks": {"HiveFormer, multi-task (paper)": 83.3, "HiveFormer, single-task (paper)": 88.4,
                  "LanCon-Learn with history (paper)": 57.4},
}


def split_episodes(dataset_split_root: Path, split: str, count: int, base_seed: int = 0) -> list[EvalEpisode]:
    """Evaluation episodes for one converted split: ``count`` per task (a multi-task dataset holds several), its
    (variation, instruction) pairs cycled, each in a fresh scene from an evaluation seed (never a generation seed)."""
    _, provenance = read_dataset_provenance(dataset_split_root)
    pairs = defaultdict(set)
    for e in provenance["episodes"]:
        pairs[e.get("task", provenance["task"])].add((e["variation_id"], e["instruction"]))
    episodes = []
    for task, task_pairs in sorted(pairs.items()):
        ordered = sorted(task_pairs)
        episodes += [EvalEpisode(task, split, *ordered[i % len(ordered)], evaluation_seed(base_seed, task, split, i))
                     for i in range(count)]
    return episodes


def dataset_export(dataset_split_root: Path) -> dict:
    """How a converted split was exported: ``{"action_space": "keyframe" | "joints" | "ee", "fps": control
    rate, "longest_seconds": the longest episode's duration}`` (from ``meta/info.json``)."""
    info, provenance = read_dataset_provenance(dataset_split_root)
    frames = [e["frames"] for e in provenance["episodes"] if "frames" in e]
    if provenance.get("granularity") != "dense":
        return {"action_space": KEYFRAME, "fps": info["fps"], "longest_seconds": None}
    return {"action_space": provenance.get("action_space", "joints"), "fps": info["fps"],
            "longest_seconds": max(frames) / info["fps"] if frames else None}


def evaluate_episode(env: KeyframeEnv, policy, episode: EvalEpisode, record_path: Path | None = None) -> dict:
    """One rollout; returns its record (instruction, predicted keyframes or dense actions, outcome).

    With ``record_path`` the rollout is also recorded to MCAP with the generator's recorder: one
    frame per step, and in a keyframe environment the predicted keyframes as keyframe markers.
    """
    env.reset(options={"episode": episode})
    policy.reset(env)
    dense = env.action_space_name != KEYFRAME
    writer = _rollout_writer(env, episode, record_path) if record_path is not None else None
    predicted, info = [], {"is_success": False, "failure_reason": ""}
    while True:
        action = np.asarray(policy.act(env), dtype=np.float64)
        predicted.append([round(float(v), 6) for v in action])
        _, _, terminated, truncated, info = env.step(action)
        if writer is not None:
            writer.write_frame(env.frame)
            if not dense:
                writer.write_keyframe(Keyframe(env.steps, env.frame.time_ns, action[:7], float(action[7] >= 0.5),
                                               env.frame.robot.gripper_pose, "predicted"))
        if terminated or truncated:
            break
    if writer is not None:
        writer.close(env.frame.time_ns, bool(info["is_success"]), [], library_versions())
    return {
        **asdict(episode),
        "success": bool(info["is_success"]),
        "failure_reason": info["failure_reason"] or None,
        "failure_subgoal": info.get("failure_subgoal"),
        "failure_detail": info.get("failure_detail") or None,
        "steps": env.steps,
        "step_limit": env.step_limit,
        **({"action_space": env.action_space_name, "fps": env.fps, "seconds": round(env.steps / env.fps, 3),
            "unreachable_ticks": info.get("unreachable_ticks", 0), "actions": predicted}
           if dense else {"predicted_keyframes": predicted}),
    }


def _rollout_writer(env: KeyframeEnv, episode: EvalEpisode, path: Path) -> EpisodeWriter:
    path.parent.mkdir(parents=True, exist_ok=True)
    variation = env.sim_task.variation(episode.variation_id)
    info = EpisodeInfo(
        format_version=FORMAT_VERSION, task=episode.task, split=episode.split, variation_id=episode.variation_id,
        variation=list(variation.words), episode_seed=episode.seed, instruction=episode.instruction,
        cameras=list(env.frame.cameras), image_size=env.image_size,
        dense_fps=float(getattr(env, "fps", 0.0)) if env.action_space_name != KEYFRAME else 0.0,
        extra={"evaluation": True, **env.sim_task.scene_facts()}, perturbations=env.world.perturbations,
    )
    writer = EpisodeWriter(path, info)
    writer.write_frame(env.frame)
    writer.write_keyframe(Keyframe(0, 0, env.frame.robot.gripper_pose, env.frame.robot.gripper_open,
                                   env.frame.robot.gripper_pose, "start"))
    return writer


def summarise(records: list[dict]) -> dict:
    """Success rate, episodes, mean steps (keyframes or control ticks) and failure reasons, overall and
    per variation. Every failed episode has exactly one reason, so ``failure_reasons`` adds up to the failures
    (most frequent first); ``failure_subgoals`` splits the task's reasons by the instructed sub-goal (1-based)
    where they happened."""
    def block(rows):
        subgoals = defaultdict(Counter)
        for r in rows:
            if not r["success"] and r.get("failure_subgoal") is not None:
                subgoals[r["failure_reason"]][str(r["failure_subgoal"])] += 1
        return {
            "success_rate": float(np.mean([r["success"] for r in rows])) if rows else 0.0,
            "episodes": len(rows),
            "mean_steps": float(np.mean([r["steps"] for r in rows])) if rows else 0.0,
            "failure_reasons": dict(Counter(r["failure_reason"] for r in rows if not r["success"]).most_common()),
            "failure_subgoals": {reason: dict(sorted(counts.items())) for reason, counts in subgoals.items()},
        }

    by_task = defaultdict(list)
    for r in records:
        by_task[r["task"]].append(r)
    if len(by_task) > 1:  # a multi-task evaluation: each task's figures, and their mean as the paper averages them
        per_task = {task: summarise(rows) for task, rows in sorted(by_task.items())}
        return {**block(records), "task_average": float(np.mean([t["success_rate"] for t in per_task.values()])),
                "per_task": per_task}
    by_variation = defaultdict(list)
    for r in records:
        by_variation[r["variation_id"]].append(r)
    return {**block(records), "per_variation": {str(v): block(rows) for v, rows in sorted(by_variation.items())}}


# Splits whose sentences differ from episode to episode and are worth reading one by one.
PER_SENTENCE_SPLITS = ("test_unseen_paraphrased", "test_unseen_human")


def per_sentence(records: list[dict]) -> list[dict]:
    """Each instruction of a split's episodes: its variation, episodes, successes and failure reasons, the
    sentences that fail most first."""
    by_sentence = defaultdict(list)
    for r in records:
        by_sentence[(r["instruction"], r["task"], r["variation_id"])].append(r)
    rows = [{"instruction": text, "task": task, "variation_id": variation, "episodes": len(rows),
             "successes": sum(r["success"] for r in rows),
             "failure_reasons": dict(Counter(r["failure_reason"] for r in rows if not r["success"]).most_common())}
            for (text, task, variation), rows in by_sentence.items()]
    return sorted(rows, key=lambda row: (row["successes"] / row["episodes"], row["instruction"]))


def sentence_table(split: str, summary: dict) -> str:
    """A split's sentences one by one (the failing first), or "" for splits without ``per_sentence``."""
    if "per_sentence" not in summary:
        return ""
    lines = [f"\n## {split}: per sentence\n", "| sentence | variation | episodes | succeeded | failures |",
             "|---|---:|---:|---:|---|"]
    lines += [f"| {row['instruction'].replace('|', '/')} | {row['variation_id']} | {row['episodes']} | "
              f"{row['successes']} | {', '.join(f'{k}: {v}' for k, v in row['failure_reasons'].items())} |"
              for row in summary["per_sentence"]]
    return "\n".join(lines) + "\n"


def write_results(out: Path, policy_name: str, task: str, results: dict[str, dict], control: dict | None = None,
                  robustness: dict[str, dict[str, dict]] | None = None) -> None:
    """``results.json``, ``results.md`` (paper layout: rows = policy, columns = split) and a PNG chart;
    ``control`` (how the policy acted: action space, rate, time limit) goes into ``results.json``; ``robustness``
    ({factor: {split: summary}}, ``eval --perturb``) into both, as a table beside the unperturbed figures."""
    out.mkdir(parents=True, exist_ok=True)
    body = {"policy": policy_name, "task": task, **({"control": control} if control else {}), "splits": results,
            **({"perturbations": robustness} if robustness else {})}
    (out / "results.json").write_text(json.dumps(body, indent=2) + "\n")
    splits = list(results)
    header = "| policy | " + " | ".join(splits) + " |\n|---|" + "---|" * len(splits) + "\n"
    row = f"| {policy_name} | " + " | ".join(f"{100 * results[s]['success_rate']:.1f}" for s in splits) + " |\n"
    paper = dict(PAPER_RESULTS.get(task, {}))
    if "test_unseen_synthetic" in paper:  # without a dataset, "test" = unseen variations, synthetic text
        paper["test"] = paper["test_unseen_synthetic"]
    if any(s in paper for s in splits):
        row += "| HiveFormer (paper) | " + " | ".join(f"{paper[s]:.1f}" if s in paper else "–" for s in splits) + " |\n"
    episodes = ", ".join(f"{s}: {results[s]['episodes']}" for s in splits)
    (out / "results.md").write_text(
        f"# Closed-loop success rate (%) — {task}\n\n{header}{row}\nEpisodes per split: {episodes}.\n"
        "Paper figures: HiveFormer (CoRL 2022), Table 3 (seen = train variations).\n" + failure_table(results)
        + "".join(task_table(policy_name, task, split, summary) for split, summary in results.items())
        + "".join(sentence_table(split, summary) for split, summary in results.items())
        + robustness_table(results, robustness or {})
    )
    _bar_chart(out / "results.png", policy_name, task, results)


def robustness_table(results: dict[str, dict], robustness: dict[str, dict[str, dict]]) -> str:
    """Success per split (rows) without and under each perturbation (columns), their average over the factors, and
    the failures under each factor by reason; "" without perturbations."""
    if not robustness:
        return ""
    factors = list(robustness)
    lines = ["\n## Under perturbation: success (%)\n", "| split | none | " + " | ".join(factors) + " | perturbed average |",
             "|---|---:|" + "---:|" * (len(factors) + 1)]
    for split, summary in results.items():
        rates = [100 * robustness[f][split]["success_rate"] for f in factors]
        lines.append(f"| {split} | {100 * summary['success_rate']:.1f} | " + " | ".join(f"{r:.1f}" for r in rates)
                     + f" | {np.mean(rates):.1f} |")
    counts = {factor: sum((Counter(s["failure_reasons"]) for s in summaries.values()), Counter())
              for factor, summaries in robustness.items()}
    reasons = [reason for reason, _ in sum(counts.values(), Counter()).most_common()]
    if reasons:
        lines += ["\n## Under perturbation: failed episodes by reason (all splits)\n",
                  "| factor | " + " | ".join(reasons) + " |", "|---|" + "---:|" * len(reasons)]
        lines += [f"| {factor} | " + " | ".join(str(c.get(r, 0)) for r in reasons) + " |" for factor, c in counts.items()]
    return "\n".join(lines) + "\n"


def contact_sheets(out: Path, plan: dict[str, list[EvalEpisode]], factors, image_size) -> list[Path]:
    """``contact_<factor>.png`` per factor: the first evaluated scene's start, every camera, without (top row)
    and under the factor (bottom row), so a person sees what changed; none without factors."""
    if not factors:
        return []
    episode = next(e for episodes in plan.values() for e in episodes)
    return [contact_sheet(out / f"contact_{factor}.png", episode.task, episode.variation_id, episode.seed, factor,
                          image_size) for factor in factors]


def contact_sheet(path: Path, task_name: str, variation_id: int, seed: int, factor: str, image_size,
                  scale_to: int = 192) -> Path:
    """A PNG of one scene's start, every camera side by side: unperturbed on top, under ``factor`` below, each
    row labelled; small images are enlarged (nearest pixel) to ``scale_to`` pixels high."""
    import cv2

    rows = []
    for label, names in (("unperturbed", ()), (factor, (factor,))):
        views = start_views(task_name, variation_id, seed, names, image_size)
        scale = max(1, scale_to // image_size[0])
        row = np.concatenate([np.kron(image, np.ones((scale, scale, 1), np.uint8)) for image in views.values()], 1)
        banner = np.full((22, row.shape[1], 3), 255, np.uint8)
        cv2.putText(banner, f"{label}   ({', '.join(views)})", (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1,
                    cv2.LINE_AA)
        rows += [banner, row]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(rows, 0)[:, :, ::-1])
    return path


def failure_table(results: dict[str, dict]) -> str:
    """The failed episodes per split by reason (rows: reasons, most frequent first), or "" without failures."""
    splits = list(results)
    totals = Counter()
    for s in splits:
        totals.update(results[s]["failure_reasons"])
    if not totals:
        return ""
    header = "| failure reason | " + " | ".join(splits) + " |\n|---|" + "---:|" * len(splits) + "\n"
    rows = "".join(f"| {reason} | " + " | ".join(str(results[s]["failure_reasons"].get(reason, 0)) for s in splits)
                   + " |\n" for reason, _ in totals.most_common())
    failed = "| **failed episodes** | " + " | ".join(
        str(sum(results[s]["failure_reasons"].values())) for s in splits) + " |\n"
    return f"\n## Failed episodes by reason\n\n{header}{rows}{failed}"


def task_table(policy_name: str, suite: str, split: str, summary: dict) -> str:
    """A multi-task split in the paper's Table 1 layout (a row per policy, a column per task, their average), then
    its failures per task and reason; "" for a single task."""
    if "per_task" not in summary:
        return ""
    tasks = summary["per_task"]
    reasons = Counter()
    for figures in tasks.values():
        reasons.update(figures["failure_reasons"])
    lines = [f"\n## {split}: success per task (%)\n", "| policy | " + " | ".join(tasks) + " | average |",
             "|---|" + "---:|" * (len(tasks) + 1),
             f"| {policy_name} | " + " | ".join(f"{100 * t['success_rate']:.1f}" for t in tasks.values())
             + f" | {100 * summary['task_average']:.1f} |"]
    lines += [f"| {name} | " + " | ".join("–" for _ in tasks) + f" | {average:.1f} |"
              for name, average in PAPER_TASK_AVERAGES.get(suite, {}).items() if split in ("train", "val")]
    if reasons:
        lines += [f"\n## {split}: failed episodes per task and reason\n",
                  "| task | episodes | " + " | ".join(reason for reason, _ in reasons.most_common()) + " |",
                  "|---|---:|" + "---:|" * len(reasons)]
        lines += [f"| {name} | {t['episodes']} | "
                  + " | ".join(str(t["failure_reasons"].get(reason, 0)) for reason, _ in reasons.most_common()) + " |"
                  for name, t in tasks.items()]
    return "\n".join(lines) + "\n"


def _bar_chart(path: Path, policy_name: str, task: str, results: dict[str, dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    splits = list(results)
    tasks = list(results[splits[0]].get("per_task", {}))
    if tasks:  # a multi-task evaluation: a group of bars per task, one bar per split
        figure, axis = plt.subplots(figsize=(0.9 * len(tasks) * len(splits) + 2, 3.8), dpi=100)
        width = 0.8 / len(splits)
        for k, split in enumerate(splits):
            heights = [100 * results[split]["per_task"].get(t, {}).get("success_rate", 0.0) for t in tasks]
            bars = axis.bar(np.arange(len(tasks)) + k * width, heights, width, label=split)
            axis.bar_label(bars, fmt="%.0f", fontsize=7)
        axis.set_xticks(np.arange(len(tasks)) + 0.4 - width / 2, tasks, fontsize=7)
        axis.legend(fontsize=7)
    else:
        figure, axis = plt.subplots(figsize=(1.6 * len(splits) + 2, 3.2), dpi=100)
        bars = axis.bar(splits, [100 * results[s]["success_rate"] for s in splits], color="#4C72B0")
        axis.bar_label(bars, fmt="%.0f%%")
    axis.set_ylim(0, 105)
    axis.set_ylabel("success rate (%)")
    axis.set_title(f"{task}: {policy_name}")
    axis.tick_params(axis="x", labelrotation=15)
    figure.tight_layout()
    figure.savefig(path, metadata={"Software": None})
    plt.close(figure)
