"""A smoke version of `make reference-tower`: the tower chain with a learning curve, interrupted and resumed
(its own file, so that the suite's processes run it beside test_reference_run's chain)."""

import json
import shutil

import pytest

from demo_factory.tools.reference_run import main


@pytest.mark.slow
@pytest.mark.timeout(1800)  # the whole chain: ~15 minutes beside the rest of the suite on 2 cores
def test_tower_reference_run_takes_its_history_from_the_longest_episode_and_plots_a_curve(tmp_path):
    out = tmp_path / "tower"
    arguments = ["--task", "tower", "--out", str(out), "--variation", "46", "--variation", "0",
                 "--episodes-per-variation", "1", "--test-episodes", "1", "--steps", "2", "--curve", "2",
                 "--batch-size", "2", "--eval-episodes", "1", "--workers", "1", "--image-size", "32",
                 "--text-encoder", "one_hot"]
    assert main(arguments) == 0
    summary = json.loads((out / "reference_run.json").read_text())
    assert summary["configuration"]["n_history"] == 13  # the two-cube episode: 6 keyframes a cube + the start
    config = json.loads((out / "train" / "checkpoints" / "last" / "pretrained_model" / "config.json").read_text())
    assert config["n_history"] == 13
    assert [c["step"] for c in summary["learning_curve"]] == [1, 2]
    assert all(0.0 <= c["success_rate"] <= 1.0 and c["per_variation"] for c in summary["learning_curve"])
    assert (out / "validation" / "000001" / "results.json").exists()
    assert (out / "learning_curve.png").read_bytes().startswith(b"\x89PNG")
    assert {"validate_step_1", "validate_step_2", "eval"} <= set(summary["stage_seconds"])
    assert json.loads((out / "eval" / "results.json").read_text())["task"] == "tower"

    # Interrupted after the first checkpoint: the training resumes from it (step 1's weights, optimizer and
    # data order), saves the last step, and the evaluation runs on that.
    checkpoints = out / "train" / "checkpoints"
    first = (checkpoints / "000001" / "pretrained_model" / "model.safetensors").read_bytes()
    shutil.rmtree(checkpoints / "000002")
    (checkpoints / "last").unlink()
    (checkpoints / "last").symlink_to("000001")
    assert main(arguments) == 0
    resumed = json.loads((checkpoints / "000002" / "pretrained_model" / "train_config.json").read_text())
    assert resumed["resume"] is True and resumed["steps"] == 2
    assert (checkpoints / "000001" / "pretrained_model" / "model.safetensors").read_bytes() == first
    assert "Start offline training" in (out / "train.log").read_text()
    # Every evaluation of the earlier weights is redone.
    assert set(json.loads((out / "reference_run.json").read_text())["stage_seconds"]) == {
        "train", "validate_step_1", "validate_step_2", "eval"}
