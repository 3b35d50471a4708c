"""`python -m demo_factory.tools.keyframe_errors`: predicted keyframes against the expert's plan of the same scene."""

import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from demo_factory.rollout.scene import start_scene
from demo_factory.tasks import get_task
from demo_factory.tools.keyframe_errors import keyframe_errors, main, read_episodes


def expert_keyframes(task_name: str, variation_id: int, seed: int) -> list[list[float]]:
    task = get_task(task_name)
    world = start_scene(task, task.variation(variation_id), seed, image_size=(16, 16))
    try:
        return [[*k.pose, k.gripper_open] for k in task.expert(world)]
    finally:
        world.close()


def test_errors_are_the_offsets_of_the_predicted_keyframes_from_the_experts(tmp_path):
    plan = expert_keyframes("tower", 0, 11)
    turned = (Rotation.from_euler("z", 10, degrees=True) * Rotation.from_quat(plan[0][3:7])).as_quat()
    predicted = [list(k) for k in plan]
    predicted[0] = [plan[0][0] + 0.03, plan[0][1] - 0.04, plan[0][2] + 0.02, *turned, 1.0]  # 5 cm in xy, 2 in z, 10°
    episode = {"task": "tower", "split": "train", "variation_id": 0, "seed": 11, "predicted_keyframes": predicted}
    rows = keyframe_errors([episode, {**episode, "predicted_keyframes": plan[:2]}])
    assert [r["keyframe"] for r in rows] == list(range(len(plan)))
    assert [r["episodes"] for r in rows[:3]] == [2, 2, 1]  # the second episode predicted two keyframes only
    assert rows[0]["xy_cm"]["p90"] == pytest.approx(4.5, abs=0.01)  # 0 and 5 cm: the 90th percentile 4.5
    assert rows[0]["z_cm"]["median"] == pytest.approx(1.0, abs=0.01)
    assert rows[0]["rotation_deg"]["p90"] == pytest.approx(9.0, abs=0.01)
    assert all(r["xy_cm"]["p90"] < 1e-6 and r["rotation_deg"]["p90"] < 0.01 for r in rows[1:])
    # Both episodes share a scene, so the expert's mean keyframe is its keyframe: a constant prediction is exact.
    assert all(r["constant"]["xy_cm"]["p90"] < 1e-6 and r["constant"]["rotation_deg"]["p90"] < 0.01 for r in rows)

    path = tmp_path / "episodes.jsonl"
    path.write_text("".join(json.dumps(e) + "\n" for e in (episode, {**episode, "split": "test_unseen_human"})))
    result = subprocess.run([sys.executable, "-m", "demo_factory.tools.keyframe_errors", str(path), "--keyframes", "2"],
                            capture_output=True, text=True, check=True)
    table = [line.split() for line in result.stdout.splitlines()[1:]]
    assert [line[:3] for line in table] == [["0", "1", "5.00"], ["1", "1", "0.00"]]


def test_the_constant_baseline_is_the_spread_of_the_experts_keyframes_and_task_picks_episodes(tmp_path):
    """Two scenes: the constant prediction (the mean of their keyframes) misses each by half their distance."""
    plans = [expert_keyframes("tower", 0, seed) for seed in (11, 12)]
    episodes = [{"task": "tower", "split": "train", "variation_id": 0, "seed": seed, "predicted_keyframes": plan[:1]}
                for seed, plan in zip((11, 12), plans)]
    half = 100 * np.linalg.norm(np.subtract(plans[0][0][:2], plans[1][0][:2])) / 2
    angle = (Rotation.from_quat(plans[0][0][3:7]).inv() * Rotation.from_quat(plans[1][0][3:7])).magnitude()
    row = keyframe_errors(episodes)[0]
    assert row["xy_cm"]["median"] < 1e-6  # the policy predicted the expert's keyframes
    assert row["constant"]["xy_cm"]["median"] == pytest.approx(half, abs=0.01)
    assert row["constant"]["rotation_deg"]["median"] == pytest.approx(np.degrees(angle) / 2, abs=0.05)

    path = tmp_path / "episodes.jsonl"
    path.write_text("".join(json.dumps(e) + "\n" for e in [*episodes, {**episodes[0], "task": "push_buttons"}]))
    assert [e["seed"] for e in read_episodes(path, "train", "tower")] == [11, 12]
    with pytest.raises(SystemExit, match=r"--task 'stack_wine': no train episode of it .* \(it holds: push_buttons, tower\)"):
        read_episodes(path, "train", "stack_wine")


def test_bad_input_gets_one_line_naming_it(tmp_path, capsys):
    bad = tmp_path / "episodes.jsonl"
    bad.write_text("not json\n")
    with pytest.raises(SystemExit, match="not a readable episodes.jsonl"):
        main([str(bad)])
    bad.write_text(json.dumps({"task": "tower"}) + "\n")
    with pytest.raises(SystemExit, match="each line needs task, split, variation_id, seed and predicted_keyframes"):
        main([str(bad)])
    bad.write_text(json.dumps({"task": "tower", "split": "train", "variation_id": 0, "seed": 1,
                               "predicted_keyframes": []}) + "\n")
    with pytest.raises(SystemExit, match=r"--split 'test_unseen_human': no episode of it .* \(it holds: train\)"):
        main([str(bad), "--split", "test_unseen_human"])
    with pytest.raises(SystemExit):
        main([str(bad), "--keyframes", "0"])
    assert "--keyframes 0: must be at least 1" in capsys.readouterr().err
