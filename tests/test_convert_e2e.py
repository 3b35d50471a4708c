"""End to end: `demo-factory generate` real episodes of both tasks, then `demo-factory convert` them."""

import pytest

from demo_factory.convert.converter import read_dataset_provenance
from demo_factory.cli import main
from demo_factory.convert import DATASET_SPLITS
from demo_factory.instructions import colour_words, load_human_instructions, shipped_human_instructions
from demo_factory.record import iter_episode_paths, read_episode


@pytest.mark.slow
@pytest.mark.parametrize("task, train, test", [("push_buttons", 3, 2), ("tower", 2, 2)])
def test_generated_episodes_convert_to_loadable_splits(task, train, test, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    raw = tmp_path / "raw" / task
    for split, episodes in (("train", train), ("test", test)):
        assert main(["generate", "--task", task, "--split", split, "--episodes", str(episodes), "--seed", "3",
                     "--image-size", "32", "--workers", "2", "--out", str(raw / split)]) == 0
    recordings = {p.name: read_episode(p) for split in ("train", "test") for p in iter_episode_paths(raw / split)}
    out = tmp_path / "lerobot" / task
    assert main(["convert", "--in", str(raw), "--out", str(out), "--repo-id", f"me/{task}", "--val-ratio", "0.34",
                 "--no-progress"]) == 0
    human_rows = {r.instruction for r in load_human_instructions(shipped_human_instructions(task))}
    for split in DATASET_SPLITS:
        dataset = LeRobotDataset(f"me/{task}_{split}", root=out / split)
        episodes = read_dataset_provenance(dataset.root)[1]["episodes"]
        assert dataset.num_frames == sum(len(recordings[e["recording"]].keyframes) for e in episodes)
        assert {recordings[e["recording"]].info.split for e in episodes} == {"train" if split in ("train", "val") else "test"}
        if split == "test_unseen_corrupted":
            assert all(colour_words(t) == [] for t in dataset.meta.tasks.index)
        if split == "test_unseen_human":
            assert set(dataset.meta.tasks.index) <= human_rows
        item = dataset[dataset.num_frames - 1]
        assert item["observation.images.wrist"].shape == (3, 32, 32) and item["action"].shape == (8,)
    card = (out / "README.md").read_text()
    assert f"demo-factory generate --task {task} --split train --episodes {train} --seed 3" in card
    assert "expert success rate" in card and (out / "contact_sheet.png").stat().st_size > 0
