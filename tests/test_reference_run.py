"""A smoke version of the reference run: the whole chain runs and writes its results table."""

import json

import pytest

from demo_factory.reference_run import main


@pytest.mark.slow
def test_reference_run_chain_writes_its_results(tmp_path):
    out = tmp_path / "reference"
    arguments = ["--out", str(out), "--variation", "8", "--episodes-per-variation", "2", "--test-episodes", "1",
                 "--steps", "2", "--batch-size", "2", "--eval-episodes", "1", "--workers", "1",
                 "--image-size", "32", "--text-encoder", "clip_tiny_random"]
    assert main(arguments) == 0
    summary = json.loads((out / "reference_run.json").read_text())
    assert set(summary["stage_seconds"]) == {"generate_train", "generate_test", "convert", "train", "eval"}
    assert "train" in summary["results"]["splits"]
    assert (out / "eval" / "results.md").read_text().strip()
    assert (out / "train" / "checkpoints" / "last" / "pretrained_model" / "model.safetensors").exists()
    # Run again: every stage is complete, so nothing runs and the same results come back.
    assert main(arguments) == 0
    again = json.loads((out / "reference_run.json").read_text())
    assert again["stage_seconds"] == {} and again["results"] == summary["results"]
