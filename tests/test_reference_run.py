"""A smoke version of the reference run: the whole chain runs and writes its results table."""

import json
import shutil

import pytest

from demo_factory.convert.converter import read_dataset_provenance
from demo_factory.tools.reference_run import main


@pytest.mark.slow
def test_reference_run_chain_writes_its_results(tmp_path):
    out = tmp_path / "reference"
    arguments = ["--out", str(out), "--variation", "8", "--episodes-per-variation", "2", "--test-episodes", "1",
                 "--steps", "2", "--batch-size", "2", "--eval-episodes", "1", "--workers", "1",
                 "--image-size", "32", "--text-encoder", "clip_tiny_random", "--seed", "3",
                 "--train-arg=--policy.whole_episodes=true"]
    assert main(arguments) == 0
    summary = json.loads((out / "reference_run.json").read_text())
    assert set(summary["stage_seconds"]) == {"generate_train", "generate_test", "convert", "train", "eval"}
    assert "train" in summary["results"]["splits"]
    assert (out / "eval" / "results.md").read_text().strip()
    checkpoint = out / "train" / "checkpoints" / "last" / "pretrained_model"
    assert (checkpoint / "model.safetensors").exists()
    assert json.loads((checkpoint / "train_config.json").read_text())["seed"] == 3
    config = json.loads((checkpoint / "config.json").read_text())  # the pinned recipe, but for --train-arg's key
    assert config["whole_episodes"] is True and config["stem_point_cloud"] is True
    # Run again: every stage is complete, so nothing runs and the same results come back.
    assert main(arguments) == 0
    again = json.loads((out / "reference_run.json").read_text())
    assert again["stage_seconds"] == {} and again["results"] == summary["results"]


@pytest.mark.slow
def test_tower_reference_run_takes_its_history_from_the_longest_episode_and_plots_a_curve(tmp_path):
    out = tmp_path / "tower"
    arguments = ["--task", "tower", "--out", str(out), "--variation", "46", "--variation", "0",
                 "--episodes-per-variation", "1", "--test-episodes", "1", "--steps", "2", "--curve", "2",
                 "--batch-size", "2", "--eval-episodes", "1", "--workers", "1", "--image-size", "32",
                 "--text-encoder", "one_hot"]
    assert main(arguments) == 0
    summary = json.loads((out / "reference_run.json").read_text())
    assert summary["configuration"]["n_history"] == 17  # the two-cube episode: 8 keyframes a cube + the start
    config = json.loads((out / "train" / "checkpoints" / "last" / "pretrained_model" / "config.json").read_text())
    assert config["n_history"] == 17
    assert [c["step"] for c in summary["learning_curve"]] == [1, 2]
    assert all(0.0 <= c["success_rate"] <= 1.0 and c["per_variation"] for c in summary["learning_curve"])
    assert (out / "curve" / "000001" / "results.json").exists()
    assert (out / "learning_curve.png").read_bytes().startswith(b"\x89PNG")
    assert "eval_step_1" in summary["stage_seconds"]
    assert json.loads((out / "eval" / "results.json").read_text())["task"] == "tower"

    # Interrupted after the first checkpoint: the training resumes from it (step 1's weights, optimizer and
    # data order), saves the last step, and the evaluation runs on that.
    checkpoints = out / "train" / "checkpoints"
    first = (checkpoints / "000001" / "pretrained_model" / "model.safetensors").read_bytes()
    shutil.rmtree(checkpoints / "000002")
    shutil.rmtree(out / "eval")
    (checkpoints / "last").unlink()
    (checkpoints / "last").symlink_to("000001")
    assert main(arguments) == 0
    resumed = json.loads((checkpoints / "000002" / "pretrained_model" / "train_config.json").read_text())
    assert resumed["resume"] is True and resumed["steps"] == 2
    assert (checkpoints / "000001" / "pretrained_model" / "model.safetensors").read_bytes() == first
    assert "Start offline training" in (out / "train.log").read_text()
    assert set(json.loads((out / "reference_run.json").read_text())["stage_seconds"]) == {"train", "eval"}


@pytest.mark.slow
def test_unseen_reference_run_trains_on_paper_train_ids_and_curves_the_unseen_split(tmp_path):
    out = tmp_path / "unseen"
    arguments = ["--unseen", "--out", str(out), "--train-variations", "2", "--episodes-per-variation", "1",
                 "--steps", "2", "--curve", "2", "--batch-size", "2", "--eval-episodes", "1", "--workers", "2",
                 "--image-size", "32"]
    assert main(arguments) == 0
    summary = json.loads((out / "reference_run.json").read_text())
    configuration = summary["configuration"]
    assert configuration["variations"] == ["0", "1"] and configuration["text_encoder"] == "minilm"
    splits = summary["results"]["splits"]
    assert {"train", "test_unseen_synthetic", "test_unseen_corrupted", "test_unseen_human"} <= set(splits)
    # The test episodes are those of the variations the authors' human-written sentences name: 51.
    human = read_dataset_provenance(out / "dataset" / "test_unseen_human")[1]["episodes"]
    assert len({e["variation_id"] for e in human}) == 51
    assert [c["step"] for c in summary["learning_curve"]] == [1, 2]
    assert all(0.0 <= c["test_unseen_synthetic_success_rate"] <= 1.0 for c in summary["learning_curve"])
    earlier = json.loads((out / "curve" / "000001" / "results.json").read_text())["splits"]
    assert set(earlier) == {"train", "test_unseen_synthetic"}
    assert (out / "learning_curve.png").read_bytes().startswith(b"\x89PNG")
    # The policy trained with every synthetic instruction of its variations: the dataset lists them.
    assert (out / "dataset" / "train" / "meta" / "task_paraphrases.json").exists()


def test_curve_must_divide_the_steps():
    with pytest.raises(SystemExit):
        main(["--steps", "10", "--curve", "3"])
    with pytest.raises(SystemExit):
        main(["--policy", "act", "--task", "tower"])
    for wrong in (["--unseen", "--task", "tower"], ["--unseen", "--variation", "3"], ["--train-variations", "5"],
                  ["--unseen", "--train-variations", "101"], ["--train-arg", "policy.whole_episodes"],
                  ["--policy", "act", "--train-arg=--steps=3"]):
        with pytest.raises(SystemExit):
            main(wrong)


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


def test_train_arguments_replace_the_runs_own_setting_of_their_key():
    from demo_factory.tools.reference_run import with_arguments

    command = ["lerobot-train", "--policy.whole_episodes=false", "--steps=5"]
    assert with_arguments(command, ["--policy.whole_episodes=true", "--policy.lr=1"]) == [
        "lerobot-train", "--steps=5", "--policy.whole_episodes=true", "--policy.lr=1"]


def test_checkpoints_are_saved_at_every_curve_point_and_at_most_500_steps_apart():
    from demo_factory.tools.reference_run import save_interval

    assert save_interval(4500, 3) == 500 and save_interval(1500, 1) == 500 and save_interval(300, 1) == 300
    assert save_interval(2, 2) == 1 and save_interval(1001, 1) == 143
