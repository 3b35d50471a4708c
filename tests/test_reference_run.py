"""A smoke version of the reference run: the whole chain runs and writes its results table."""

import json

import pytest

from demo_factory.tools.reference_run import main


@pytest.mark.slow
def test_reference_run_chain_writes_its_results(tmp_path):
    out = tmp_path / "reference"
    arguments = ["--out", str(out), "--variation", "8", "--episodes-per-variation", "2", "--test-episodes", "1",
                 "--steps", "2", "--batch-size", "2", "--eval-episodes", "1", "--workers", "1",
                 "--image-size", "32", "--text-encoder", "clip_tiny_random", "--seed", "3"]
    assert main(arguments) == 0
    summary = json.loads((out / "reference_run.json").read_text())
    assert set(summary["stage_seconds"]) == {"generate_train", "generate_test", "convert", "train", "eval"}
    assert "train" in summary["results"]["splits"]
    assert (out / "eval" / "results.md").read_text().strip()
    checkpoint = out / "train" / "checkpoints" / "last" / "pretrained_model"
    assert (checkpoint / "model.safetensors").exists()
    assert json.loads((checkpoint / "train_config.json").read_text())["seed"] == 3
    # Run again: every stage is complete, so nothing runs and the same results come back.
    assert main(arguments) == 0
    again = json.loads((out / "reference_run.json").read_text())
    assert again["stage_seconds"] == {} and again["results"] == summary["results"]


def test_act_reference_trains_with_the_chunk_its_shortest_episode_holds(tmp_path):
    from demo_factory.convert import DATASET_FORMAT_VERSION
    from demo_factory.tools.reference_run import act_train_command

    meta = tmp_path / "train" / "meta"
    meta.mkdir(parents=True)
    info = {"fps": 20, "features": {"observation.images.wrist": {"shape": [64, 64, 3]}}}
    (meta / "info.json").write_text(json.dumps(info))
    provenance = {"format_version": DATASET_FORMAT_VERSION, "cameras": ["wrist"], "episodes": [{"frames": 60}, {"frames": 31}]}
    (meta / "demo_factory.json").write_text(json.dumps(provenance))
    command = act_train_command(tmp_path / "train", tmp_path / "out", steps=300, batch_size=8)
    assert command[0].endswith("lerobot-train") and "--policy.type=act" in command
    assert "--policy.chunk_size=31" in command and "--policy.n_action_steps=15" in command  # 2 s = 40 > 31
    assert {"--steps=300", "--batch_size=8", "--save_freq=300", "--policy.pretrained_backbone_weights=null"} <= set(command)
    features = json.loads(next(a for a in command if a.startswith("--policy.input_features=")).split("=", 1)[1])
    assert features["observation.images.wrist"]["shape"] == [3, 64, 64]
