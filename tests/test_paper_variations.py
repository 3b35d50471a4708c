"""The HiveFormer paper's variation ids and its human-written instructions (the authors' annotations.json)."""

import json

import pytest

from demo_factory.cli import main
from demo_factory.convert import DATASET_FORMAT_VERSION, ConvertError, check_dataset_provenance
from demo_factory.instructions import (
    HumanInstructionError,
    hiveformer_annotations,
    load_human_instructions,
    shipped_human_instructions,
)
from demo_factory.instructions.human import sentence_rows, variations_in_file
from demo_factory.record import FORMAT_VERSION, EpisodeInfo, EpisodeWriter, RecordingError, read_episode
from demo_factory.tasks import get_task

# Variation id → colour sequence in the authors' RLBench fork. push_buttons 0 and 1 are the check
# values the annotations' README states; the others follow from the fork's rule, and tower's
# 100-199 are confirmed by the colours annotations.json gives for every one of them.
CHECK_VALUES = {
    "push_buttons": {
        0: ("green", "rose", "black"),
        1: ("violet", "black", "yellow"),
        2: ("blue", "olive", "orange"),
        99: ("violet", "navy", "orange"),
        100: ("olive", "blue"),
        110: ("magenta", "purple"),  # annotated "Press the pink button and then the purple one."
        199: ("violet", "yellow", "blue"),
        5219: ("green", "olive", "violet"),
    },
    "tower": {
        0: ("black", "yellow"),
        1: ("white", "gray", "red"),
        100: ("lime", "rose"),
        199: ("red", "green", "lime"),
        200: ("red",),  # the first sequence the fork does not use
    },
}


def _raw_rows():
    return json.loads(hiveformer_annotations().read_text(encoding="utf-8"))


@pytest.mark.parametrize("task_name", ["push_buttons", "tower"])
def test_variation_ids_are_the_forks(task_name):
    task = get_task(task_name)
    for vid, colours in CHECK_VALUES[task_name].items():
        assert task.variation(vid).words == colours, vid
    assert [v.id for v in task.split_variations("train")] == list(range(100))
    assert [v.id for v in task.split_variations("test")] == list(range(100, 200))
    assert len({v.words for v in task.variations}) == len(task.variations)  # each sequence once
    assert "HiveFormer paper ids" in task.variation_scheme


def test_every_sequence_has_an_id():
    assert len(get_task("push_buttons").variations) == 18 * 17 * 16 + 18 * 17 + 18 == 5220
    assert len(get_task("tower").variations) == 20 * 19 * 18 + 20 * 19 + 20 == 7240


def test_tasks_command_names_the_numbering(capsys):
    assert main(["tasks"]) == 0
    out = capsys.readouterr().out
    assert "HiveFormer paper ids (the authors' RLBench fork, push_buttons3): train 0-99, test 100-199" in out
    assert "tower3" in out


def test_all_162_rows_map_to_test_variations_with_their_exact_sentences():
    path = shipped_human_instructions("push_buttons")
    assert path == shipped_human_instructions("tower") == hiveformer_annotations()
    assert (path.parent / "LICENSE").read_text().startswith("MIT License")
    raw = _raw_rows()
    rows = load_human_instructions(path)
    assert len(rows) == len(raw) == 162
    for row, record in zip(rows, raw):
        fields = record["fields"]
        assert row.instruction == fields["instruction"]  # exactly: typos, line breaks, trailing spaces
        assert row.variation_id == fields["variation"] and row.record_id == record["id"]
        task = get_task(row.task)
        assert task.variation(row.variation_id) in task.split_variations("test")
        assert row.words == task.variation(row.variation_id).words
        if "colors" in fields:
            assert list(row.words) == fields["colors"]
    by_task = {t: [r for r in rows if r.task == t] for t in ("push_buttons", "tower")}
    assert len(by_task["push_buttons"]) == 62 and len({r.variation_id for r in by_task["push_buttons"]}) == 51
    assert len(by_task["tower"]) == 100 and len({r.variation_id for r in by_task["tower"]}) == 100
    assert any(r.instruction.endswith(" ") for r in rows) and any("\n" in r.instruction for r in rows)
    usable, blank = sentence_rows(rows)
    assert len(usable) == 161 and [(r.task, r.variation_id, r.instruction) for r in blank] == [("tower", 136, "")]


def test_variations_from_the_annotations_file_as_it_is():
    path = hiveformer_annotations()
    assert [v.id for v in variations_in_file(path, get_task("push_buttons"))] == list(
        dict.fromkeys(r["fields"]["variation"] for r in _raw_rows() if r["fields"]["task"] == "push_buttons3"))
    assert len(variations_in_file(path, get_task("tower"))) == 100


def _annotations_with(tmp_path, **changes):
    """A copy of annotations.json whose first push_buttons3 row has ``changes`` in its fields."""
    records = _raw_rows()
    first = next(r for r in records if r["fields"]["task"] == "push_buttons3")
    first["fields"].update(changes)
    path = tmp_path / "annotations.json"
    path.write_text(json.dumps(records))
    return path, records.index(first) + 1, first["id"]


def test_a_row_for_a_train_variation_is_refused_naming_the_leak(tmp_path, capsys):
    path, number, record_id = _annotations_with(tmp_path, variation=5)
    with pytest.raises(HumanInstructionError) as error:
        load_human_instructions(path)
    message = str(error.value)
    assert f"row {number} ({record_id}): variation 5 (" in message
    assert "is a train variation of push_buttons" in message and "would leak train data into a test split" in message

    out = tmp_path / "raw"
    assert main(["generate", "--task", "push_buttons", "--variations-from", str(path), "--out", str(out)]) == 2
    error_line = capsys.readouterr().err.strip()
    assert len(error_line.splitlines()) == 1 and "would leak train data" in error_line and not out.exists()


@pytest.mark.parametrize("changes, message", [
    ({"task": "stack_blocks"}, "unknown task 'stack_blocks'; accepted: push_buttons3, tower3"),
    ({"variation": 5220}, "variation 5220 does not exist; push_buttons3 has ids 0 to 5219"),
    ({"colors": ["red"]}, "colors ['red'] disagree with push_buttons3 variation"),
    ({"instruction": None}, "instruction is missing; expected a string"),
])
def test_bad_annotation_rows_name_the_row(tmp_path, changes, message):
    path, number, _ = _annotations_with(tmp_path, **changes)
    with pytest.raises(HumanInstructionError, match=f"row {number} .*" + message.replace("[", r"\[").replace("]", r"\]")):
        load_human_instructions(path)


def test_recordings_of_the_old_numbering_are_refused(tmp_path):
    info = EpisodeInfo(format_version=1, task="push_buttons", split="train", variation_id=0, variation=["navy"],
                       episode_seed=1, instruction="push the navy button", cameras=["wrist"], image_size=(32, 32),
                       dense_fps=0.0)
    path = EpisodeWriter(tmp_path / "old.mcap", info).close(0, True, [], {})
    with pytest.raises(RecordingError, match="format version 1 numbers variations the old way .*regenerate"):
        read_episode(path)
    assert FORMAT_VERSION == 6


def test_datasets_of_the_old_numbering_are_refused():
    with pytest.raises(ConvertError, match="dataset format version 1 is older"):
        check_dataset_provenance({"task": "push_buttons", "episodes": []}, "old/test_unseen_human")
    with pytest.raises(ConvertError, match="not a demo-factory dataset"):
        check_dataset_provenance(None, "x")
    current = {"format_version": DATASET_FORMAT_VERSION, "task": "tower", "episodes": []}
    assert check_dataset_provenance(current, "new") is current


@pytest.mark.slow
def test_generate_then_convert_gives_exactly_the_papers_sentences(tmp_path):
    """A few of the paper's variations (one with two sentences), generated from an annotations file as
    the authors publish it, converted with the shipped annotations (the default)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    records = _raw_rows()
    chosen = {113, 191}  # push_buttons3 variations with two annotated sentences each
    subset = [r for r in records if r["fields"]["task"] == "push_buttons3" and r["fields"]["variation"] in chosen]
    assert len(subset) == 4
    path = tmp_path / "annotations.json"
    path.write_text(json.dumps(subset, indent=2))
    raw, out = tmp_path / "raw", tmp_path / "lerobot"
    assert main(["generate", "--task", "push_buttons", "--variations-from", str(path), "--episodes-per-variation", "1",
                 "--image-size", "32", "--workers", "2", "--out", str(raw)]) == 0
    assert main(["convert", "--in", str(raw), "--out", str(out), "--repo-id", "me/paper", "--no-progress"]) == 0
    human = LeRobotDataset("me/paper_test_unseen_human", root=out / "test_unseen_human")
    assert sorted(human.meta.tasks.index) == sorted(r["fields"]["instruction"] for r in subset)
    info = json.loads((out / "test_unseen_human" / "meta" / "demo_factory.json").read_text())
    assert info["format_version"] == DATASET_FORMAT_VERSION
    assert sorted((e["variation_id"], e["instruction"], e["annotation_id"]) for e in info["episodes"]) == sorted(
        (r["fields"]["variation"], r["fields"]["instruction"], r["id"]) for r in subset)
    card = " ".join((out / "README.md").read_text().split())  # its prose is wrapped: phrases span lines
    assert "HiveFormer paper's human-written instructions" in card and "MIT licence" in card
    assert "62 sentences for push_buttons covering 51 test variations" in card
    assert "train** (seen) = variations 0-99" in card


def old_numbering_dataset(root):
    """A converted split folder as demo-factory wrote it before the paper's numbering (format 1)."""
    meta = root / "train" / "meta"
    meta.mkdir(parents=True)
    provenance = {"task": "push_buttons", "episodes": [{"variation_id": 0, "instruction": "press navy"}]}
    meta.joinpath("info.json").write_text(json.dumps({"codebase_version": "v3.0", "demo_factory": provenance}))
    return root


def test_eval_and_publish_refuse_datasets_of_the_old_numbering(tmp_path, capsys):
    from demo_factory.cli import main
    from demo_factory.publish.plan import PublishError, find_splits

    dataset = old_numbering_dataset(tmp_path / "old")
    assert main(["eval", "--expert", "--dataset", str(dataset), "--out", str(tmp_path / "eval")]) == 2
    assert "dataset format version 1 is older" in capsys.readouterr().err
    assert not (tmp_path / "eval").exists()
    with pytest.raises(PublishError, match="dataset format version 1 is older"):
        find_splits(dataset)


def test_variations_past_the_papers_ids_may_train_but_test_ones_may_not():
    from demo_factory.tasks import get_task

    task = get_task("push_buttons")
    extra = task.parse_variation("205")
    assert extra.words == ("maroon",) and extra not in task.split_variations("test")
    task.check_split_membership(extra, "train")  # an extra training variation: accepted
    task.check_split_membership(extra, "test")  # or a further unseen one
    with pytest.raises(ValueError, match="leak"):
        task.check_split_membership(task.parse_variation("100"), "train")
