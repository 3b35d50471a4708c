"""`lerobot-train --policy.type=hiveformer` end to end, then a rollout with the saved checkpoint."""

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hiveformer_fixtures import EPISODE_LENGTHS, tiny_dataset_root
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import make_pre_post_processors
from lerobot_policy_hiveformer import HiveformerPolicy

__all__ = ["tiny_dataset_root"]  # the fixture is used by name

LEROBOT_TRAIN = Path(sys.executable).with_name("lerobot-train")


def lerobot_train_command(dataset_root: Path, output_dir: Path) -> list[str]:
    """The offline CPU smoke-training command (the tiny random CLIP needs no download)."""
    return [
        str(LEROBOT_TRAIN),
        "--policy.type=hiveformer",
        "--dataset.repo_id=local/tiny",
        f"--dataset.root={dataset_root}",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        "--policy.text_encoder=clip_tiny_random",
        "--policy.n_history=3",
        "--steps=3",
        "--batch_size=2",
        "--num_workers=0",
        "--save_freq=3",
        "--log_freq=1",
        "--wandb.enable=false",
        f"--output_dir={output_dir}",
    ]


@pytest.mark.slow
def test_lerobot_train_then_rollout_from_the_checkpoint(tiny_dataset_root, tmp_path):
    output_dir = tmp_path / "out"
    result = subprocess.run(
        lerobot_train_command(tiny_dataset_root, output_dir), capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "step:3 " in result.stdout + result.stderr

    checkpoint = output_dir / "checkpoints" / "last" / "pretrained_model"
    policy = HiveformerPolicy.from_pretrained(checkpoint)
    assert policy.config.text_encoder == "clip_tiny_random" and policy.config.n_history == 3
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(checkpoint))

    dataset = LeRobotDataset("local/tiny", root=tiny_dataset_root)
    start = sum(EPISODE_LENGTHS[:3])
    policy.reset()
    actions = []
    for index in range(start, start + EPISODE_LENGTHS[3]):
        frame = dataset[index]
        observation = {k: v for k, v in frame.items() if k.startswith("observation.")}
        observation["task"] = frame["task"]
        action = postprocessor(policy.select_action(preprocessor(observation)))
        actions.append(action)
    actions = torch.cat(actions)
    assert actions.shape == (EPISODE_LENGTHS[3], 8)
    assert torch.isfinite(actions).all()
    assert torch.allclose(actions[:, 3:7].norm(dim=-1), torch.ones(len(actions)), atol=1e-5)
    assert len(policy._history) == policy.config.n_history
