"""A smoke version of `make reference-unseen` (the whole chain: generation, conversion, training, a learning
curve, evaluation per split), and the reference run's options and commands (tower: test_reference_run_tower)."""

import json
from pathlib import Path

import pytest

from demo_factory.convert.converter import read_dataset_provenance
from demo_factory.instructions import shipped_human_instructions
from demo_factory.tools.reference_run import main, selected_step


@pytest.mark.slow
@pytest.mark.timeout(1800)  # the whole chain: ~15 minutes beside the rest of the suite on 2 cores
def test_unseen_reference_run_trains_on_paper_train_ids_and_curves_the_unseen_split(tmp_path):
    out = tmp_path / "unseen"
    # Two of the authors' sentences, for two test variations (the whole file names 51: test_paper_variations).
    rows = [r for r in json.loads(shipped_human_instructions("push_buttons").read_text())
            if r["fields"]["task"].startswith("push_buttons")]
    rows = [rows[0], next(r for r in rows if r["fields"]["variation"] != rows[0]["fields"]["variation"])]
    human_file = tmp_path / "human.json"
    human_file.write_text(json.dumps(rows))
    arguments = ["--unseen", "--out", str(out), "--train-variations", "2", "--episodes-per-variation", "1",
                 "--steps", "2", "--curve", "2", "--batch-size", "2", "--eval-episodes", "1", "--workers", "2",
                 "--image-size", "32", "--seed", "3", "--train-arg=--policy.whole_episodes=true",
                 "--human-instructions", str(human_file)]
    assert main(arguments) == 0
    summary = json.loads((out / "reference_run.json").read_text())
    configuration = summary["configuration"]
    assert configuration["variations"] == ["0", "1"] and configuration["text_encoder"] == "minilm_causal"
    assert set(summary["stage_seconds"]) >= {"generate_train", "generate_test", "convert", "train", "eval"}
    checkpoint = out / "train" / "checkpoints" / "last" / "pretrained_model"
    assert json.loads((checkpoint / "train_config.json").read_text())["seed"] == 3
    config = json.loads((checkpoint / "config.json").read_text())  # the unseen recipe, but for --train-arg's key
    assert config["stem_point_cloud"] is False and config["whole_episodes"] is True
    assert config["instruction_position_embeddings"] is True and config["optimizer_lr"] == 2e-3
    assert config["lr_schedule"] == "constant_then_cosine" and config["heatmap_loss_weight"] == 0.1
    assert json.loads((checkpoint / "train_config.json").read_text())["scheduler"]["type"] == "constant_then_cosine"
    assert config["text_encoder"] == "minilm_causal" and config["n_history"] == 10
    splits = summary["results"]["splits"]
    assert {"train", "test_unseen_synthetic", "test_unseen_corrupted", "test_unseen_human"} <= set(splits)
    # The test episodes are those of the variations the human-written sentences name, with those sentences.
    human = read_dataset_provenance(out / "dataset" / "test_unseen_human")[1]["episodes"]
    assert sorted((e["variation_id"], e["instruction"]) for e in human) == sorted(
        (r["fields"]["variation"], r["fields"]["instruction"]) for r in rows)
    assert [c["step"] for c in summary["learning_curve"]] == [1, 2]
    assert all(0.0 <= c["test_unseen_synthetic_success_rate"] <= 1.0 for c in summary["learning_curve"])
    # The curve's checkpoints on validation scenes (their own scene seeds); the best one on the test scenes.
    test_seeds = {e["seed"] for e in map(json.loads, (out / "eval" / "episodes.jsonl").read_text().splitlines())}
    for step in ("000001", "000002"):
        validation = json.loads((out / "validation" / step / "results.json").read_text())
        assert set(validation["splits"]) == {"train", "test_unseen_synthetic"}
        assert test_seeds.isdisjoint(
            e["seed"] for e in map(json.loads, (out / "validation" / step / "episodes.jsonl").read_text().splitlines()))
    assert summary["selected_step"] == selected_step(summary["learning_curve"])
    assert Path(summary["evaluated_checkpoint"]).parent.name == f"{summary['selected_step']:06d}"
    assert (out / "learning_curve.png").read_bytes().startswith(b"\x89PNG")
    # The policy trained with every synthetic instruction of its variations: the dataset lists them.
    assert (out / "dataset" / "train" / "meta" / "task_paraphrases.json").exists()
    # Run again: every stage is complete, so nothing runs and the same results come back.
    assert main(arguments) == 0
    again = json.loads((out / "reference_run.json").read_text())
    assert again["stage_seconds"] == {} and again["results"] == summary["results"]


def test_the_checkpoint_kept_is_the_best_on_validation_the_later_on_a_tie():
    curve = [{"step": step, "success_rate": rate} for step, rate in [(500, 0.5), (1000, 0.9), (1500, 0.9), (2000, 0.8)]]
    assert selected_step(curve) == 1500
    assert selected_step(curve[:1]) == 500


@pytest.mark.parametrize("argv, message", [
    (["--steps", "10", "--curve", "3"], "--curve 3: a positive number of checkpoints that divides --steps 10"),
    (["--policy", "act", "--task", "tower"], "--task tower: the act reference run is push_buttons only"),
    (["--unseen", "--policy", "act"], "--unseen is the HiveFormer run on the paper's train variations: without --policy"),
    (["--unseen", "--task", "tower", "--ablation", "one_hot"], "--ablation one_hot: one of the paper's ablation rows"),
    (["--unseen", "--variation", "150"], "--variation 150: with --unseen, a paper train id 0-99"),
    (["--unseen", "--variation", "red"], "--variation red: with --unseen, a paper train id 0-99"),
    (["--unseen", "--variation", "3", "--train-variations", "5"], "--variation and --train-variations: with --unseen, one"),
    (["--train-variations", "5"], "--train-variations 5: with --unseen, 1 to 100"),
    (["--unseen", "--train-variations", "101"], "--train-variations 101: with --unseen, 1 to 100"),
    (["--human-instructions", "x.json"], "--human-instructions x.json: only with --unseen"),
    (["--unseen", "--human-instructions", "/nonexistent.json"], "--human-instructions /nonexistent.json: not a file"),
    (["--train-arg", "policy.whole_episodes"], "--train-arg 'policy.whole_episodes': expected --KEY=VALUE"),
    (["--policy", "act", "--train-arg=--steps=3"], "--train-arg: HiveFormer runs only"),
    (["--unseen", "--text-encoder", "bogus"], "argument --text-encoder: invalid choice: 'bogus'"),
    (["--extra-episodes", "-1"], "--extra-episodes -1: a number >= 0"),
    (["--unseen", "--extra-episodes", "5"], "--extra-episodes 5: a number >= 0, above 0 only for HiveFormer runs without"),
    (["--policy", "act", "--extra-episodes", "5"], "--extra-episodes 5: a number >= 0, above 0 only for HiveFormer runs"),
    (["--ablation", "no_history"], "--ablation no_history: one of the paper's ablation rows, measured against `make "
                                   "reference-unseen`: only with --unseen, on push_buttons"),
    (["--unseen", "--ablation", "no_history", "--train-arg=--policy.use_history=true"],
     "--ablation no_history: --policy.use_history=true would undo it"),
    (["--unseen", "--ablation", "one_hot", "--text-encoder", "minilm"], "--ablation one_hot: --text-encoder would undo it"),
    (["--unseen", "--ablation", "no_hands"], "argument --ablation: invalid choice: 'no_hands'"),
    (["--perturb", "fog"], "--perturb fog: unknown perturbation 'fog'; accepted: lighting,"),
    (["--perturb", "all=1.5"], "--perturb all=1.5: perturbation probability 1.5 of 'all' is out of range"),
])
def test_bad_options_are_refused_naming_the_value(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2 and message in capsys.readouterr().err


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


def test_make_reference_pins_its_recipe_and_train_arguments_replace_settings(tmp_path):
    from argparse import Namespace

    from demo_factory.tools.reference_run import SEEN_RECIPE, UNSEEN_RECIPE, hiveformer_run_command, policy_flags

    run = Namespace(task="push_buttons", suite=None, unseen=False, steps=1500, batch_size=16, text_encoder="one_hot",
                    n_history=10, curve=1, train_arg=[], ablation=None)
    command = hiveformer_run_command(run, tmp_path / "train", tmp_path / "out")
    assert set(policy_flags(SEEN_RECIPE)) <= set(command) and "--policy.n_history=10" in command and "--save_freq=500" in command
    run.train_arg = ["--policy.whole_episodes=true"]
    command = hiveformer_run_command(run, tmp_path / "train", tmp_path / "out")
    assert "--policy.whole_episodes=true" in command and "--policy.whole_episodes=false" not in command
    assert "--policy.stem_point_cloud=true" in command
    tower = Namespace(**{**vars(run), "task": "tower", "train_arg": []})  # make reference-tower: annealed from 2e-3
    command = hiveformer_run_command(tower, tmp_path / "train", tmp_path / "out")
    assert set(policy_flags(SEEN_RECIPE)) <= set(command) and "--policy.lr_schedule=cosine" in command
    assert "--policy.optimizer_lr=0.002" in command
    assert "--policy.lr_schedule=cosine" not in hiveformer_run_command(run, tmp_path / "train", tmp_path / "out")
    unseen = Namespace(**{**vars(run), "unseen": True, "train_arg": []})  # windows, the authors' 4-channel stem, 2e-3
    command = hiveformer_run_command(unseen, tmp_path / "train", tmp_path / "out")
    assert set(policy_flags(UNSEEN_RECIPE)) <= set(command) and "--policy.instruction_position_embeddings=false" not in command
    assert "--policy.stem_point_cloud=false" in command and "--policy.stem_point_cloud=true" not in command
    assert "--policy.heatmap_loss_weight=0.1" in command  # the heatmap loss: unseen only
    assert "--policy.heatmap_loss_weight=0.1" not in hiveformer_run_command(run, tmp_path / "train", tmp_path / "out")
    assert "--policy.optimizer_lr=0.002" in command and "--policy.optimizer_lr=0.002" not in hiveformer_run_command(
        run, tmp_path / "train", tmp_path / "out")  # make reference keeps the plugin's rate


def test_hiveformer_runs_validate_a_checkpoint_about_every_100_steps_by_default():
    from demo_factory.tools.reference_run import default_curve, parse_arguments

    assert parse_arguments([]).curve == 15 and parse_arguments(["--steps", "1000"]).curve == 10
    assert parse_arguments(["--unseen"]).curve == 4 and parse_arguments(["--policy", "act"]).curve == 1
    assert parse_arguments(["--steps", "1500", "--curve", "3"]).curve == 3
    tower = parse_arguments(["--task", "tower"])  # make reference-tower: 80 episodes, 6000 steps, validated every 1200
    assert (tower.episodes_per_variation, tower.steps, tower.curve) == (80, 6000, 5)
    assert parse_arguments(["--task", "tower", "--steps", "1200"]).curve == 5  # as --unseen's, the preset's curve
    assert default_curve(1001) == 7 and default_curve(2) == 1 and default_curve(150) == 1


def test_seen_runs_give_their_one_colour_variation_more_episodes_of_their_own_scenes(tmp_path):
    import subprocess

    from demo_factory.tools.reference_run import (
        EXTRA_EPISODES,
        extra_generation_command,
        parse_arguments,
        single_colour_variations,
    )

    assert single_colour_variations("tower", ["46", "0", "1", "red"]) == ["46", "red"]  # green: one cube
    assert parse_arguments([]).extra_episodes == EXTRA_EPISODES["push_buttons"] == 60  # 205 (maroon): 100 in all
    assert parse_arguments(["--task", "tower"]).extra_episodes == EXTRA_EPISODES["tower"] == 80  # 46 (green): 160
    assert parse_arguments(["--unseen"]).extra_episodes == 0
    assert extra_generation_command(parse_arguments(["--extra-episodes", "0"])) is None
    assert extra_generation_command(parse_arguments(["--variation", "24", "--variation", "2"])) is None
    args = parse_arguments(["--variation", "navy", "--variation", "205", "--variation", "2", "--extra-episodes", "2",
                            "--image-size", "32", "--workers", "1"])
    subprocess.run(extra_generation_command(args) + ["--out", str(tmp_path / "extra")], check=True, capture_output=True)
    recorded = sorted(p.name for p in (tmp_path / "extra").glob("*.mcap"))
    # Two episodes of each one-button variation (navy is a colour sequence, 205 an id), none of the three-button one.
    assert len(recorded) == 4 and sum("var0205" in name for name in recorded) == 2
    assert not any("var0002_" in name for name in recorded)


def test_randomised_runs_perturb_every_training_generation_and_nothing_else():
    from demo_factory.tools.reference_run import (
        extra_generation_command,
        generate_test_command,
        parse_arguments,
        train_generation_command,
    )

    args = parse_arguments(["--perturb", "all=0.3", "--robustness"])
    assert args.robustness
    for command in (train_generation_command(args, args.variations, 2), extra_generation_command(args)):
        assert command[command.index("--perturb") + 1] == "all=0.3"
    assert "--perturb" not in generate_test_command(args)  # the unseen splits' scenes stay as evaluated
    assert "--perturb" not in train_generation_command(parse_arguments([]), ["2"], 2)


def test_make_reference_randomised_is_the_measured_recipe():
    import re
    import shlex

    from demo_factory.tools.reference_run import parse_arguments

    makefile = (Path(__file__).resolve().parents[1] / "Makefile").read_text().replace("\\\n", " ")
    recipe = re.search(r"^reference-randomised:.*\n\t(.*)$", makefile, re.MULTILINE).group(1)
    args = parse_arguments(shlex.split(recipe.split("demo_factory.tools.reference_run", 1)[1]))
    # docs/robustness.md: visual factors at p 0.5 on 360 episodes, 3000 steps, evaluated under every factor
    assert (args.perturb, args.robustness, args.steps) == ("visual=0.5", True, 3000)
    assert (args.episodes_per_variation, args.extra_episodes, len(args.variations)) == (80, 120, 3)


def test_checkpoints_are_saved_at_every_curve_point_and_at_most_500_steps_apart():
    from demo_factory.tools.reference_run import save_interval

    assert save_interval(4500, 3) == 500 and save_interval(1500, 1) == 500 and save_interval(300, 1) == 300
    assert save_interval(2, 2) == 1 and save_interval(1001, 1) == 143


def test_unseen_runs_take_the_paper_train_ids_asked_and_say_which_test_ones_they_cannot_compose():
    from demo_factory.tools.reference_run import (
        composability_note,
        parse_arguments,
        pressed_colours,
        uncomposable_test_variations,
    )

    default = parse_arguments(["--unseen"])  # every paper train id, 6 episodes each
    assert default.variations == [str(i) for i in range(100)] and default.episodes_per_variation == 6
    assert (default.steps, default.text_encoder) == (8000, "minilm_causal")
    assert parse_arguments(["--unseen", "--train-variations", "3"]).variations == ["0", "1", "2"]
    named = parse_arguments(["--unseen", "--variation", "0", "--variation", "2"])
    assert named.variations == ["0", "2"] and named.train_variations is None
    assert pressed_colours(["0", "8"]) == {(0, "green"), (1, "rose"), (2, "black"), (0, "orange"), (1, "navy")}
    # A test variation is composable when each of its colours was pressed at the same place in training. The
    # first 20 train ids leave 68 of the 100 test variations; all 100 the 9 that name azure second (no train
    # variation does).
    first_20 = [str(i) for i in range(20)]
    assert len(uncomposable_test_variations(first_20)) == 68
    left = uncomposable_test_variations(default.variations)
    assert len(left) == 9 and pressed_colours(left) - pressed_colours(default.variations) == {(1, "azure")}
    note = composability_note(first_20)
    assert note.startswith("note: 68 of the 100 test variations") and "azure second" in note and "third" in note
    assert composability_note([str(i) for i in range(100, 200)]) is None  # (test ids: every press is made)


def test_each_ablation_is_the_unseen_run_with_one_part_of_the_model_taken_out(tmp_path):
    from demo_factory.tools.reference_run import (ABLATIONS, UNSEEN_RECIPE, hiveformer_run_command, parse_arguments,
                                                  policy_flags)
    from demo_factory.tools.runs import ABLATION_ROWS

    assert set(ABLATIONS) == set(ABLATION_ROWS)  # every ablation has its row in the ablation table
    full = hiveformer_run_command(parse_arguments(["--unseen"]), tmp_path / "train", tmp_path / "out")
    for name, settings in ABLATIONS.items():
        args = parse_arguments(["--unseen", "--ablation", name])
        command = hiveformer_run_command(args, tmp_path / "train", tmp_path / "out")
        changed = set(policy_flags(settings))
        assert changed <= set(command) and not changed & set(full)
        # Everything else is the full model's: the same steps, recipe and data.
        keys = {flag.split("=", 1)[0] for flag in changed}
        unchanged = [a for a in command if a.split("=", 1)[0] not in keys]
        assert unchanged == [a for a in full if a.split("=", 1)[0] not in keys]
        assert set(policy_flags(UNSEEN_RECIPE)) - changed <= set(command)
    one_hot = parse_arguments(["--unseen", "--ablation", "one_hot"])
    assert one_hot.text_encoder == "one_hot"  # as its reference_run.json records it
    assert "--policy.text_encoder=minilm_words" not in hiveformer_run_command(one_hot, tmp_path, tmp_path)


@pytest.mark.parametrize("argv, folder", [
    ([], "reference"), (["--policy", "act"], "reference_act"), (["--task", "tower"], "reference_tower"),
    (["--suite", "ten_tasks"], "reference_ten_tasks"), (["--unseen"], "reference_unseen"),
    (["--unseen", "--task", "tower"], "reference_tower_unseen"),
    (["--unseen", "--ablation", "no_ex"], "reference_unseen_no_ex"),
])
def test_each_run_has_a_folder_of_its_own_by_default(argv, folder):
    from demo_factory.tools.reference_run import default_out, parse_arguments

    assert default_out(parse_arguments(argv)) == Path("outputs") / folder


def test_beyond_ten_tasks_defaults_to_its_measured_steps():
    from demo_factory.tools.reference_run import SUITE, parse_arguments

    beyond = parse_arguments(["--suite", "beyond_ten_tasks"])  # make reference-suite SUITE=beyond_ten_tasks
    assert (beyond.steps, beyond.curve) == (4000, 2)
    assert parse_arguments(["--suite", "ten_tasks"]).steps == SUITE["steps"]
    assert parse_arguments(["--suite", "beyond_ten_tasks", "--steps", "6000"]).steps == 6000


def test_tower_unseen_is_the_unseen_chain_on_towers_paper_variations(tmp_path):
    from demo_factory.tools.reference_run import (UNSEEN, UNSEEN_RECIPE, generate_test_command, hiveformer_run_command,
                                                  parse_arguments, policy_flags)
    from demo_factory.tools.runs import run_row

    args = parse_arguments(["--unseen", "--task", "tower"])  # make reference-tower-unseen
    assert args.variations == [str(i) for i in range(100)] and args.extra_episodes == 0
    assert (args.steps, args.episodes_per_variation, args.text_encoder) == (
        UNSEEN["steps"], UNSEEN["episodes_per_variation"], UNSEEN["text_encoder"])
    assert set(policy_flags(UNSEEN_RECIPE)) <= set(hiveformer_run_command(args, tmp_path, tmp_path))
    test = generate_test_command(args)  # one episode of each test variation the authors' sentences name
    assert test[test.index("--task") + 1] == "tower" and "--variations-from" in test
    summary = {"configuration": vars(args), "stage_seconds": {}, "results": {"splits": {}}}
    assert run_row(summary, "x")["recipe"] == "make reference-tower-unseen"
