"""Dense exports (fixed control rate, joints or ee actions) and closed-loop evaluation of dense policies."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from demo_factory.convert.converter import read_dataset_provenance
from demo_factory.cli import main
from demo_factory.convert.features import canonical_quaternion
from demo_factory.convert.usage import act_chunk, act_train_args
from demo_factory.record import read_episode
from demo_factory.tasks import get_task

CAMERAS = ["left_shoulder", "right_shoulder", "wrist"]
RECORDED_FPS = 4  # write_dense_recording's rate


@pytest.fixture(scope="module")
def dense_recordings(tmp_path_factory, write_dense_recording):
    folder = tmp_path_factory.mktemp("dense_raw")
    train = get_task("push_buttons").split_variations("train")
    test = get_task("push_buttons").split_variations("test")
    write_dense_recording(folder, "train", train[0], 1, ticks=9)
    write_dense_recording(folder, "train", train[1], 2, ticks=12)
    write_dense_recording(folder, "test", test[0], 3, ticks=8)
    return folder


def convert(recordings: Path, out: Path, *options: str) -> int:
    return main(["convert", "--in", str(recordings), "--out", str(out), "--repo-id", "me/pb_dense",
                 "--granularity", "dense", "--val-ratio", "0", "--no-progress", *options])


def _episodes(root: Path, split: str):
    """(dataset frames, recording) per episode of one converted split."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset(f"me/pb_dense_{split}", root=root / split)
    items = [dataset[i] for i in range(len(dataset))]
    for source in read_dataset_provenance(dataset.root)[1]["episodes"]:
        frames = [it for it in items if it["episode_index"].item() == source["episode_index"]]
        yield dataset, frames, source


@pytest.mark.parametrize("space", ["joints", "ee"])
def test_dense_action_is_the_next_control_tick_in_the_chosen_space(dense_recordings, tmp_path, space):
    out = tmp_path / "dense"
    assert convert(dense_recordings, out, "--action-space", space) == 0
    expected_names = ([f"joint_{i}" for i in range(7)] if space == "joints" else ["x", "y", "z", "qx", "qy", "qz", "qw"])
    for dataset, frames, source in _episodes(out, "train"):
        assert dataset.fps == RECORDED_FPS
        assert tuple(dataset.features["action"]["shape"]) == (8,)
        assert dataset.features["action"]["names"] == [*expected_names, "open"]
        assert read_dataset_provenance(dataset.root)[1]["action_space"] == space
        recorded = read_episode(dense_recordings / source["recording"]).dense_frames()
        assert len(frames) == len(recorded) == source["frames"]
        for t, item in enumerate(frames):
            following = recorded[min(t + 1, len(recorded) - 1)].robot  # the last frame holds still
            if space == "joints":
                target = np.append(following.joint_positions, following.gripper_open)
            else:
                target = np.concatenate([following.gripper_pose[:3], canonical_quaternion(following.gripper_pose[3:]),
                                         [following.gripper_open]])
                assert item["action"][3] >= 0  # one quaternion sign: no jumps between q and -q
            assert np.allclose(item["action"].numpy(), target, atol=1e-6)
            robot = recorded[t].robot  # observations as in the keyframe export
            state = np.concatenate([robot.gripper_pose, [robot.gripper_open], robot.joint_positions])
            assert np.allclose(item["observation.state"].numpy(), state, atol=1e-6)
    card = (out / "README.md").read_text()
    assert f"action space `{space}`" in card and "- dense" in card
    assert "--policy.type=act" in card and "lerobot-doctor gate" in card


def test_fps_keeps_every_kth_dense_frame_and_actions_follow_the_kept_ticks(dense_recordings, tmp_path):
    out = tmp_path / "dense2"
    assert convert(dense_recordings, out, "--fps", "2") == 0
    for dataset, frames, source in _episodes(out, "train"):
        recorded = read_episode(dense_recordings / source["recording"]).dense_frames()[::2]
        assert dataset.fps == 2 and len(frames) == len(recorded)
        assert read_dataset_provenance(dataset.root)[1]["action_space"] == "joints"  # the default
        for t, item in enumerate(frames[:-1]):
            assert np.allclose(item["action"][:7].numpy(), recorded[t + 1].robot.joint_positions, atol=1e-6)


def test_image_stats_are_right_so_policies_can_normalise_images(dense_recordings, tmp_path):
    out = tmp_path / "stats"
    assert convert(dense_recordings, out) == 0
    stats = json.loads((out / "train" / "meta" / "stats.json").read_text())
    pixels = np.concatenate([f.cameras["wrist"].rgb.reshape(-1, 3) / 255.0 for path in sorted(dense_recordings.glob("*train*"))
                             for f in read_episode(path).dense_frames()])
    assert np.allclose(np.ravel(stats["observation.images.wrist"]["mean"]), pixels.mean(axis=0), atol=1e-6)
    assert np.allclose(np.ravel(stats["observation.images.wrist"]["std"]), pixels.std(axis=0), atol=1e-4)
    depth_mean = np.ravel(stats["observation.depth.wrist"]["mean"])  # LeRobot's depth statistics: in mm, not / 255
    assert depth_mean.shape == (1,) and 100 < depth_mean[0] < 3000


def test_summary_suggests_act_with_a_chunk_the_shortest_episode_holds(dense_recordings, tmp_path, capsys):
    out = tmp_path / "dense3"
    assert convert(dense_recordings, out) == 0
    printed = capsys.readouterr().out
    chunk, steps = act_chunk(9, RECORDED_FPS)  # the shorter train episode has 9 frames
    assert (chunk, steps) == (8, 4)  # 2 s at 4 fps
    assert f"--policy.chunk_size={chunk} --policy.n_action_steps={steps}" in printed
    assert f"lerobot-doctor gate {out / 'train'} --policy act --chunk-size {chunk}" in printed
    assert act_chunk(5, 10) == (5, 2) and act_chunk(300, 10) == (20, 10)


@pytest.mark.parametrize("options, message", [
    (["--action-space", "cartesian"], "unknown --action-space 'cartesian'; accepted: joints, ee"),
    (["--fps", "3"], "--fps 3 does not divide the recorded dense rate 4 fps"),
    (["--fps", "0"], "--fps 0 is out of range"),
])
def test_bad_dense_option_is_one_line_and_exit_2(dense_recordings, tmp_path, capsys, options, message):
    out = tmp_path / "bad"
    assert convert(dense_recordings, out, *options) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not out.exists() and not list(tmp_path.glob(".bad*"))


def test_action_space_needs_the_dense_granularity(dense_recordings, tmp_path, capsys):
    out = tmp_path / "keyframes"
    code = main(["convert", "--in", str(dense_recordings), "--out", str(out), "--repo-id", "me/pb",
                 "--action-space", "ee", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "--action-space applies to --granularity dense only" in err
    assert len(err.strip().splitlines()) == 1 and not out.exists()


def test_keyframe_export_suggests_hiveformer(dense_recordings, tmp_path, capsys):
    out = tmp_path / "keyframes"
    assert main(["convert", "--in", str(dense_recordings), "--out", str(out), "--repo-id", "me/pb", "--val-ratio", "0",
                 "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "lerobot-train --policy.type=hiveformer" in printed and "--policy.type=act" not in printed
    assert "lerobot-train --policy.type=hiveformer" in (out / "README.md").read_text()


def test_lerobot_doctor_gate_passes_the_suggested_act_chunk(tmp_path, write_dense_recording):
    gate = pytest.importorskip("lerobot_doctor.gate", reason="lerobot-doctor is not installed (pip install lerobot-doctor)")
    raw = tmp_path / "raw"
    raw.mkdir()
    train = get_task("push_buttons").split_variations("train")
    for i in range(2):  # the gate wants most episodes >= 50 frames for ACT
        write_dense_recording(raw, "train", train[i], 10 + i, ticks=52 + i)
    assert convert(raw, tmp_path / "out") == 0
    result = gate.gate_check(tmp_path / "out" / "train", policy="act", custom_chunk_size=act_chunk(52, RECORDED_FPS)[0])
    assert result.passed, result.blockers


# -- closed loop on real recordings ------------------------------------------------------------

def evaluate(*args):
    return subprocess.run([sys.executable, "-m", "demo_factory.cli", "eval", *args], capture_output=True, text=True)


@pytest.fixture(scope="module")
def dense_push_buttons(tmp_path_factory):
    """One push_buttons train and one test episode recorded with dense frames at 20 fps (32x32 cameras),
    converted densely with joints and with ee actions: {"joints": root, "ee": root}."""
    base = tmp_path_factory.mktemp("dense_pb")
    for split in ("train", "test"):
        assert main(["generate", "--task", "push_buttons", "--split", split, "--episodes", "1", "--image-size", "32",
                     "--dense-fps", "20", "--workers", "1", "--out", str(base / "raw" / split)]) == 0
    roots = {}
    for space in ("joints", "ee"):
        roots[space] = base / space
        assert main(["convert", "--in", str(base / "raw"), "--out", str(roots[space]), "--repo-id", f"me/pb_{space}",
                     "--granularity", "dense", "--action-space", space, "--no-progress"]) == 0
    return roots


@pytest.mark.slow
@pytest.mark.parametrize("space", ["joints", "ee"])
def test_replaying_the_experts_dense_actions_succeeds_closed_loop(dense_push_buttons, tmp_path, space):
    out = tmp_path / "eval"
    result = evaluate("--expert", "--dataset", str(dense_push_buttons[space]), "--episodes", "1", "--out", str(out))
    assert result.returncode == 0, result.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    assert results["control"]["action_space"] == space and results["control"]["fps"] == 20
    assert {"train", "test_unseen_synthetic", "test_unseen_corrupted"} <= set(results["splits"])
    for split, summary in results["splits"].items():
        assert summary["success_rate"] == 1.0, (split, summary["failure_reasons"])
    row = json.loads((out / "episodes.jsonl").read_text().splitlines()[0])
    assert row["action_space"] == space and len(row["actions"]) == row["steps"] > 10
    assert (out / "results.md").is_file() and (out / "results.png").is_file()


@pytest.mark.slow
def test_holding_still_scores_zero_within_the_time_limit(dense_push_buttons, tmp_path):
    out = tmp_path / "eval"
    result = evaluate("--current-pose", "--dataset", str(dense_push_buttons["joints"]), "--splits", "train",
                      "--episodes", "1", "--max-seconds", "2", "--out", str(out))
    assert result.returncode == 0, result.stderr[-3000:]
    row = json.loads((out / "episodes.jsonl").read_text())
    assert not row["success"] and row["failure_reason"] == "step limit" and row["steps"] == 40


def test_bad_eval_action_space_is_one_line_and_exit_2(tmp_path):
    result = evaluate("--expert", "--task", "push_buttons", "--action-space", "torques", "--out", str(tmp_path / "o"))
    lines = [line for line in result.stderr.splitlines() if not line.startswith("pybullet build time")]  # pybullet's banner
    assert result.returncode == 2 and len(lines) == 1
    assert "unknown --action-space 'torques'; accepted: keyframe, joints, ee" in result.stderr
    assert not (tmp_path / "o").exists()


@pytest.fixture(scope="module")
def tiny_act(dense_push_buttons, tmp_path_factory):
    """ACT trained for two steps with the command the converter suggests (chunk from the shortest episode)."""
    root = dense_push_buttons["joints"] / "train"
    info = json.loads((root / "meta" / "info.json").read_text())
    shortest = min(e["frames"] for e in json.loads((root / "meta" / "demo_factory.json").read_text())["episodes"])
    out = tmp_path_factory.mktemp("act") / "train"
    args = act_train_args("me/pb_joints_train", root, CAMERAS, (32, 32), out, steps=2, batch_size=2, num_workers=0,
                          log_freq=1, chunk=act_chunk(shortest, 20))
    command = [str(Path(sys.executable).with_name("lerobot-train")), *args[1:], "--save_freq=2"]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1", "CUDA_VISIBLE_DEVICES": ""}
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    return out / "checkpoints" / "last" / "pretrained_model"


@pytest.mark.slow
def test_tiny_act_runs_closed_loop_through_demo_factory_eval(tiny_act, dense_push_buttons, tmp_path):
    out = tmp_path / "eval"
    result = evaluate("--policy.path", str(tiny_act), "--task", "push_buttons", "--splits", "test", "--episodes", "1",
                      "--image-size", "32", "--max-seconds", "3", "--out", str(out))
    assert result.returncode == 0, result.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    assert results["policy"].startswith("act") and results["control"]["action_space"] == "joints"  # from train_config
    row = json.loads((out / "episodes.jsonl").read_text())
    assert row["steps"] == 60 and len(row["actions"]) == 60 and len(row["actions"][0]) == 8
    wrong = evaluate("--policy.path", str(tiny_act), "--dataset", str(dense_push_buttons["ee"]), "--out",
                     str(tmp_path / "wrong"))
    assert wrong.returncode == 2 and "trained on a joints export" in wrong.stderr


@pytest.mark.slow
def test_tiny_act_runs_through_lerobot_eval(tiny_act, tmp_path):
    command = [
        str(Path(sys.executable).with_name("lerobot-eval")),
        "--env.discover_packages_path=demo_factory.evaluate.lerobot_env", "--env.type=demo_factory",
        "--env.task=push_buttons", "--env.image_height=32", "--env.image_width=32", "--env.action_space=joints",
        "--env.max_seconds=1", f"--policy.path={tiny_act}", "--policy.device=cpu", "--eval.n_episodes=1",
        "--eval.batch_size=1", f"--output_dir={tmp_path / 'lerobot_eval'}",
    ]
    result = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert result.returncode == 0, result.stderr[-3000:]
    assert "'n_episodes': 1" in result.stdout + result.stderr and "pc_success" in result.stdout + result.stderr
