"""How to load and train on a converted split: one place for the CLI summary and the card."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

from demo_factory.convert.features import image_key


def load_command(repo_id: str, root: Path) -> str:
    """A shell command that loads one split offline and prints it."""
    code = f'from lerobot.datasets.lerobot_dataset import LeRobotDataset as D; print(D("{repo_id}", root="{root}"))'
    return f"python -c {shlex.quote(code)}"


def act_input_features(cameras: list[str], image_size: tuple[int, int]) -> dict:
    """ACT's inputs restricted to the RGB cameras and the state (packed depth is no image to ACT)."""
    height, width = image_size
    features = {image_key(c): {"type": "VISUAL", "shape": [3, height, width]} for c in cameras}
    features["observation.state"] = {"type": "STATE", "shape": [15]}
    return features


def act_train_args(repo_id: str, root: Path, cameras: list[str], image_size: tuple[int, int],
                   output_dir: Path, steps: int = 2000, batch_size: int = 8, num_workers: int = 2,
                   log_freq: int = 100) -> list[str]:
    """``lerobot-train`` arguments for ACT on one split: offline, CPU, no Hub push, no wandb."""
    return [
        "lerobot-train",
        "--policy.type=act",
        f"--dataset.repo_id={repo_id}",
        f"--dataset.root={root}",
        "--policy.device=cpu",
        "--policy.pretrained_backbone_weights=null",  # ImageNet weights would be downloaded
        "--policy.push_to_hub=false",
        f"--policy.input_features={json.dumps(act_input_features(cameras, image_size), separators=(',', ':'))}",
        "--wandb.enable=false",
        f"--output_dir={output_dir}",
        f"--steps={steps}",
        f"--batch_size={batch_size}",
        f"--num_workers={num_workers}",
        f"--log_freq={log_freq}",
    ]


def act_train_command(*args, **kwargs) -> str:
    return " ".join(shlex.quote(a) for a in act_train_args(*args, **kwargs))
