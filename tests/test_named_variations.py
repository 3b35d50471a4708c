"""Episodes for exactly the variations a user names, converted with their human instructions."""

import json

import pytest

from demo_factory.cli import main
from demo_factory.instructions import load_human_instructions
from demo_factory.tasks import get_task


def unseen_beyond_test_set(task_name: str, count: int, length: int):
    """Variations that are neither train nor default-test variations (named by users)."""
    task = get_task(task_name)
    taken = set(task.split_variations("train")) | set(task.split_variations("test"))
    return [v for v in task.variations if len(v.words) == length and v not in taken][:count]


@pytest.mark.slow
def test_instruction_file_yields_episodes_for_exactly_its_variations_and_every_row(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    named = unseen_beyond_test_set("push_buttons", 4, 2) + get_task("push_buttons").split_variations("test")[:1]
    rows = [{"task": "push_buttons", "colours": [c.title() for c in v.words],
             "instruction": f"please tap {' then '.join(v.words)}"} for v in named]
    rows.append({"task": "push_buttons", "variation_id": named[0].id, "instruction": "hit those two, in order"})
    instructions = tmp_path / "mine.jsonl"
    instructions.write_text("".join(json.dumps(r) + "\n" for r in rows))

    raw, out = tmp_path / "raw", tmp_path / "lerobot"
    assert main(["generate", "--task", "push_buttons", "--variations-from", str(instructions),
                 "--episodes-per-variation", "1", "--image-size", "32", "--workers", "2", "--out", str(raw)]) == 0
    recorded = sorted(int(p.name.split("_var")[1][:4]) for p in raw.glob("*.mcap"))
    assert recorded == sorted(v.id for v in named)  # exactly those 5, one episode each

    assert main(["convert", "--in", str(raw), "--out", str(out), "--repo-id", "me/named",
                 "--human-instructions", str(instructions), "--no-progress"]) == 0
    human = LeRobotDataset("me/named_test_unseen_human", root=out / "test_unseen_human")
    assert set(human.meta.tasks.index) == {r.instruction for r in load_human_instructions(instructions)}
    assert human.meta.total_episodes == len(rows)  # every row is used (its variation's episode repeats)
    for split in ("test_unseen_synthetic", "test_unseen_corrupted"):
        info = json.loads((out / split / "meta" / "demo_factory.json").read_text())
        assert sorted(e["variation_id"] for e in info["episodes"]) == sorted(v.id for v in named)
    card = " ".join((out / "README.md").read_text().split())  # its prose is wrapped: phrases span lines
    assert "Named test variations" in card and all(str(v.id) in card for v in named[:4])


@pytest.mark.slow
def test_a_named_tower_variation_generates_and_converts(tmp_path):
    variation = unseen_beyond_test_set("tower", 1, 3)[0]
    raw, out = tmp_path / "raw", tmp_path / "lerobot"
    assert main(["generate", "--task", "tower", "--variation", variation.name, "--episodes", "1",
                 "--image-size", "32", "--out", str(raw)]) == 0
    assert main(["convert", "--in", str(raw), "--out", str(out), "--repo-id", "me/tower_named", "--no-progress"]) == 0
    info = json.loads((out / "test_unseen_synthetic" / "meta" / "demo_factory.json").read_text())
    assert [e["variation_id"] for e in info["episodes"]] == [variation.id]
    assert not (out / "train").exists()  # no train-variation episodes: the split is skipped, not written empty
