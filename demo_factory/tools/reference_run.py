"""The reference run: proof, on one CPU, that a policy trained on our datasets succeeds closed loop.

    python -m demo_factory.tools.reference_run [--out outputs/reference] [--steps 1500] ...   (or `make reference`)
    python -m demo_factory.tools.reference_run --policy act [--out outputs/reference_act]     (or `make reference-act`)
    python -m demo_factory.tools.reference_run --task tower [--out outputs/reference_tower]   (or `make reference-tower`)
    python -m demo_factory.tools.reference_run --unseen [--out outputs/reference_unseen]     (or `make reference-unseen`)
    python -m demo_factory.tools.reference_run --suite ten_tasks [--out outputs/reference_ten_tasks]   (`make reference-suite`)
    python -m demo_factory.tools.reference_run --unseen --task tower   (`make reference-tower-unseen`)
    python -m demo_factory.tools.reference_run --unseen --ablation no_history   (one of the paper's ablation rows)

The whole chain with the real components and the commands a user runs: `demo-factory generate` (push_buttons
or tower demonstrations of a few train variations, one of each length, plus test-variation episodes for the
unseen splits; the seen run gives its one-colour variation more episodes) → `demo-factory convert` →
`lerobot-train` → `demo-factory eval` on new scene seeds, per split. HiveFormer's history holds the longest
training episode (push_buttons 10 keyframes, tower 19). With `--curve N` the training also saves N - 1
intermediate checkpoints and each of the N is evaluated on validation scenes of the seen variations (scene
seeds of their own, not the test ones): a learning curve that tells how far a longer run would go, and the
checkpoint that does best there is the one evaluated on the test scenes, as the authors keep the checkpoint
that does best on validation. HiveFormer (the default) trains on the keyframe export; ACT on the dense
export (20 fps, joint-position actions), with the command the converter suggests for it. Every stage writes
into its own folder under --out and is skipped when that folder is complete, so an interrupted run resumes
where it stopped; the training itself resumes from its last checkpoint (`lerobot-train --resume=true`; one
at least every 500 steps).
With `--unseen` the run is built to show instructions followed that were never seen: the paper's train
variations 0-99 (6 episodes each), pretrained MiniLM run with a causal mask (`minilm_causal`), windows
as `make reference` with the authors' 4-channel CNN stem, the test episodes on the paper's test variations that
the authors' human-written sentences name, and a learning curve of both the seen and the unseen-synthetic success
(push_buttons, or tower with `--task tower`); `--ablation NAME` takes one part of the model out of that run.
With `--suite NAME` it trains one multi-task policy over a suite's tasks in the paper's Table 1 setting (each
task's first train variation, its synthetic instructions) and reports success per task and their average.
At the end it prints the results table (also `OUT/eval/results.md`, `results.json`, `results.png`)
and writes `OUT/reference_run.json` (configuration, stage wall times, success rates) and, with a
learning curve, prints it and plots it to `OUT/learning_curve.png`.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from lerobot.common.train_utils import get_step_checkpoint_dir
from lerobot_policy_hiveformer.configuration_hiveformer import TEXT_ENCODERS

from demo_factory.convert.converter import read_dataset_provenance
from demo_factory.convert.usage import MULTI_TASK_RECIPE, MULTI_TASK_STEPS, act_chunk, act_train_args, policy_flags
from demo_factory.instructions import shipped_human_instructions
from demo_factory.rollout.perturbations import parse_perturb_option
from demo_factory.suites import SUITES
from demo_factory.tasks import TASKS, get_task

BIN = Path(sys.executable).parent
# Seen variations, one of each length: 205 (maroon) is past the paper's 0-199 (its train ids have no
# one-button variation); 24 (navy, cyan) and 2 (blue, olive, orange) are paper train variations.
DEFAULT_VARIATIONS = ("205", "24", "2")
# tower: paper train variations 46 (green), 0 (black, yellow), 1 (white, gray, red): 7, 13, 19 keyframes.
TASK_VARIATIONS = {"push_buttons": DEFAULT_VARIATIONS, "tower": ("46", "0", "1")}
# The CPU configuration: camera size, batch, steps, instruction encoder.
REFERENCE_IMAGE_SIZE = 64
REFERENCE_BATCH_SIZE = 16
REFERENCE_STEPS = 1500
REFERENCE_TEXT_ENCODER = "one_hot"
# HiveFormer runs validate a checkpoint every this many steps by default: success swings by tens of points
# between checkpoints 100 steps apart at the authors' constant learning rate (seed 2: 77.5, 30.0, 45.0, 87.5 %
# at steps 800-1100; docs/reference/push_buttons.md), so the run keeps the one that does best on validation
# scenes, as the authors do.
VALIDATE_EVERY = 100
# Keyframes of history: by default the longest training episode (push_buttons: 10), as the authors feed
# whole episodes; with fewer, windows that slide past the episode start look alike.
REFERENCE_HISTORY = 10
# Each policy's run: seen variations, episodes, steps, batch, evaluation episodes. ACT takes no
# instruction, so it learns one variation (blue: one button) and is evaluated on it alone.
PRESETS = {
    "hiveformer": {"variations": DEFAULT_VARIATIONS, "episodes_per_variation": 40, "test_episodes": 20,
                   "steps": REFERENCE_STEPS, "batch_size": REFERENCE_BATCH_SIZE, "eval_episodes": 40},
    "act": {"variations": ("blue",), "episodes_per_variation": 50, "test_episodes": 0,
            "steps": 1000, "batch_size": 8, "eval_episodes": 20},
}
# `make reference`: the one-button variation gets EXTRA_EPISODES more episodes (100 in all; generation seed
# EXTRA_SEED). Its 4-keyframe episodes give it 19 % of the training windows, and only its scenes with a navy or blue
# distractor (about 1 in 4) tell the instruction apart from a shortcut that fits every other training scene: press
# navy, else blue, else maroon (the variations' first targets). On 40 episodes, 10 of the 23 test failures of seeds
# 1000 / 2 / 3 press navy or blue where maroon is asked; on 100, none (docs/reference/push_buttons.md). Tower's
# one-cube variation (46, green) has the same shortcut (pick black, else white, else green) and gets 80 more (160 in
# all).
EXTRA_EPISODES = {"push_buttons": 60, "tower": 80}
EXTRA_SEED = 5
# --unseen: the paper's 100 train ids 0-99, 6 episodes each (600); the test episodes are one per test variation that
# the authors' human-written sentences name (51 of the 100), so the human split is the paper's. MiniLM's transformer
# run with a causal mask (`minilm_causal`: a token's features hold the words before it, as CLIP's): trained on the
# instruction grammar, seed 1000 scores 67.5 % unseen synthetic, 52.5 held-out phrasings and 57.5 human where the
# context-free word pieces (`minilm_words`) score 47.5, 40.0 and 47.5 (docs/reference/unseen.md). Validated every
# 2000 steps, as the curve still rises at 8000 and each validation costs ~1 min.
UNSEEN = {"episodes_per_variation": 6, "test_episodes_per_variation": 1,
          "text_encoder": "minilm_causal", "steps": 8000, "curve": 4, "eval_episodes": 40}
CURVE_SPLITS = {False: ("train",), True: ("train", "test_unseen_synthetic")}
# --ablation NAME: the paper's ablation rows, each `make reference-unseen`'s chain (same data, steps and seed) with one
# part of the model taken out (HiveformerConfig fields): the history, the instruction as a token sequence (averaged
# into one token, the paper's "Avg."), the patch-column embedding E_x, both patch-position embeddings E_x and E_y, the
# pretrained instruction features (one-hot codes).
ABLATIONS = {"no_history": {"use_history": False}, "averaged_instruction": {"instruction_as_sequence": False},
             "no_ex": {"use_column_embeddings": False}, "no_ex_ey": {"use_position_embeddings": False},
             "one_hot": {"text_encoder": "one_hot"}}
# Windows ending at every frame and the 7-channel CNN stem (HiveformerConfig fields), with the compiled CPU loops.
RECIPE = {"whole_episodes": False, "stem_point_cloud": True, "cpu_kernels": True}
# `make reference-unseen`: windows ending at every frame, the authors' 4-channel CNN stem, the plugin's instruction
# position embeddings, a learning rate of 2e-3 held through the early plateau (position loss ~0.005, the attention
# between the buttons) and annealed to 0 over the last 3000 steps (constant_then_cosine), and the heatmap
# cross-entropy beside the authors' losses, which ends that plateau at ~1,500 steps instead of ~4,000-5,000 (each
# seed's figures and the settings compared: docs/reference/unseen.md; every run: docs/results/runs.csv).
UNSEEN_RECIPE = RECIPE | {"stem_point_cloud": False, "optimizer_lr": 2e-3, "lr_schedule": "constant_then_cosine",
                          "heatmap_loss_weight": 0.1}
# `make reference`: without instruction position embeddings. Its last checkpoint scores 97.5 / 52.5 /
# 90.0 % on seeds 1000 / 2 / 3 (an annealed learning rate does not make that robust); the checkpoint kept by
# validation 97.5 / 90.0 / 95.0 % (docs/reference/push_buttons.md). With the plugin's defaults (the authors':
# whole episodes, 4-channel stem) seed 1000 scores 52.5 % after 1500 steps (the three-button variation 0/16,
# every failure its third press).
SEEN_RECIPE = RECIPE | {"instruction_position_embeddings": False}
# `make reference-tower`: SEEN_RECIPE with the learning rate annealed to 0 from a peak of 2e-3, on 80 episodes a
# variation (the one-cube one 160: EXTRA_EPISODES), for 6000 steps, validated every 1200. At a constant rate for
# 2400 steps (37.5 % seen) its first grasp was 1.5 cm off the expert's; annealed over 4800 steps, 0.33 cm
# (tools/keyframe_errors.py). Annealed from 1e-3 for 6000 steps: 87.5 / 77.5 % on seeds 1000 / 2, from 5e-4 45.0 %
# (seed 1000); with the extra one-cube episodes, from 1e-3 77.5 / 87.5 %, from 2e-3 80.0 / 85.0 %
# (docs/reference/tower.md).
TOWER = {"episodes_per_variation": 80, "steps": 6000, "curve": 5}
TOWER_RECIPE = SEEN_RECIPE | {"lr_schedule": "cosine", "optimizer_lr": 2e-3}
# `make reference-suite` (--suite NAME): one multi-task HiveFormer over a suite's tasks in the paper's Table 1
# setting, one variation a task (its first train variation) with its synthetic instructions, TOWER_RECIPE's annealed
# learning rate; validated on 10 scenes a task, evaluated on 20 new ones a task.
# The recipe and steps are what the converter suggests for a multi-task export (TOWER_RECIPE's settings), with the
# compiled CPU loops on, as in every reference run.
SUITE = {"episodes_per_variation": 50, "steps": MULTI_TASK_STEPS, "curve": 4, "eval_episodes": 20,
         "validation_episodes": 10}
SUITE_RECIPE = MULTI_TASK_RECIPE | {"cpu_kernels": True}
# beyond_ten_tasks: its history of 25 keyframes makes a training step ~0.6 s, so 12,000 steps would take over two
# hours; at 4,000 (validated at 2,000 and 4,000) the chain takes ~52 minutes and averages 76.9 %
# (docs/reference/suite.md).
SUITE_STEPS = {"beyond_ten_tasks": {"steps": 4000, "curve": 2}}
DENSE_FPS = 20  # the dense export's control rate (ACT)
RESUME_EVERY = 500  # training steps between checkpoints at most: what an interrupted run can lose
TRAIN_SEED = 1000  # lerobot-train's own default
# `demo-factory eval --seed` of the validation scenes that pick the checkpoint; the final evaluation's is 0.
VALIDATION_SEED = 1


# glibc's malloc told to keep the memory tensors free (no mmap for large blocks, no trimming of the heap) instead of
# handing it back to the kernel and faulting it in, zero-filled, for the next tensor: a CPU training step takes up to
# half as long, and the process keeps its peak heap (docs/plugin.md). Set in the training's environment; other C
# libraries ignore these variables.
KEEP_FREED_MEMORY = {"MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": str(2**31 - 1)}


def training_environment() -> dict[str, str]:
    """This process's environment with the malloc settings a CPU training runs with."""
    return {**os.environ, **KEEP_FREED_MEMORY}


def longest_episode(dataset_root: Path) -> int:
    """Frames (keyframes) of the split's longest episode."""
    return max(e["frames"] for e in read_dataset_provenance(dataset_root)[1]["episodes"])


def train_command(dataset_root: Path, output_dir: Path, steps: int = REFERENCE_STEPS,
                  batch_size: int = REFERENCE_BATCH_SIZE, text_encoder: str = REFERENCE_TEXT_ENCODER,
                  n_history: int = REFERENCE_HISTORY, log_freq: int = 50, save_freq: int | None = None) -> list[str]:
    """`lerobot-train` of HiveFormer on CPU in the reference configuration (no attention dropout: on CPU
    it forces PyTorch's unfused attention; one loader worker beside the two training threads)."""
    return [str(BIN / "lerobot-train"), "--policy.type=hiveformer", "--dataset.repo_id=local/reference_train",
            f"--dataset.root={dataset_root}", "--policy.device=cpu", "--policy.push_to_hub=false",
            f"--policy.text_encoder={text_encoder}", "--policy.attention_dropout=0",
            f"--policy.n_history={n_history}", f"--steps={steps}",
            f"--batch_size={batch_size}", "--num_workers=1", f"--save_freq={save_freq or steps}", f"--log_freq={log_freq}",
            "--wandb.enable=false", f"--output_dir={output_dir}"]


def hiveformer_run_command(args: argparse.Namespace, dataset_root: Path, output_dir: Path) -> list[str]:
    """The run's HiveFormer `lerobot-train` command: the reference configuration, `make reference`'s pinned
    recipe (tower: with the learning rate annealed from 2e-3; with --unseen, `make reference-unseen`'s), the
    --ablation's settings, then each --train-arg replacing the setting of its key."""
    command = train_command(dataset_root, output_dir, args.steps, args.batch_size, args.text_encoder,
                            args.n_history, save_freq=save_interval(args.steps, args.curve))
    recipe = (SUITE_RECIPE if args.suite else UNSEEN_RECIPE if args.unseen else TOWER_RECIPE if args.task == "tower"
              else SEEN_RECIPE)
    command += policy_flags(recipe)
    return with_arguments(with_arguments(command, policy_flags(ABLATIONS.get(args.ablation, {}))), args.train_arg)


def act_train_command(dataset_root: Path, output_dir: Path, steps: int, batch_size: int,
                      log_freq: int = 50) -> list[str]:
    """`lerobot-train` of ACT as the converter suggests it for the dense export (its chunk from the shortest
    episode), at learning rate 1e-4 for the transformer and the backbone alike: ACT's preset 1e-5 is for
    100k-step runs from ImageNet weights, and offline the backbone starts from random weights."""
    info, provenance = read_dataset_provenance(dataset_root)
    shortest = min(e["frames"] for e in provenance["episodes"])
    features = info["features"]
    cameras = provenance["cameras"]
    image_size = tuple(features[f"observation.images.{cameras[0]}"]["shape"][:2])
    args = act_train_args("local/reference_train", dataset_root, cameras, image_size, output_dir, steps=steps,
                          batch_size=batch_size, num_workers=1, log_freq=log_freq,
                          chunk=act_chunk(shortest, info["fps"]))
    return [str(BIN / args[0]), *args[1:], "--policy.optimizer_lr=1e-4", "--policy.optimizer_lr_backbone=1e-4",
            f"--save_freq={steps}"]


def save_interval(steps: int, curve: int) -> int:
    """Steps between saved checkpoints: every learning-curve point, and between them at most RESUME_EVERY
    apart so that an interrupted training resumes from a recent one."""
    interval = steps // curve
    parts = -(-interval // RESUME_EVERY)
    while interval % parts:
        parts += 1
    return interval // parts


def train_stage_command(train: Path, steps: int, fresh: list[str]) -> list[str]:
    """`fresh` when nothing of the training is saved; else lerobot-train resuming from its last checkpoint
    (weights, optimizer, step and data order); the run's folder is cleared when it holds no checkpoint."""
    last = train / "checkpoints" / "last" / "pretrained_model"
    if last.exists() and not get_step_checkpoint_dir(train, steps, steps).exists():
        return [fresh[0], f"--config_path={last / 'train_config.json'}", "--resume=true"]
    if not last.exists():
        shutil.rmtree(train, ignore_errors=True)
    return fresh


def with_arguments(command: list[str], extra: list[str]) -> list[str]:
    """`command` with each `--KEY=VALUE` of `extra` replacing the command's own `--KEY=...` (or appended)."""
    keys = {argument.split("=", 1)[0] for argument in extra}
    return [a for a in command if a.split("=", 1)[0] not in keys] + list(extra)


def train_log_timings(log: str) -> dict:
    """Median update and data-loading seconds per step over lerobot-train's log lines (the first, with
    the start-up, left out) and the share of the step spent waiting for data."""
    updates = [float(x) for x in re.findall(r"updt_s:([0-9.]+)", log)][1:]
    data = [float(x) for x in re.findall(r"data_s:([0-9.]+)", log)][1:]
    if not updates:
        return {"error": "no training log lines"}
    update_s, data_s = statistics.median(updates), statistics.median(data)
    return {"updt_s": update_s, "data_s": data_s, "data_share_of_step": data_s / (update_s + data_s)}


def learning_curve(train: Path, dataset: Path, episodes: int, timings: dict, out: Path, every: int,
                   splits: tuple[str, ...] = ("train",)) -> list[dict]:
    """Success on `splits` (the seen variations, the train split, first) of every `every`-th step's
    checkpoint, on validation scenes: the same variations and instructions as the final evaluation, on
    scene seeds of their own (`eval --seed VALIDATION_SEED`), so that picking a checkpoint by them leaves
    the test scenes unseen. Each in `OUT/validation/<step>/`."""
    saved = sorted((p for p in (train / "checkpoints").iterdir() if p.name.isdigit() and int(p.name) % every == 0),
                   key=lambda p: int(p.name))
    curve = []
    for checkpoint in saved:
        folder = out / "validation" / checkpoint.name
        stage(f"validate_step_{int(checkpoint.name)}", folder / "results.json", timings,
              [str(BIN / "demo-factory"), "eval", "--policy.path", str(checkpoint / "pretrained_model"),
               "--dataset", str(dataset), "--splits", ",".join(splits), "--episodes", str(episodes),
               "--seed", str(VALIDATION_SEED), "--out", str(folder), "--overwrite"], out)
        results = json.loads((folder / "results.json").read_text())["splits"]
        seen = results["train"]
        parts = "per_task" if "per_task" in seen else "per_variation"
        curve.append({"step": int(checkpoint.name), "success_rate": seen["success_rate"],
                      parts: {name: r["success_rate"] for name, r in seen[parts].items()},
                      **{f"{split}_success_rate": results[split]["success_rate"] for split in splits[1:]}})
    return curve


def selected_step(curve: list[dict]) -> int:
    """The checkpoint kept: the best seen-variation success on the validation scenes, the later on a tie
    (the authors keep the checkpoint that does best on validation)."""
    return max(curve, key=lambda point: (point["success_rate"], point["step"]))["step"]


def plot_learning_curve(path: Path, curve: list[dict], title: str) -> None:
    """Success at each checkpoint, one line per curve split (seen; with --unseen also unseen synthetic)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [point["step"] for point in curve]
    lines = {"seen variations": "success_rate"} | {
        key.removesuffix("_success_rate").removeprefix("test_").replace("_", " "): key
        for key in curve[0] if key.startswith("test_") and key.endswith("_success_rate")}
    figure, axis = plt.subplots(figsize=(5, 3.2), dpi=100)
    for label, key in lines.items():
        axis.plot(steps, [100 * point[key] for point in curve], marker="o", label=label)
    axis.set_ylim(-2, 102)
    axis.set_xlabel("training step")
    axis.set_ylabel("closed-loop success (%)")
    axis.set_title(title)
    axis.legend()
    figure.tight_layout()
    figure.savefig(path, metadata={"Software": None})
    plt.close(figure)


def run(command: list[str], log: Path, env: dict[str, str] | None = None) -> None:
    """Run one stage's command (in `env`, default this process's environment), its output teed to a log file; stop
    the run if it fails."""
    print("$ " + " ".join(command), flush=True)
    with log.open("a") as out:  # a resumed stage adds to its log, never replaces it
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
                                   env=env)
        for line in process.stdout:
            out.write(line)
            shown = line.rstrip().split("\r")[-1]  # a progress bar's last state
            if shown and not shown.startswith("Map"):
                print("  " + shown[-200:], flush=True)
        if process.wait() != 0:
            raise SystemExit(f"reference run: stage failed ({command[0]} exited {process.returncode}); see {log}")


def stage(name: str, done: Path, timings: dict, command: list[str], out: Path, env: dict[str, str] | None = None) -> None:
    """Run a stage unless `done` exists (resume); record its wall time."""
    if done.exists():
        print(f"[{name}] already done ({done}), skipped", flush=True)
        return
    began = time.time()
    run(command, out / f"{name}.log", env)
    timings[name] = round(time.time() - began, 1)
    print(f"[{name}] {timings[name]:.0f} s", flush=True)


def generation_stage(name: str, folder: Path, timings: dict, command: list[str], out: Path) -> None:
    """A `demo-factory generate` stage into `folder`, marked complete there once it has run (resume)."""
    stage(name, folder / ".complete", timings, command + ["--out", str(folder)], out)
    (folder / ".complete").touch()


def parse_arguments(argv=None) -> argparse.Namespace:
    """The run's options, checked, with every default filled in and `variations` the seen variations."""
    parser = argparse.ArgumentParser(prog="python -m demo_factory.tools.reference_run", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", choices=sorted(PRESETS), default="hiveformer",
                        help="hiveformer on the keyframe export, or act on the dense export (default: hiveformer)")
    parser.add_argument("--out", type=Path, help="run folder, resumed if present (default: outputs/reference, with "
                        "_tower, _act, _<SUITE>, _unseen, _tower_unseen or _unseen_<ABLATION> after it)")
    parser.add_argument("--task", choices=sorted(TASK_VARIATIONS), default="push_buttons",
                        help="push_buttons (default) or tower (HiveFormer only)")
    parser.add_argument("--suite", choices=[*sorted(SUITES), *sorted(TASKS)], metavar="SUITE_OR_TASK",
                        help="one multi-task HiveFormer over a suite's tasks, one variation a task (its first train "
                        "variation), as the paper's Table 1 (a task name: that task alone, the paper's single-task "
                        "rows; `make reference-suite`: "
                        f"ten_tasks); {SUITE['episodes_per_variation']} episodes a task, {SUITE['steps']} steps "
                        f"(beyond_ten_tasks: {SUITE_STEPS['beyond_ten_tasks']['steps']}), "
                        f"{SUITE['curve']} checkpoints validated on {SUITE['validation_episodes']} scenes a task, the best "
                        f"evaluated on {SUITE['eval_episodes']} new scenes a task; results in Table 1's layout")
    parser.add_argument("--unseen", action="store_true", help="push_buttons (or --task tower: `make "
                        "reference-tower-unseen`) built to follow unseen instructions: "
                        f"the paper's train variations 0-99, {UNSEEN['episodes_per_variation']} episodes each, MiniLM's "
                        f"`{UNSEEN['text_encoder']}` instruction features, {UNSEEN['steps']} steps at a learning rate of "
                        f"{UNSEEN_RECIPE['optimizer_lr']:g} annealed to 0 over the last 3/8 with the pixel attention's "
                        f"cross-entropy beside the position loss, a learning curve of {UNSEEN['curve']} checkpoints, seen and "
                        "unseen-synthetic success; test episodes on the test variations of the authors' human sentences")
    parser.add_argument("--ablation", choices=sorted(ABLATIONS), help="with --unseen: the same run with one part of "
                        "the model taken out, one of the paper's ablation rows (no_history, averaged_instruction: the "
                        "instruction's features averaged into one token, no_ex: without the patch-column embedding, "
                        "no_ex_ey: without both patch-position embeddings, one_hot: one-hot instruction codes); "
                        "default folder outputs/reference_unseen_<NAME>")
    parser.add_argument("--train-variations", type=int, help="with --unseen: the paper's train variations "
                        "0..N-1 (default: 100)")
    parser.add_argument("--human-instructions", type=Path, metavar="FILE", help="with --unseen: human-written "
                        "instructions (the authors' annotations.json format or `demo-factory collect-instructions` "
                        "JSON Lines); one test episode is generated for each test variation they name, and they "
                        "make the human split (default: the paper authors' 162 sentences, 51 test variations)")
    parser.add_argument("--variation", action="append", help="seen variation id or colour sequence (repeatable; "
                        f"default push_buttons: {', '.join(DEFAULT_VARIATIONS)}, tower: "
                        f"{', '.join(TASK_VARIATIONS['tower'])}; ACT: blue; with --unseen: paper train ids 0-99, in place of "
                        "--train-variations)")
    parser.add_argument("--episodes-per-variation", type=int, help="training episodes per seen variation "
                        f"(default: 40; tower: {TOWER['episodes_per_variation']}; "
                        f"--unseen: {UNSEEN['episodes_per_variation']}; ACT: 50)")
    parser.add_argument("--extra-episodes", type=int, help="more training episodes of each seen variation of one "
                        "colour (one button, one cube), with scene seeds of their own (default for HiveFormer "
                        f"runs without --unseen: push_buttons {EXTRA_EPISODES['push_buttons']}, so that 205 has 100; "
                        f"tower {EXTRA_EPISODES['tower']}, so that 46 has 160; else 0)")
    parser.add_argument("--test-episodes", type=int, help="episodes of test variations for the unseen splits "
                        "(default: 20; ACT: 0)")
    parser.add_argument("--image-size", type=int, default=REFERENCE_IMAGE_SIZE,
                        help="camera size in pixels (multiple of 16)")
    parser.add_argument("--steps", type=int, help=f"lerobot-train steps (default: {REFERENCE_STEPS}; tower: {TOWER['steps']}; "
                        f"--unseen: {UNSEEN['steps']}; ACT: 1000)")
    parser.add_argument("--batch-size", type=int, help=f"default: {REFERENCE_BATCH_SIZE}; ACT: 8")
    parser.add_argument("--text-encoder", choices=TEXT_ENCODERS, help="HiveFormer instruction encoder (default: "
                        f"{REFERENCE_TEXT_ENCODER}; --unseen: {UNSEEN['text_encoder']})")
    parser.add_argument("--n-history", type=int, help="HiveFormer keyframes of history (default: the longest "
                        "training episode)")
    parser.add_argument("--curve", type=int, help="checkpoints evaluated on validation scenes of the seen variations "
                        "(and with --unseen the unseen-synthetic split), evenly spaced; the best on the seen ones is "
                        f"evaluated on the test scenes (default: HiveFormer about one every {VALIDATE_EVERY} steps, "
                        f"tower {TOWER['curve']}, --unseen {UNSEEN['curve']}, ACT 1 = the last only)")
    parser.add_argument("--eval-episodes", type=int, help="evaluation episodes per split (default: 40; ACT: 20)")
    parser.add_argument("--validation-episodes", type=int, help="validation episodes per checkpoint of the curve "
                        f"(default: --eval-episodes; --suite: {SUITE['validation_episodes']} a task)")
    parser.add_argument("--workers", type=int, default=2, help="generation processes")
    parser.add_argument("--train-arg", action="append", default=[], metavar="--KEY=VALUE",
                        help="extra lerobot-train argument, repeatable (e.g. --train-arg=--policy.whole_episodes=true); "
                        "it replaces the run's own setting of the same key")
    parser.add_argument("--perturb", metavar="NAME[=P],...", help="training episodes generated under named "
                        "perturbations, each factor with its probability (`demo-factory generate --perturb`, e.g. "
                        "all=0.3; docs/robustness.md); validation and evaluation scenes stay unperturbed")
    parser.add_argument("--robustness", action="store_true", help="also evaluate the kept checkpoint on the curve's "
                        "splits under every perturbation (`demo-factory eval --perturb all`, --eval-episodes each), "
                        "into OUT/robustness")
    parser.add_argument("--seed", type=int, default=TRAIN_SEED, help="lerobot-train's seed: other seeds show how "
                        f"much the result varies with the initial weights and batch order (default: {TRAIN_SEED})")
    args = parser.parse_args(argv)
    if args.suite and (args.policy != "hiveformer" or args.unseen or args.task != "push_buttons" or args.variation
                       or args.extra_episodes or args.test_episodes or args.human_instructions):
        parser.error(f"--suite {args.suite}: a HiveFormer run of the suite's tasks, one variation each; without "
                     "--policy, --task, --unseen, --variation, --extra-episodes, --test-episodes, --human-instructions")
    if args.policy != "hiveformer" and args.task != "push_buttons":
        parser.error(f"--task {args.task}: the {args.policy} reference run is push_buttons only")
    if args.unseen and args.policy != "hiveformer":
        parser.error("--unseen is the HiveFormer run on the paper's train variations: without --policy")
    if args.ablation and (not args.unseen or args.task != "push_buttons"):
        parser.error(f"--ablation {args.ablation}: one of the paper's ablation rows, measured against `make "
                     "reference-unseen`: only with --unseen, on push_buttons")
    if args.ablation:  # the run is filed as the ablation: nothing may set its settings back
        ablated = {flag.split("=", 1)[0] for flag in policy_flags(ABLATIONS[args.ablation])}
        undone = [a for a in args.train_arg if a.split("=", 1)[0] in ablated]
        if undone or (args.ablation == "one_hot" and args.text_encoder not in (None, "one_hot")):
            parser.error(f"--ablation {args.ablation}: {undone[0] if undone else '--text-encoder'} would undo it")
        args.text_encoder = ABLATIONS[args.ablation].get("text_encoder", args.text_encoder)
    if args.unseen and args.variation:
        outside = [v for v in args.variation if not (v.isdigit() and int(v) < 100)]
        if outside or args.train_variations is not None:
            parser.error(f"--variation {outside[0]}: with --unseen, a paper train id 0-99" if outside else
                         "--variation and --train-variations: with --unseen, one or the other")
    if args.perturb is not None:
        try:
            parse_perturb_option(args.perturb)
        except ValueError as error:
            parser.error(f"--perturb {args.perturb}: {error}")
    malformed = [a for a in args.train_arg if not (a.startswith("--") and "=" in a)]
    if malformed:
        parser.error(f"--train-arg {malformed[0]!r}: expected --KEY=VALUE (a lerobot-train argument)")
    if args.train_arg and args.policy != "hiveformer":
        parser.error("--train-arg: HiveFormer runs only")
    if args.human_instructions is not None and not (args.unseen and args.human_instructions.is_file()):
        parser.error(f"--human-instructions {args.human_instructions}: "
                     + ("not a file" if args.unseen else "only with --unseen"))
    if args.train_variations is not None and not (args.unseen and 1 <= args.train_variations <= 100):
        parser.error(f"--train-variations {args.train_variations}: with --unseen, 1 to 100 (the paper's train ids)")
    seen_run = args.policy == "hiveformer" and not args.unseen and not args.suite
    if args.extra_episodes is not None and (args.extra_episodes < 0 or (args.extra_episodes and not seen_run)):
        parser.error(f"--extra-episodes {args.extra_episodes}: a number >= 0, above 0 only for HiveFormer runs "
                     "without --unseen")
    if args.extra_episodes is None:
        args.extra_episodes = EXTRA_EPISODES[args.task] if seen_run else 0
    defaults = ({"text_encoder": REFERENCE_TEXT_ENCODER} | PRESETS[args.policy]
                | (UNSEEN if args.unseen else TOWER if args.task == "tower" else {})
                | (SUITE | {"test_episodes": 0} | SUITE_STEPS.get(args.suite, {}) if args.suite else {}))
    for name, value in defaults.items():
        if name != "variations" and getattr(args, name, None) is None:
            setattr(args, name, value)
    if args.curve is None:
        args.curve = default_curve(args.steps) if args.policy == "hiveformer" else 1
    if args.curve < 1 or args.steps % args.curve:
        parser.error(f"--curve {args.curve}: a positive number of checkpoints that divides --steps {args.steps}")
    args.validation_episodes = args.validation_episodes or (SUITE["validation_episodes"] if args.suite
                                                            else args.eval_episodes)
    args.variations = args.variation or list(PRESETS[args.policy]["variations"] if args.policy != "hiveformer"
                                             else TASK_VARIATIONS[args.task])
    if args.suite:  # each task's first train variation, the paper's one variation a task
        args.variations = {task: str(get_task(task).split_variations("train")[0].id)
                           for task in SUITES.get(args.suite, (args.suite,))}
    if args.unseen and not args.variation:
        paper_train_ids = [str(v.id) for v in get_task(args.task).split_variations("train")]  # 0-99
        args.variations = paper_train_ids[:args.train_variations]
    return args


def default_out(args: argparse.Namespace) -> Path:
    """The run's folder when --out names none: outputs/reference with what sets the run apart after it."""
    suffix = ("_act" if args.policy != "hiveformer" else f"_{args.suite}" if args.suite
              else "_tower" if args.task == "tower" else "")
    suffix += ("_unseen" + (f"_{args.ablation}" if args.ablation else "")) if args.unseen else ""
    return Path("outputs/reference" + suffix)


def default_curve(steps: int) -> int:
    """Checkpoints a HiveFormer run validates by default: about one every VALIDATE_EVERY steps, evenly spaced
    (a divisor of `steps`), at least the last."""
    return max(n for n in range(1, max(steps // VALIDATE_EVERY, 1) + 1) if steps % n == 0)


PRESSES = ("first", "second", "third")


def pressed_colours(variation_ids) -> set[tuple[int, str]]:
    """(press position, colour) pairs of push_buttons variations: (0, "green") for "green, then ..."."""
    task = get_task("push_buttons")
    return {pair for v in variation_ids for pair in enumerate(task.variation(int(v)).words)}


def uncomposable_test_variations(train_variations: list[str]) -> list[int]:
    """The paper's push_buttons test variations (100-199) with a colour at a press position where no train
    variation has it: an instruction that a policy grounding each colour word at its position cannot follow."""
    trained = pressed_colours(train_variations)
    return [v.id for v in get_task("push_buttons").split_variations("test") if not set(enumerate(v.words)) <= trained]


def composability_note(train_variations: list[str]) -> str | None:
    """What the user is told when train variations leave test variations that cannot be composed."""
    uncomposable = uncomposable_test_variations(train_variations)
    if not uncomposable:
        return None
    missing = sorted(pressed_colours(uncomposable) - pressed_colours(train_variations))
    return (f"note: {len(uncomposable)} of the 100 test variations name a colour at a press where no train variation "
            f"has it ({', '.join(f'{colour} {PRESSES[press]}' for press, colour in missing)}): a policy that grounds "
            "each colour word at its place in the instruction cannot follow them")


def generate_command(args: argparse.Namespace, task: str | None = None) -> list[str]:
    """`demo-factory generate` in the run's task (or `task`), camera size and worker count; the caller adds the
    episodes."""
    return [str(BIN / "demo-factory"), "generate", "--task", task or args.task, "--image-size", str(args.image_size),
            "--workers", str(args.workers), *(["--dense-fps", str(DENSE_FPS)] if args.policy != "hiveformer" else [])]


def train_generation_command(args: argparse.Namespace, variations: list[str], episodes: int,
                             task: str | None = None) -> list[str]:
    """`demo-factory generate` of `episodes` training episodes of each of `variations` (without --out)."""
    return generate_command(args, task) + ["--split", "train", *[f"--variation={v}" for v in variations],
                                           "--episodes-per-variation", str(episodes),
                                           *(["--perturb", args.perturb] if args.perturb else [])]


def single_colour_variations(task_name: str, variations: list[str]) -> list[str]:
    """The variations (ids or colour sequences) that name one colour: push_buttons' one button, tower's one cube."""
    task = get_task(task_name)
    return [v for v in variations if len(task.parse_variation(v).words) == 1]


def extra_generation_command(args: argparse.Namespace) -> list[str] | None:
    """The generation (without --out) of --extra-episodes more training episodes of each one-colour seen
    variation, or None when there are none to make."""
    variations = single_colour_variations(args.task, args.variations) if args.extra_episodes else []
    if not variations:
        return None
    return train_generation_command(args, variations, args.extra_episodes) + ["--seed", str(EXTRA_SEED)]


def generate_test_command(args: argparse.Namespace) -> list[str] | None:
    """`demo-factory generate` of the test split (without --out): with --unseen, episodes of each test variation
    that the human-written sentences name; else --test-episodes episodes; None when there are none."""
    if args.unseen:
        human = args.human_instructions or shipped_human_instructions(args.task)
        which = ["--variations-from", str(human),
                 "--episodes-per-variation", str(UNSEEN["test_episodes_per_variation"])]
    elif args.test_episodes:
        which = ["--episodes", str(args.test_episodes)]
    else:
        return None
    return generate_command(args) + ["--split", "test", *which, "--seed", "1"]


def main(argv=None) -> int:
    args = parse_arguments(argv)
    if args.unseen and args.task == "push_buttons" and (note := composability_note(args.variations)):
        print(note, flush=True)
    dense = args.policy != "hiveformer"
    out = args.out or default_out(args)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict = {}
    began = time.time()

    raw, dataset, train, evaluation = out / "raw", out / "dataset", out / "train", out / "eval"
    if args.suite:  # each task's episodes in a folder of its own: one multi-task dataset
        for task, variation in args.variations.items():
            generation_stage(f"generate_train_{task}", raw / "train" / task, timings,
                             train_generation_command(args, [variation], args.episodes_per_variation, task), out)
    else:
        generation_stage("generate_train", raw / "train", timings,
                         train_generation_command(args, args.variations, args.episodes_per_variation), out)
    if extra := extra_generation_command(args):
        generation_stage("generate_train_extra", raw / "train_extra", timings, extra, out)
    if test := generate_test_command(args):
        generation_stage("generate_test", raw / "test", timings, test, out)
    if not (dataset / "train").exists():
        shutil.rmtree(dataset, ignore_errors=True)
    stage("convert", dataset / "train", timings,
          [str(BIN / "demo-factory"), "convert", "--in", str(raw), "--out", str(dataset), "--repo-id",
           "local/reference", "--val-ratio", "0", "--no-progress",
           *(["--human-instructions", str(args.human_instructions)] if args.human_instructions else []),
           *(["--granularity", "dense", "--action-space", "joints", "--fps", str(DENSE_FPS)] if dense else [])], out)
    checkpoint = get_step_checkpoint_dir(train, args.steps, args.steps) / "pretrained_model"
    if dense:
        command = act_train_command(dataset / "train", train, args.steps, args.batch_size)
    else:
        args.n_history = args.n_history or longest_episode(dataset / "train")
        command = hiveformer_run_command(args, dataset / "train", train)
    stage("train", checkpoint, timings, train_stage_command(train, args.steps, command + [f"--seed={args.seed}"]), out,
          training_environment())
    if "train" in timings:  # trained (or resumed) now: any earlier evaluation was of other weights
        for folder in (out / "validation", evaluation):
            shutil.rmtree(folder, ignore_errors=True)
    curve = (learning_curve(train, dataset, args.validation_episodes, timings, out, args.steps // args.curve,
                            CURVE_SPLITS[args.unseen])
             if args.curve > 1 else [])
    chosen = selected_step(curve) if curve else args.steps
    kept = get_step_checkpoint_dir(train, args.steps, chosen) / "pretrained_model"
    stage("eval", evaluation / "results.json", timings,
          [str(BIN / "demo-factory"), "eval", "--policy.path", str(kept), "--dataset", str(dataset),
           "--episodes", str(args.eval_episodes), "--out", str(evaluation), "--overwrite"], out)

    if args.robustness:
        stage("robustness", out / "robustness" / "results.json", timings,
              [str(BIN / "demo-factory"), "eval", "--policy.path", str(kept), "--dataset", str(dataset),
               "--splits", ",".join(CURVE_SPLITS[args.unseen]), "--episodes", str(args.eval_episodes),
               "--perturb", "all", "--out", str(out / "robustness"), "--overwrite"], out)

    results = json.loads((evaluation / "results.json").read_text())
    train_log = out / "train.log"
    summary = {"command": shlex.join(["python", "-m", "demo_factory.tools.reference_run",
                                      *(sys.argv[1:] if argv is None else argv)]),
               "configuration": vars(args) | {"out": str(out),
                                              **({"dense_fps": DENSE_FPS, "action_space": "joints"} if dense else {})},
               "stage_seconds": timings, "train_step": train_log_timings(train_log.read_text() if train_log.exists() else ""), "wall_seconds_this_invocation": round(time.time() - began, 1),
               "learning_curve": curve, "selected_step": chosen,
               "evaluated_checkpoint": str(kept), "results": results,
               **({"robustness": json.loads((out / "robustness" / "results.json").read_text())["perturbations"]}
                  if args.robustness else {})}
    (out / "reference_run.json").write_text(json.dumps(summary, indent=2, default=str) + "\n")
    print((evaluation / "results.md").read_text())
    if args.robustness:
        report = (out / "robustness" / "results.md").read_text()
        print(report[report.index("## Under perturbation"):])
    if curve:
        plot_learning_curve(out / "learning_curve.png", curve, f"{args.suite or args.task}: HiveFormer, seed {args.seed}")
        unseen = "test_unseen_synthetic_success_rate"
        print("Learning curve on validation scenes (seen variations" + (" / unseen synthetic" if args.unseen else "")
              + "): " + ", ".join(f"step {c['step']}: {100 * c['success_rate']:.1f}"
                                  + (f" / {100 * c[unseen]:.1f}" if unseen in c else "") + " %" for c in curve))
        for task in curve[0].get("per_task", {}):
            print(f"  {task:<36} " + ", ".join(f"{100 * point['per_task'][task]:.0f}" for point in curve) + " %")
        print(f"Evaluated above: the step-{chosen} checkpoint, the best on the validation scenes", flush=True)
    print(f"reference run: {summary['wall_seconds_this_invocation']:.0f} s; figures in {out / 'reference_run.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
