"""Dataset cards: the converter's card, its per-split Hub version and the committed standard cards."""

from __future__ import annotations

from pathlib import Path

import pytest
from huggingface_hub import DatasetCard, DatasetCardData

from demo_factory.convert.card import hub_card
from demo_factory.convert.wrap import join_continued, wrap_card

CARDS = Path(__file__).resolve().parents[1] / "dataset_cards"
LONGEST_LINE = 200  # cards are read in terminals and diffs too
SECTIONS = ["## Task and variations", "## Splits", "## Features", "## Cameras", "## Generation statistics",
            "## Load, train and evaluate", "## Regenerate", "## Licence", "## Limitations", "## Citation"]


def check_card(text: str) -> DatasetCard:
    """The fields and sections every card must have; returns the parsed card."""
    card = DatasetCard(text)
    data = card.data
    assert isinstance(data, DatasetCardData)
    assert data.license == "apache-2.0"
    assert data.task_categories == ["robotics"]
    assert "LeRobot" in data.tags
    assert data.configs and data.configs[0]["config_name"] == "default"
    assert data.pretty_name and data.size_categories
    for heading in SECTIONS:
        assert f"\n{heading}\n" in card.text, heading
    for word in ("Simulated", "Primitive shapes", "guhur2022hiveformer", "james2020rlbench", "cadene2024lerobot",
                 "lerobot-train", "LeRobotDataset", "demo-factory eval", "demo-factory generate", "demo-factory convert"):
        assert word in card.text, word
    assert max(len(line) for line in text.splitlines()) <= LONGEST_LINE
    return card


def test_long_lines_are_wrapped_saying_the_same():
    prose = "- **corrupted**: " + ", ".join(f"colour{i} → synonym{i}" for i in range(12)) + "."
    command = "lerobot-train " + " ".join(f"--option{i}=value{i}" for i in range(12)) + " --out 'a b'"
    row = "| " + " | ".join(f"cell {i}" for i in range(20)) + " |"
    front = "---\npretty_name: " + "x " * 40 + "\n---"
    text = wrap_card(f"{front}\n\n{prose}\n{row}\n\n```bash\n{command}\n```\n", width=60)
    lines = text.splitlines()
    assert text.startswith(front + "\n") and row in lines  # front matter and table rows as they were
    item = lines[lines.index("") + 1:lines.index(row)]
    assert len(item) > 1 and all(len(line) <= 60 and line.startswith("  ") for line in item[1:])
    assert " ".join(" ".join(item).split()) == prose
    assert not any("→" in (line.split()[0], line.split()[-1]) for line in item)  # never cut beside an arrow
    commands = lines[lines.index("```bash") + 1:-1]
    assert len(commands) > 1 and all(len(line) <= 60 for line in commands) and join_continued(commands) == [command]


def test_converter_card_parses_with_the_hub_card_classes(converted_push_buttons):
    card = check_card((converted_push_buttons / "README.md").read_text())
    splits = sorted(p.name for p in converted_push_buttons.iterdir() if (p / "meta").is_dir())
    paths = {f["split"]: f["path"] for f in card.data.configs[0]["data_files"]}
    assert paths == {s: f"{s}/data/*/*.parquet" for s in splits}
    assert all(f"`me/push_buttons_{s}`" in card.text for s in splits)


def test_hub_card_is_the_card_of_one_split_repo_linking_the_others(converted_push_buttons):
    splits = ["train", "val", "test_unseen_synthetic"]
    text = hub_card((converted_push_buttons / "README.md").read_text(), "lab/pb", "val", splits,
                    ["left_shoulder", "right_shoulder", "wrist"], (32, 32), "demo-factory publish --dataset d --repo-id lab/pb")
    card = check_card(text)
    assert card.data.configs == [{"config_name": "default", "data_files": [{"split": "val", "path": "data/*/*.parquet"}]}]
    assert card.text.startswith("\n# lab/pb_val:")
    assert "me/push_buttons" not in card.text
    assert "[`train`](https://huggingface.co/datasets/lab/pb_train)" in card.text
    assert "[`test_unseen_synthetic`](https://huggingface.co/datasets/lab/pb_test_unseen_synthetic)" in card.text
    assert 'D("lab/pb_val")' in card.text and "--dataset.repo_id=lab/pb_val" in card.text and "root=" not in card.text
    regenerate = card.text.split("## Regenerate")[1].split("```")[1]
    assert regenerate.strip().endswith("demo-factory publish --dataset d --repo-id lab/pb")


def test_hub_card_refuses_a_card_without_its_title():
    with pytest.raises(ValueError, match="title"):
        hub_card("---\nlicense: apache-2.0\n---\n\nno title\n", "lab/pb", "train", ["train"], [], (1, 1), "")


@pytest.mark.parametrize("name", ["push_buttons", "tower"])
def test_committed_standard_cards(name):
    folder = CARDS / name
    card = check_card((folder / "README.md").read_text())
    assert f"demo-factory/{name}_train" in card.text
    assert f"--out data/raw/{name}/train" in card.text  # regeneration with the paths a user types
    assert 0 < (folder / "contact_sheet.png").stat().st_size <= 100_000
    assert not [p for p in folder.iterdir() if p.name not in ("README.md", "contact_sheet.png")]  # no data


@pytest.mark.parametrize("suite", ["ten_tasks", "categories"])
def test_committed_suite_cards_cover_the_suite_with_each_tasks_categories(suite):
    import cv2

    from demo_factory.suites import SUITES
    from demo_factory.tasks import get_task

    card = (CARDS / suite / "README.md").read_text()
    check_card(card)
    for name in SUITES[suite]:  # its episodes (4 train-variation ones, 3 test-variation ones: tools/cards.py), its tags
        assert f"| `{name}` | 7 | {', '.join(get_task(name).categories)} |" in card
    sheet = cv2.imread(str(CARDS / suite / "contact_sheet.png"))
    assert sheet.shape[0] == 24 + 128 * len(SUITES[suite])  # a row per task
