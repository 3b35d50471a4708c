"""`make reference-suite`: one multi-task HiveFormer over a suite's tasks (the paper's Table 1 setting), and the
multi-task evaluation it ends with: success per task and their average, failures per task."""

import json

import pytest

from demo_factory.cli import main as demo_factory
from demo_factory.convert.converter import read_dataset_provenance
from demo_factory.suites import SUITES
from demo_factory.tasks import get_task
from demo_factory.tools.reference_run import SUITE_RECIPE, TOWER_RECIPE, hiveformer_run_command, main, parse_arguments

TWO_TASKS = "motion_planner"  # open_drawer and close_drawer: the smallest suite


@pytest.fixture(scope="module")
def two_task_dataset(tmp_path_factory):
    """A converted multi-task dataset of the two-task suite: one train episode a task, 32x32 cameras."""
    base = tmp_path_factory.mktemp("suite")
    assert demo_factory(["generate", "--suite", TWO_TASKS, "--episodes-per-task", "1", "--image-size", "32",
                         "--workers", "1", "--out", str(base / "raw" / "train")]) == 0
    assert demo_factory(["convert", "--in", str(base / "raw"), "--out", str(base / "dataset"), "--repo-id", "me/mp",
                         "--val-ratio", "0", "--no-progress"]) == 0
    return base / "dataset"


def test_a_multi_task_dataset_is_evaluated_per_task(two_task_dataset, tmp_path, capsys):
    out = tmp_path / "eval"
    assert demo_factory(["eval", "--expert", "--dataset", str(two_task_dataset), "--episodes", "2",
                         "--out", str(out)]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["task"] == TWO_TASKS
    train = results["splits"]["train"]
    assert set(train["per_task"]) == set(SUITES[TWO_TASKS]) and train["episodes"] == 4
    assert all(t["episodes"] == 2 and t["success_rate"] == 1.0 for t in train["per_task"].values())
    assert train["task_average"] == 1.0
    rows = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert sorted(r["task"] for r in rows) == sorted(SUITES[TWO_TASKS] * 2)
    table = (out / "results.md").read_text()
    assert "## train: success per task (%)" in table and "| policy | close_drawer | open_drawer | average |" in table
    printed = capsys.readouterr().out
    assert "average over the tasks" in printed and "open_drawer" in printed


def test_one_task_of_a_multi_task_dataset_is_evaluated_alone_and_others_are_refused(two_task_dataset, tmp_path,
                                                                                    capsys):
    out = tmp_path / "one"
    assert demo_factory(["eval", "--expert", "--dataset", str(two_task_dataset), "--task", "open_drawer",
                         "--episodes", "1", "--out", str(out)]) == 0
    split = json.loads((out / "results.json").read_text())["splits"]["train"]
    assert split["episodes"] == 1 and "per_task" not in split and "per_variation" in split
    assert demo_factory(["eval", "--expert", "--dataset", str(two_task_dataset), "--task", "tower",
                         "--episodes", "1", "--out", str(tmp_path / "refused")]) == 2
    assert "--task tower is not in --dataset" in capsys.readouterr().err
    assert not (tmp_path / "refused").exists()


def test_a_suite_run_takes_each_tasks_first_train_variation_and_its_recipe(tmp_path):
    args = parse_arguments(["--suite", "ten_tasks", "--out", str(tmp_path)])
    assert list(args.variations) == list(SUITES["ten_tasks"])
    assert args.variations == {t: str(get_task(t).split_variations("train")[0].id) for t in SUITES["ten_tasks"]}
    assert (args.steps, args.curve, args.eval_episodes, args.validation_episodes) == (12000, 4, 20, 10)
    # The converter's multi-task suggestion: tower's annealed recipe with the heatmap loss and a heavier position loss.
    assert SUITE_RECIPE == TOWER_RECIPE | {"heatmap_loss_weight": 0.1, "position_loss_weight": 30.0}
    assert args.extra_episodes == 0 and args.test_episodes == 0 and args.text_encoder == "one_hot"
    command = hiveformer_run_command(args, tmp_path / "dataset", tmp_path / "train")
    assert all(f"--policy.{name}={str(value).lower()}" in command for name, value in SUITE_RECIPE.items())


def test_a_task_name_runs_the_suite_chain_on_that_task_alone(tmp_path, capsys):
    args = parse_arguments(["--suite", "pick_and_lift", "--out", str(tmp_path)])
    assert args.variations == {"pick_and_lift": str(get_task("pick_and_lift").split_variations("train")[0].id)}
    assert (args.steps, args.eval_episodes, args.text_encoder) == (12000, 20, "one_hot")
    with pytest.raises(SystemExit):
        parse_arguments(["--suite", "no_such_task"])
    assert "argument --suite: invalid choice: 'no_such_task'" in capsys.readouterr().err


@pytest.mark.parametrize("other", [["--task", "tower"], ["--unseen"], ["--variation", "3"], ["--policy", "act"]])
def test_a_suite_run_refuses_single_task_options(other, capsys):
    with pytest.raises(SystemExit) as exit_:
        parse_arguments(["--suite", "ten_tasks", *other])
    assert exit_.value.code == 2
    assert "--suite ten_tasks: a HiveFormer run of the suite's tasks" in capsys.readouterr().err


def test_the_other_tasks_suite_holds_every_task_beyond_ten_tasks_and_the_two_reference_tasks():
    from demo_factory.tasks import TASKS

    assert set(SUITES["beyond_ten_tasks"]) == set(TASKS) - set(SUITES["ten_tasks"]) - {"push_buttons", "tower"}


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_the_suite_chain_trains_one_policy_and_reports_each_task(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["--suite", TWO_TASKS, "--out", str(out), "--episodes-per-variation", "1", "--steps", "2",
                 "--curve", "2", "--batch-size", "2", "--eval-episodes", "1", "--validation-episodes", "1",
                 "--image-size", "32", "--workers", "1"]) == 0
    summary = json.loads((out / "reference_run.json").read_text())
    assert {f"generate_train_{task}" for task in SUITES[TWO_TASKS]} <= set(summary["stage_seconds"])
    episodes = read_dataset_provenance(out / "dataset" / "train")[1]["episodes"]
    assert sorted((e["task"], e["variation_id"]) for e in episodes) == sorted(
        (task, get_task(task).split_variations("train")[0].id) for task in SUITES[TWO_TASKS])
    assert [set(point["per_task"]) for point in summary["learning_curve"]] == [set(SUITES[TWO_TASKS])] * 2
    train = summary["results"]["splits"]["train"]
    assert set(train["per_task"]) == set(SUITES[TWO_TASKS]) and "task_average" in train
    assert "success per task" in capsys.readouterr().out


def test_a_multi_task_card_counts_each_tasks_episodes_and_pictures_every_task(two_task_dataset):
    import cv2

    card = (two_task_dataset / "README.md").read_text()
    for task in SUITES[TWO_TASKS]:
        assert f"| `{task}` | 1 |" in card
    sheet = cv2.imread(str(two_task_dataset / "contact_sheet.png"))
    assert sheet.shape[0] == 24 + 2 * 128  # a header, then a row per task (one split: one row before)


def test_lerobot_evals_env_takes_a_tasks_episodes_from_a_multi_task_dataset(two_task_dataset):
    from demo_factory.evaluate.lerobot_env import DemoFactoryEnv

    env = DemoFactoryEnv(task="open_drawer", split="train", dataset=str(two_task_dataset))
    episodes = env.gym_kwargs["episodes"]
    trained = {e["variation_id"] for e in read_dataset_provenance(two_task_dataset / "train")[1]["episodes"]
               if e["task"] == "open_drawer"}
    assert len(episodes) == 100 and {e.task for e in episodes} == {"open_drawer"}
    assert {e.variation_id for e in episodes} == trained
    with pytest.raises(ValueError, match="holds no tower episode in its 'train' split"):
        DemoFactoryEnv(task="tower", split="train", dataset=str(two_task_dataset))
    with pytest.raises(ValueError, match="has no converted 'test' split"):
        DemoFactoryEnv(task="open_drawer", split="test", dataset=str(two_task_dataset))
    assert "episodes" not in DemoFactoryEnv(task="open_drawer").gym_kwargs
