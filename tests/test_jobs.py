"""Generation jobs: parallel workers, shards, resuming after kill -9, manifests, named variations."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from demo_factory.tasks import get_task

SMALL = ["--image-size", "32"]


def generate(*args):
    return subprocess.run([sys.executable, "-m", "demo_factory.cli", "generate", *args], capture_output=True, text=True)


def files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.glob("*.mcap"))}


@pytest.mark.slow
def test_workers_shards_and_resume_after_kill_give_the_same_files(tmp_path):
    job = ["--task", "push_buttons", "--episodes", "6", "--seed", "4", *SMALL]
    one = generate(*job, "--workers", "1", "--out", str(tmp_path / "one"))
    assert one.returncode == 0, one.stderr
    reference = files(tmp_path / "one")
    assert len(reference) == 6

    two = generate(*job, "--workers", "2", "--out", str(tmp_path / "two"))
    assert two.returncode == 0, two.stderr
    assert files(tmp_path / "two") == reference

    for i in range(2):
        shard = generate(*job, "--workers", "1", "--shard", f"{i}/2", "--out", str(tmp_path / "sharded"))
        assert shard.returncode == 0, shard.stderr
    assert files(tmp_path / "sharded") == reference

    # kill -9 mid-job, then the same command finishes it: the same set, nothing generated twice.
    out = tmp_path / "killed"
    process = subprocess.Popen([sys.executable, "-m", "demo_factory.cli", "generate", *job, "--workers", "1",
                                "--out", str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and len(list(out.glob("*.mcap"))) < 2:
        time.sleep(0.05)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    survivors = {p.name: p.stat().st_mtime_ns for p in out.glob("*.mcap")}
    assert 2 <= len(survivors) < 6
    resumed = generate(*job, "--workers", "1", "--out", str(out))
    assert resumed.returncode == 0, resumed.stderr
    assert f"({len(survivors)} already present)" in resumed.stdout
    assert files(out) == reference
    assert all((out / name).stat().st_mtime_ns == mtime for name, mtime in survivors.items())
    assert not list(out.glob(".*.partial"))


def test_resuming_with_other_parameters_is_refused(tmp_path):
    first = generate("--task", "push_buttons", "--episodes", "1", *SMALL, "--out", str(tmp_path))
    assert first.returncode == 0, first.stderr
    again = generate("--task", "push_buttons", "--episodes", "1", "--seed", "9", *SMALL, "--out", str(tmp_path))
    assert again.returncode == 2
    assert "other parameters (seed: 0 before, 9 now)" in again.stderr
    other_split = generate("--task", "push_buttons", "--split", "test", "--episodes", "1", *SMALL, "--out", str(tmp_path))
    assert other_split.returncode == 0, other_split.stderr  # another job may share the folder


def test_named_variations_generate_exactly_those(tmp_path):
    result = generate("--task", "push_buttons", "--variation", "Maroon,grey", "--variation", "teal",
                      "--episodes-per-variation", "2", *SMALL, "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    task = get_task("push_buttons")
    ids = {task.variation_of(["maroon", "gray"]).id, task.variation_of(["teal"]).id}
    names = sorted(p.name for p in tmp_path.glob("*.mcap"))
    assert len(names) == 4 and all(n.startswith("push_buttons_test_") for n in names)
    assert {int(n.split("_var")[1][:4]) for n in names} == ids


@pytest.mark.parametrize("variation, message", [
    ("red", "unknown colour 'red' for push_buttons"),
    ("navy,Navy", "colour 'navy' is repeated"),
    ("navy,teal,olive,azure", "has 4 colours; push_buttons takes 1 to 3"),
])
def test_bad_named_variations_are_refused(tmp_path, variation, message):
    result = generate("--task", "push_buttons", "--variation", variation, "--out", str(tmp_path / "out"))
    assert result.returncode == 2 and message in result.stderr
    assert not (tmp_path / "out").exists()


def test_a_training_variation_requested_for_test_is_refused_as_a_leak(tmp_path):
    train_variation = get_task("tower").split_variations("train")[0]
    result = generate("--task", "tower", "--variation", train_variation.name, "--out", str(tmp_path / "out"))
    assert result.returncode == 2
    assert "is a train variation of tower" in result.stderr and "would leak train data into a test split" in result.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_ray_executor_gives_the_same_files_as_the_process_pool(tmp_path):
    from demo_factory.generate import job_requests, run_requests

    requests = job_requests("push_buttons", "train", 3, 5, image_size=(32, 32))
    pool = list(run_requests(requests, tmp_path / "pool", workers=2))
    ray = list(run_requests(requests, tmp_path / "ray", workers=2, executor="ray"))
    assert [o.kept for o in ray] == [o.kept for o in pool] == [True] * 3
    assert files(tmp_path / "ray") == files(tmp_path / "pool")


def test_disk_full_stops_with_a_clear_message_and_keeps_finished_episodes(tmp_path, monkeypatch, capsys):
    import errno

    from demo_factory.cli import main
    from demo_factory.record import read_episode
    from demo_factory.record.writer import EpisodeWriter

    original_close, calls = EpisodeWriter.close, []

    def close_until_the_disk_fills(self, *args, **kwargs):
        calls.append(self.path)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return original_close(self, *args, **kwargs)

    monkeypatch.setattr(EpisodeWriter, "close", close_until_the_disk_fills)
    code = main(["generate", "--task", "push_buttons", "--episodes", "3", "--workers", "1", *SMALL, "--out", str(tmp_path)])
    assert code == 1
    message = capsys.readouterr().err.strip().splitlines()[-1]
    assert "No space left on device" in message and "episodes finished before it: 1, all complete and valid" in message
    recordings = list(tmp_path.glob("*.mcap"))
    assert len(recordings) == 1 and read_episode(recordings[0]).info.success
    assert not list(tmp_path.glob(".*.partial"))  # the interrupted episode left nothing behind
