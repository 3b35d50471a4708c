"""MCAP recordings → LeRobot datasets: splits, features, instructions, robustness (training: test_dense, test_evaluate, test_reference_run)."""

import json
from pathlib import Path

import numpy as np
import pytest

from demo_factory.convert.converter import read_dataset_provenance
from demo_factory.convert import DATASET_SPLITS, world_points
from demo_factory.cli import main
from demo_factory.convert.usage import train_args
from demo_factory.instructions import colour_words, corrupt_instruction
from demo_factory.record import read_episode
from demo_factory.tasks import get_task
from demo_factory.tasks.variations import Variation
from demo_factory.convert.writer import PARAPHRASES_FILE, RELABELS_FILE

CAMERAS = ["left_shoulder", "right_shoulder", "wrist"]
SIZE = (32, 32)


def _variations(task, split, n):
    return get_task(task).split_variations(split)[:n]


@pytest.fixture(scope="module")
def recordings(tmp_path_factory, write_recording):
    """push_buttons: 4 train-variation episodes, 3 test-variation ones (two of one variation)."""
    folder = tmp_path_factory.mktemp("raw") / "push_buttons"
    folder.mkdir()
    train = _variations("push_buttons", "train", 4)
    test = _variations("push_buttons", "test", 2)
    for i, v in enumerate(train):
        write_recording(folder, "push_buttons", "train", v, 100 + i, keyframes=3 + i % 3)
    for i, v in enumerate([test[0], test[0], test[1]]):
        write_recording(folder, "push_buttons", "test", v, 200 + i, keyframes=4)
    return folder


@pytest.fixture(scope="module")
def human_file(tmp_path_factory):
    """Three rows for the first test variation (it has 2 episodes), one for the second (1 episode)."""
    a, b = _variations("push_buttons", "test", 2)
    rows = [{"task": "push_buttons", "variation_id": a.id, "instruction": f"hit them, take {i}", "author": "t"}
            for i in range(3)] + [{"task": "push_buttons", "colours": list(b.words), "instruction": "tap the grey-ish ones"}]
    path = tmp_path_factory.mktemp("human") / "human.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


@pytest.fixture(scope="module")
def converted(recordings, human_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("lerobot") / "push_buttons"
    code = main(["convert", "--in", str(recordings), "--out", str(out), "--repo-id", "me/push_buttons",
                 "--val-ratio", "0.25", "--human-instructions", str(human_file), "--no-progress"])
    assert code == 0
    return out


def _load(out: Path, split: str):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(f"me/push_buttons_{split}", root=out / split)


def _episodes(dataset):
    """Dataset frames grouped by episode, with the recording each came from."""
    provenance = read_dataset_provenance(dataset.root)[1]["episodes"]
    items = [dataset[i] for i in range(len(dataset))]
    return [([it for it in items if it["episode_index"].item() == p["episode_index"]], p) for p in provenance]


def test_layout_every_split_loads_offline(converted):
    assert sorted(p.name for p in converted.iterdir()) == sorted([*DATASET_SPLITS, "README.md", "contact_sheet.png"])
    for split in DATASET_SPLITS:
        dataset = _load(converted, split)
        assert dataset.num_episodes > 0 and dataset.fps == 10
        provenance = read_dataset_provenance(dataset.root)[1]
        assert provenance["cameras"] == CAMERAS and provenance["split"] == split
        for camera in CAMERAS:  # LeRobot's native depth
            assert dataset.meta.features[f"observation.depth.{camera}"]["info"] == {"is_depth_map": True, "depth_unit": "mm"}
        assert dataset.meta.depth_keys == [f"observation.depth.{camera}" for camera in CAMERAS]
        assert not (converted / split / "images").exists()
    assert not list(converted.parent.glob(".push_buttons.*"))  # no staging folder left


def test_frames_and_actions_follow_the_recorded_keyframes(converted, recordings):
    for split in ("train", "val", "test_unseen_synthetic"):
        for frames, source in _episodes(_load(converted, split)):
            episode = read_episode(recordings / source["recording"])
            assert len(frames) == len(episode.keyframes)
            for k, item in enumerate(frames):
                target = episode.keyframes[min(k + 1, len(episode.keyframes) - 1)]
                expected = np.append(target.target_pose, target.gripper_open)
                assert np.allclose(item["action"].numpy(), expected, atol=1e-6)
                robot = episode.keyframe_frames()[k].robot
                state = np.concatenate([robot.gripper_pose, [robot.gripper_open], robot.joint_positions])
                assert np.allclose(item["observation.state"].numpy(), state, atol=1e-6)
                assert item["keyframe_index"].item() == k and item["variation_id"].item() == episode.info.variation_id
                rgb = np.rint(item["observation.images.wrist"].numpy() * 255).astype(np.uint8).transpose(1, 2, 0)
                assert np.array_equal(rgb, episode.keyframe_frames()[k].cameras["wrist"].rgb)


def test_world_points_from_dataset_equal_those_from_the_recording(converted, recordings):
    frames, source = _episodes(_load(converted, "train"))[0]
    episode = read_episode(recordings / source["recording"])
    for k, item in enumerate(frames):
        for camera in CAMERAS:
            recorded = episode.keyframe_frames()[k].cameras[camera]
            fx, fy, cx, cy = recorded.intrinsics
            v, u = np.mgrid[0:SIZE[0], 0:SIZE[1]]
            z = np.where(recorded.depth > 0, recorded.depth, np.nan)
            homogeneous = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z, np.ones_like(z)], axis=-1)
            expected = (homogeneous @ recorded.extrinsics.T)[..., :3]
            depth_mm = item[f"observation.depth.{camera}"].numpy()
            assert depth_mm.shape == (1, *SIZE) and depth_mm.dtype == np.float32
            # every pixel: the recording's millimetres (the simulator's depth rounded to whole mm), exactly
            assert np.array_equal(depth_mm[0], np.rint(recorded.depth.astype(np.float64) * 1000))
            depth = depth_mm[0] / 1000.0
            rebuilt = world_points(depth, item[f"observation.calibration.{camera}"].numpy())
            assert np.array_equal(np.isnan(rebuilt), np.isnan(expected))
            assert np.nanmax(np.abs(rebuilt - expected)) < 1e-5


def test_splits_keep_seen_and_unseen_variations_apart(converted):
    test_ids = {v.id for v in get_task("push_buttons").split_variations("test")}
    seen = {split: read_dataset_provenance(_load(converted, split).root)[1]["episodes"] for split in DATASET_SPLITS}
    for split in ("train", "val"):
        assert seen[split] and all(e["variation_id"] not in test_ids for e in seen[split])
    for split in ("test_unseen_synthetic", "test_unseen_corrupted", "test_unseen_human"):
        assert all(e["variation_id"] in test_ids for e in seen[split])
    assert len(seen["val"]) == 1 and len(seen["train"]) == 3
    assert not {e["recording"] for e in seen["val"]} & {e["recording"] for e in seen["train"]}


def test_corrupted_split_has_no_seen_colour_word(converted):
    synthetic = _load(converted, "test_unseen_synthetic")
    corrupted = _load(converted, "test_unseen_corrupted")
    tasks = list(corrupted.meta.tasks.index)
    assert tasks and all(colour_words(t) == [] for t in tasks)
    assert sorted(tasks) == sorted({corrupt_instruction(t) for t in synthetic.meta.tasks.index})
    assert all(corrupted[i]["task"] in tasks for i in range(len(corrupted)))


def test_synthetic_splits_list_every_phrasing_of_each_task(converted):
    """meta/task_paraphrases.json: each task string -> its variation's phrasings from the task's grammar (the
    templates first, itself among them), for the policy to draw from; the other test splits have none."""
    task = get_task("push_buttons")
    for split in ("train", "val", "test_unseen_synthetic"):
        dataset = _load(converted, split)
        paraphrases = json.loads((dataset.root / PARAPHRASES_FILE).read_text())
        assert sorted(paraphrases) == sorted(dataset.meta.tasks.index)
        for episode in read_dataset_provenance(dataset.root)[1]["episodes"]:
            variation = Variation(episode["variation_id"], tuple(episode["colours"]))
            alternatives = paraphrases[episode["instruction"]]
            assert alternatives == task.paraphrases(variation) and len(set(alternatives)) >= 30
            assert alternatives[:4] == task.synthetic_instructions(variation) and episode["instruction"] in alternatives
    for split in ("test_unseen_corrupted", "test_unseen_paraphrased", "test_unseen_human"):
        assert not (converted / split / PARAPHRASES_FILE).exists()


def test_paraphrased_split_instructs_test_episodes_with_phrasings_no_training_source_holds(converted):
    task = get_task("push_buttons")
    training = {text for split in ("train", "val") for texts in
                json.loads((converted / split / PARAPHRASES_FILE).read_text()).values() for text in texts}
    synthetic = read_dataset_provenance(converted / "test_unseen_synthetic")[1]["episodes"]
    paraphrased = read_dataset_provenance(converted / "test_unseen_paraphrased")[1]["episodes"]
    assert [(e["recording"], e["variation_id"]) for e in paraphrased] == [(e["recording"], e["variation_id"])
                                                                            for e in synthetic]
    for episode in paraphrased:
        variation = Variation(episode["variation_id"], tuple(episode["colours"]))
        assert episode["instruction"] in task.held_out_phrasings(variation) and episode["instruction"] not in training
        assert episode["instruction"] == task.held_out_instruction(variation, episode["episode_seed"])
    assert "`test_unseen_paraphrased` instructs each test episode" in (converted / "README.md").read_text()


def test_train_splits_list_each_episode_s_relabels_none_of_a_test_variation(tmp_path, write_recording):
    """meta/instruction_relabels.json: episode index -> [[n, synthetic instructions], ...] from the recorded
    scene (`Task.instruction_relabels`), without the relabels that are test variations; none for test splits."""
    task = get_task("push_buttons")
    test = task.split_variations("test")
    # A train variation whose scene holds a test variation's buttons: (a, b) with a test (a, c) among its relabels.
    variation, leak = next((v, t) for t in test if len(t.words) == 2 for v in task.split_variations("train")
                           if v.words[0] == t.words[0] and t.words[1] not in v.words and len(v.words) == 2)
    scene = {"buttons": {c: [0.5, 0.1 * i] for i, c in enumerate((*variation.words, leak.words[1]))}}
    folder = tmp_path / "raw"
    folder.mkdir()
    write_recording(folder, "push_buttons", "train", variation, 5, keyframes=7, scene=scene)
    write_recording(folder, "push_buttons", "test", test[0], 6, keyframes=4, scene={"buttons": {}})
    out = tmp_path / "lerobot"
    assert main(["convert", "--in", str(folder), "--out", str(out), "--repo-id", "me/pb", "--no-progress"]) == 0
    relabels = json.loads((out / "train" / RELABELS_FILE).read_text())
    expected = [(words, n) for v, n in task.instruction_relabels(variation, scene) if v != leak
                for words in [task.synthetic_instructions(v)]]
    assert leak in {v for v, _ in task.instruction_relabels(variation, scene)} and len(expected) == 3
    assert sorted(relabels) == ["0"] and sorted((r[1], r[0]) for r in relabels["0"]) == sorted(expected)
    assert not (out / "test_unseen_synthetic" / RELABELS_FILE).exists()


def test_human_split_uses_every_sentence_of_the_file(converted, human_file):
    human = _load(converted, "test_unseen_human")
    sentences = [json.loads(line)["instruction"] for line in human_file.read_text().splitlines()]
    used = [e["instruction"] for e in read_dataset_provenance(human.root)[1]["episodes"]]
    # variation a: 2 episodes, 3 rows → 3 episodes; variation b: 1 episode, 1 row
    assert sorted(used) == sorted(sentences)
    assert {human[i]["task"] for i in range(len(human))} == set(sentences)


def test_card_lists_splits_features_and_how_to_train(converted):
    card = (converted / "README.md").read_text()
    words = " ".join(card.split())  # the card's prose is wrapped: phrases are looked for across its lines
    assert card.startswith("---\nlicense: apache-2.0\ntask_categories:\n- robotics\n")
    assert "- LeRobot" in card and "path: test_unseen_human/data/*/*.parquet" in card
    assert "| `test_unseen_human` | `me/push_buttons_test_unseen_human` | 4 |" in card
    assert "`observation.calibration.wrist`" in card
    assert "sentences from `human.jsonl`, a file supplied at conversion (`--human-instructions`): 4 sentences" in words
    assert "lerobot-train --policy.type=hiveformer" in card  # keyframes; ACT needs a dense export (test_dense)
    # Unseen splits are for new instructions: the suggested encoder is the pretrained one that carries to them.
    assert "--policy.text_encoder=minilm_causal" in card and "MiniLM sentence encoder's left-context token features" in words
    assert "guhur2022hiveformer" in card and "james2020rlbench" in card and "cadene2024lerobot" in card
    assert "planned transition: mean 2.00, max 3" in words


def test_truncated_recording_stops_the_conversion_naming_the_file(recordings, tmp_path, capsys):
    folder = tmp_path / "raw"
    folder.mkdir()
    for path in sorted(recordings.glob("*.mcap"))[:2]:
        (folder / path.name).write_bytes(path.read_bytes())
    damaged = folder / "zz_truncated.mcap"
    data = next(recordings.glob("*.mcap")).read_bytes()
    damaged.write_bytes(data[: len(data) // 2])
    out = tmp_path / "out"
    assert main(["convert", "--in", str(folder), "--out", str(out), "--no-progress"]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "zz_truncated.mcap: corrupt or truncated" in error and "--skip-invalid" in error
    assert not out.exists() and not list(tmp_path.glob(".out*"))
    assert main(["convert", "--in", str(folder), "--out", str(out), "--no-progress", "--skip-invalid"]) == 0
    assert "zz_truncated.mcap" in capsys.readouterr().out
    assert "zz_truncated.mcap" in (out / "README.md").read_text()


def test_existing_output_and_bad_options_are_refused(converted, recordings, tmp_path, capsys):
    before = sorted(p.name for p in converted.iterdir())
    assert main(["convert", "--in", str(recordings), "--out", str(converted), "--no-progress"]) == 2
    assert "already exists; pass --overwrite" in capsys.readouterr().err
    assert sorted(p.name for p in converted.iterdir()) == before
    for args, message in [
        (["--val-ratio", "1.5"], "--val-ratio 1.5 is out of range"),
        (["--repo-id", "no-slash"], "--repo-id 'no-slash' is not a Hub repo id"),
        (["--task", "juggle"], "unknown task 'juggle'; accepted: push_buttons, tower"),
        (["--granularity", "dense"], "no dense frames"),
    ]:
        code = main(["convert", "--in", str(recordings), "--out", str(tmp_path / "x"), "--no-progress", *args])
        error = capsys.readouterr().err
        assert code == 2 and message in error and len(error.strip().splitlines()) == 1, error
        assert not (tmp_path / "x").exists()


def test_overwrite_replaces_and_dense_granularity_uses_dense_frames(tmp_path, write_recording):
    raw = tmp_path / "raw"
    raw.mkdir()
    (train,), (test,) = _variations("tower", "train", 1), _variations("tower", "test", 1)
    write_recording(raw, "tower", "train", train, 1, keyframes=3, dense_fps=2.0, cameras=["front", "wrist"])
    write_recording(raw, "tower", "test", test, 2, keyframes=4, dense_fps=2.0, cameras=["front", "wrist"])
    out = tmp_path / "tower"
    out.mkdir()
    (out / "stale.txt").write_text("old")
    args = ["convert", "--in", str(raw), "--out", str(out), "--repo-id", "me/tower", "--granularity", "dense",
            "--overwrite", "--no-progress"]
    assert main(args) == 0
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    assert not (out / "stale.txt").exists() and not (out / "val").exists()  # one train episode: no val
    train_set = LeRobotDataset("me/tower_train", root=out / "train")
    assert train_set.fps == 2 and len(train_set) == 2  # the dense frames, not the 3 keyframes
    assert [train_set[i]["keyframe_index"].item() for i in range(2)] == [0, 1]
    assert sorted(k for k in train_set.features if k.startswith("observation.images")) == [
        "observation.images.front", "observation.images.wrist"]
    human = LeRobotDataset("me/tower_test_unseen_human", root=out / "test_unseen_human")  # the paper's sentences
    assert human.num_episodes == 1  # the first test variation (100) has one row in annotations.json


@pytest.mark.parametrize("unseen, encoder", [(True, "minilm_causal"), (False, "one_hot")])
def test_suggested_hiveformer_encoder_follows_the_splits(unseen, encoder):
    args = train_args("keyframe", "me/pb_train", Path("pb/train"), CAMERAS, SIZE, 10, 4, unseen_splits=unseen)
    assert f"--policy.text_encoder={encoder}" in args
