"""MCAP recordings: round trip, byte-identical regeneration, damaged and future files."""

import subprocess
import sys

import numpy as np
import pytest

from demo_factory.generate import EpisodeRequest, run_episode
from demo_factory.record import (
    FORMAT_VERSION,
    EpisodeInfo,
    EpisodeWriter,
    Frame,
    Keyframe,
    RecordingError,
    RobotState,
    read_episode,
)
from demo_factory.sim import World


def _info(**overrides):
    values = dict(format_version=FORMAT_VERSION, task="push_buttons", split="train", variation_id=0,
                  variation=["navy"], episode_seed=1, instruction="push the navy button",
                  cameras=["left_shoulder", "right_shoulder", "wrist"], image_size=(128, 128), dense_fps=0.0)
    values.update(overrides)
    return EpisodeInfo(**values)


def _frame(world, index):
    return Frame(world.time_ns, True, False, index, RobotState(world.joint_positions(), world.gripper_pose(), 1.0,
                                                               world.finger_width()), world.render_cameras())


def test_round_trip_equals_what_was_recorded(tmp_path):
    with World() as world:
        world.add_box((0.03, 0.03, 0.03), (0.5, 0.0, 0.03), (0, 0, 1, 1))
        recorded = []
        writer = EpisodeWriter(tmp_path / "episode.mcap", _info())
        for index in range(3):
            world.step(30)
            frame = _frame(world, index)
            recorded.append(frame)
            writer.write_frame(frame)
            writer.write_keyframe(Keyframe(index, world.time_ns, world.gripper_pose(), 1.0, world.gripper_pose(), "start"))
        path = writer.close(world.time_ns, True, [], {"x": "1"})
    episode = read_episode(path)
    assert episode.info.instruction == "push the navy button" and episode.info.success
    assert len(episode.frames) == 3 and [k.index for k in episode.keyframes] == [0, 1, 2]
    for original, read in zip(recorded, episode.frames):
        assert read.time_ns == original.time_ns
        assert np.allclose(read.robot.joint_positions, original.robot.joint_positions, atol=1e-6)
        assert np.allclose(read.robot.gripper_pose, original.robot.gripper_pose, atol=1e-6)
        for name, cam in original.cameras.items():
            back = read.cameras[name]
            assert np.array_equal(back.rgb, cam.rgb)  # PNG: exact
            assert np.abs(back.depth - cam.depth).max() <= 0.0005 + 1e-6  # millimetres
            assert np.array_equal(back.segmentation, cam.segmentation)
            assert np.allclose(back.intrinsics, cam.intrinsics)
            assert np.allclose(back.extrinsics, cam.extrinsics, atol=1e-6)


def test_partial_file_is_hidden_until_closed_and_removed_on_abort(tmp_path):
    writer = EpisodeWriter(tmp_path / "episode.mcap", _info())
    assert not (tmp_path / "episode.mcap").exists() and writer.partial_path.exists()
    writer.abort()
    assert list(tmp_path.iterdir()) == []


def test_truncated_recording_is_reported(recorded_episodes, tmp_path):
    data = open(recorded_episodes["push_buttons"][0], "rb").read()
    damaged = tmp_path / "truncated.mcap"
    damaged.write_bytes(data[: len(data) // 2])
    with pytest.raises(RecordingError, match="truncated.mcap: corrupt or truncated"):
        read_episode(damaged)


def test_foreign_file_is_reported(tmp_path):
    path = tmp_path / "notes.mcap"
    path.write_text("hello")
    with pytest.raises(RecordingError, match="notes.mcap"):
        read_episode(path)


def test_future_format_version_is_refused(tmp_path):
    writer = EpisodeWriter(tmp_path / "future.mcap", _info(format_version=FORMAT_VERSION + 1))
    path = writer.close(0, True, [], {})
    with pytest.raises(RecordingError, match=f"format version {FORMAT_VERSION + 1} is newer"):
        read_episode(path)


def test_recorded_keyframes_and_actions_line_up(recorded_episodes):
    for paths in recorded_episodes.values():
        for path in paths:
            episode = read_episode(path)
            frames = episode.keyframe_frames()
            assert [f.keyframe_index for f in frames] == [k.index for k in episode.keyframes] == list(range(len(frames)))
            for frame, keyframe in zip(frames, episode.keyframes):
                assert frame.time_ns == keyframe.time_ns
                assert np.allclose(frame.robot.gripper_pose[:3], keyframe.reached_pose[:3])
            for keyframe in episode.keyframes[1:]:  # the expert reached what it targeted
                assert np.linalg.norm(keyframe.reached_pose[:3] - keyframe.target_pose[:3]) < 0.01


REGENERATE = """
import sys
from demo_factory.generate import EpisodeRequest, run_episode
run_episode(EpisodeRequest("tower", "test", {variation}, {seed}), sys.argv[1])
"""


@pytest.mark.slow
def test_same_episode_gives_a_byte_identical_file(recorded_episodes, tmp_path):
    original = read_episode(recorded_episodes["tower"][0]).info
    code = REGENERATE.format(variation=original.variation_id, seed=original.episode_seed)
    subprocess.run([sys.executable, "-c", code, str(tmp_path)], check=True, capture_output=True)
    regenerated = tmp_path / EpisodeRequest("tower", "test", original.variation_id, original.episode_seed).filename
    assert regenerated.read_bytes() == open(recorded_episodes["tower"][0], "rb").read()
    # ... and in this process too, after other episodes ran here.
    again = run_episode(EpisodeRequest("tower", "test", original.variation_id, original.episode_seed), tmp_path / "again")
    assert open(again.path, "rb").read() == regenerated.read_bytes()


def test_dense_frames_between_keyframes(tmp_path):
    request = EpisodeRequest("push_buttons", "train", 0, 5, image_size=(32, 32), dense_fps=10.0)
    outcome = run_episode(request, tmp_path)
    episode = read_episode(outcome.path)
    dense = episode.dense_frames()
    times = [f.time_ns for f in dense]
    assert len(dense) > len(episode.keyframes)
    assert all(b - a == 100_000_000 for a, b in zip(times[:-1], times[1:]))  # exactly 10 fps of sim time
    assert len({f.time_ns for f in episode.frames}) == len(episode.frames)  # one frame per instant
    assert episode.frames[0].is_keyframe and episode.frames[0].is_dense


def test_format_version_2_recordings_are_still_read(tmp_path):
    path = EpisodeWriter(tmp_path / "v2.mcap", _info(format_version=2)).close(0, True, [], {})
    assert read_episode(path).info.format_version == 2
