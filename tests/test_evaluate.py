"""Closed-loop evaluation: the expert scores 100%, a do-nothing policy 0%, outputs in the paper's layout."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from demo_factory.evaluate.env import KeyframeEnv, default_episodes, evaluation_seed
from demo_factory.evaluate.policies import CurrentPosePolicy, ExpertPolicy
from demo_factory.evaluate.runner import evaluate_episode, summarise
from demo_factory.generate import episode_seed
from demo_factory.record import read_episode


def evaluate(*args):
    return subprocess.run([sys.executable, "-m", "demo_factory.cli", "eval", *args], capture_output=True, text=True)


@pytest.mark.slow
@pytest.mark.parametrize("task", ["push_buttons", "tower"])
def test_expert_scores_100_percent_on_4_episodes_of_each_split(task, tmp_path):
    """(The expert's success over many more episodes: `make bench`, expert_success.)"""
    out = tmp_path / "eval"
    result = evaluate("--expert", "--task", task, "--episodes", "4", "--image-size", "32", "--out", str(out))
    assert result.returncode == 0, result.stderr
    results = json.loads((out / "results.json").read_text())
    for split in ("train", "test"):
        assert results["splits"][split]["episodes"] == 4
        assert results["splits"][split]["success_rate"] == 1.0, results["splits"][split]["failure_reasons"]
    table = (out / "results.md").read_text()
    assert "| policy | train | test |" in table and "| expert | 100.0 | 100.0 |" in table
    assert (out / "results.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    episodes = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert len(episodes) == 8 and all(e["instruction"] and e["predicted_keyframes"] for e in episodes)


def test_current_pose_policy_scores_zero_and_stops_at_the_step_limit():
    episodes = default_episodes("push_buttons", "test", 3)
    env = KeyframeEnv("push_buttons", episodes, image_size=(32, 32), step_slack=2)
    records = [evaluate_episode(env, CurrentPosePolicy(), e) for e in episodes]
    env.close()
    assert summarise(records)["success_rate"] == 0.0
    for record in records:
        assert record["failure_reason"] == "step limit" and record["failure_subgoal"] is None
        assert record["steps"] == record["step_limit"] > 2


def test_evaluation_is_deterministic_and_records_rollouts(tmp_path):
    episode = default_episodes("push_buttons", "train", 1)[0]
    env = KeyframeEnv("push_buttons", [episode], image_size=(32, 32))
    first = evaluate_episode(env, ExpertPolicy(), episode, record_path=tmp_path / "a.mcap")
    again = evaluate_episode(env, ExpertPolicy(), episode, record_path=tmp_path / "b.mcap")
    env.close()
    assert first == again and first["success"]
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()
    recorded = read_episode(tmp_path / "a.mcap")
    assert recorded.info.success and len(recorded.frames) == first["steps"] + 1
    assert recorded.info.instruction == episode.instruction


def test_evaluation_seeds_are_not_generation_seeds():
    generation = {episode_seed(0, "push_buttons", split, i) for split in ("train", "test") for i in range(2000)}
    evaluation = {evaluation_seed(0, "push_buttons", split, i) for split in ("train", "test") for i in range(2000)}
    assert not generation & evaluation


@pytest.mark.parametrize("args, message", [
    (["--expert"], "give --dataset (a converted dataset) or --task"),
    (["--expert", "--task", "tower", "--splits", "val"], "unknown split 'val' without --dataset"),
    (["--policy.path", "/nonexistent", "--task", "tower"], "not a LeRobot checkpoint (no config.json)"),
    (["--expert", "--dataset", "/nonexistent"], "--dataset /nonexistent: no such folder"),
])
def test_bad_evaluation_input_is_one_line_and_exit_2(tmp_path, args, message):
    result = evaluate(*args, "--out", str(tmp_path / "out"))
    assert result.returncode == 2 and message in result.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_expert_on_the_splits_of_a_converted_dataset(converted_push_buttons, tmp_path):
    out = tmp_path / "eval"
    splits = "test_unseen_synthetic,test_unseen_corrupted,test_unseen_paraphrased"
    result = evaluate("--expert", "--dataset", str(converted_push_buttons), "--splits", splits, "--episodes", "3",
                      "--out", str(out))
    assert result.returncode == 0, result.stderr
    results = json.loads((out / "results.json").read_text())
    assert list(results["splits"]) == splits.split(",")
    assert all(s["success_rate"] == 1.0 and s["episodes"] == 3 for s in results["splits"].values())
    corrupted = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()
                 if '"test_unseen_corrupted"' in line]
    dataset_tasks = json.loads((converted_push_buttons / "test_unseen_corrupted" / "meta" / "demo_factory.json").read_text())
    assert {e["instruction"] for e in corrupted} <= {e["instruction"] for e in dataset_tasks["episodes"]}
    table = (out / "results.md").read_text()
    assert "| HiveFormer (paper) | 86.3 | 85.6 |" in table
    # The held-out phrasings one by one: each sentence, its variation, episodes and successes.
    sentences = results["splits"]["test_unseen_paraphrased"]["per_sentence"]
    held_out = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()
                if '"test_unseen_paraphrased"' in line]
    assert sum(row["episodes"] for row in sentences) == 3 == sum(row["successes"] for row in sentences)
    assert {row["instruction"] for row in sentences} == {e["instruction"] for e in held_out}
    assert "## test_unseen_paraphrased: per sentence" in table
    assert all(f"| {row['instruction']} | {row['variation_id']} | " in table for row in sentences)
    assert "per_sentence" not in results["splits"]["test_unseen_synthetic"]


@pytest.fixture(scope="module")
def tiny_hiveformer(converted_push_buttons, tmp_path_factory):
    """A HiveFormer trained for two steps on the converted train split with `lerobot-train`."""
    out = tmp_path_factory.mktemp("hiveformer") / "train"
    command = [
        str(Path(sys.executable).with_name("lerobot-train")), "--policy.type=hiveformer",
        "--dataset.repo_id=me/push_buttons_train", f"--dataset.root={converted_push_buttons / 'train'}",
        "--policy.device=cpu", "--policy.push_to_hub=false", "--policy.text_encoder=clip_tiny_random",
        "--policy.n_history=3", "--steps=2", "--batch_size=2", "--num_workers=0", "--save_freq=2",
        "--wandb.enable=false", f"--output_dir={out}",
    ]
    result = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert result.returncode == 0, result.stderr[-3000:]
    return out / "checkpoints" / "last" / "pretrained_model"


@pytest.mark.slow
def test_tiny_hiveformer_runs_through_demo_factory_eval(tiny_hiveformer, converted_push_buttons, tmp_path):
    out = tmp_path / "eval"
    result = evaluate("--policy.path", str(tiny_hiveformer), "--dataset", str(converted_push_buttons),
                      "--splits", "test_unseen_synthetic,test_unseen_human", "--episodes", "2", "--out", str(out))
    assert result.returncode == 0, result.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    assert results["policy"].startswith("hiveformer")
    for split in ("test_unseen_synthetic", "test_unseen_human"):
        summary = results["splits"][split]
        assert summary["episodes"] == 2 and 0.0 <= summary["success_rate"] <= 1.0
        assert summary["mean_steps"] >= 1
    rows = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert all(len(r["predicted_keyframes"]) == r["steps"] and len(r["predicted_keyframes"][0]) == 8 for r in rows)
    keyframes = np.array([k for r in rows for k in r["predicted_keyframes"]])  # the checkpoint's own rollouts
    assert np.isfinite(keyframes).all() and np.allclose(np.linalg.norm(keyframes[:, 3:7], axis=1), 1, atol=1e-4)
    assert set(keyframes[:, 7]) <= {0.0, 1.0}


@pytest.mark.slow
def test_tiny_hiveformer_runs_through_lerobot_eval(tiny_hiveformer, tmp_path):
    command = [
        str(Path(sys.executable).with_name("lerobot-eval")),
        "--env.discover_packages_path=demo_factory.evaluate.lerobot_env", "--env.type=demo_factory",
        "--env.task=push_buttons", "--env.image_height=32", "--env.image_width=32",
        f"--policy.path={tiny_hiveformer}", "--policy.device=cpu", "--eval.n_episodes=2", "--eval.batch_size=1",
        f"--output_dir={tmp_path / 'lerobot_eval'}",
    ]
    result = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert result.returncode == 0, result.stderr[-3000:]
    assert "'n_episodes': 2" in result.stdout + result.stderr
    assert "pc_success" in result.stdout + result.stderr
