"""Shared fixtures: the suite's offline Hub setting, small real recordings generated once per test session, and
builders of synthetic recordings."""

from __future__ import annotations

import os
from pathlib import Path

# Tests need no network: every Hugging Face client of the suite's processes is offline, set before anything
# imports huggingface_hub. The Hub's own tests start the client in a process with an environment of its own.
os.environ.setdefault("HF_HUB_OFFLINE", "1")

# The suite runs in one process per core (`-n auto`, pyproject.toml). Each of them, and every command a test
# starts, gets one OpenMP thread: several processes each spinning a thread per core slow one another down
# many times over.
if "PYTEST_XDIST_WORKER" in os.environ:
    os.environ["OMP_NUM_THREADS"] = "1"

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from demo_factory.generate import job_requests, run_requests  # noqa: E402
from demo_factory.record import (  # noqa: E402
    FORMAT_VERSION,
    CameraObservation,
    EpisodeInfo,
    EpisodeWriter,
    Frame,
    Keyframe,
    PlannerAttempt,
    RobotState,
)
from demo_factory.tasks import get_task  # noqa: E402

# The files that take longest (end-to-end chains), first: each is handed to a process at the start instead of
# ending the run alone (with `--dist loadfile --no-loadscope-reorder`, files are handed out in this order).
LONGEST_FIRST = ("test_reference_run_tower.py", "test_reference_run.py", "test_reference_suite.py", "test_lerobot_tools.py", "test_publish_http.py",
                 "test_dense.py", "test_evaluate.py", "test_experts.py", "test_ten_tasks.py")


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: file order otherwise


@pytest.fixture(scope="session")
def recorded_episodes(tmp_path_factory):
    """Two push_buttons and one tower episode recorded to MCAP: ``{task: [paths]}``."""
    out = tmp_path_factory.mktemp("recordings")
    requests = job_requests("push_buttons", "train", 2, 0) + job_requests("tower", "test", 1, 0)
    outcomes = list(run_requests(requests, out))
    assert all(o.kept for o in outcomes), [o.reason for o in outcomes]
    paths: dict[str, list[str]] = {}
    for o in outcomes:
        paths.setdefault(o.request.task, []).append(o.path)
    return paths


@pytest.fixture(scope="session")
def converted_push_buttons(tmp_path_factory):
    """A small converted push_buttons dataset (32x32 cameras): its root, with one folder per split."""
    from demo_factory.cli import main

    base = tmp_path_factory.mktemp("push_buttons")
    raw, out = base / "raw", base / "lerobot"
    for split, episodes in (("train", 3), ("test", 2)):
        assert main(["generate", "--task", "push_buttons", "--split", split, "--episodes", str(episodes),
                     "--image-size", "32", "--workers", "1", "--out", str(raw / split)]) == 0
    assert main(["convert", "--in", str(raw), "--out", str(out), "--repo-id", "me/push_buttons",
                 "--val-ratio", "0.34", "--no-progress"]) == 0
    return out


# Synthetic recordings: random images and poses written by the recorder's own writer, for the tests of what reads
# recordings (the converter, the dense export) without the simulator's cost.
RECORDING_CAMERAS = ("left_shoulder", "right_shoulder", "wrist")
SECOND = 1_000_000_000


def synthetic_camera(rng: np.random.Generator, size: tuple[int, int]) -> CameraObservation:
    """Random RGB, depth (0.2-2 m in whole millimetres, a few pixels without a hit), segmentation and camera pose."""
    extrinsics = np.eye(4)
    extrinsics[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    extrinsics[:3, 3] = rng.uniform(-1, 1, 3)
    depth = np.round(rng.uniform(0.2, 2.0, size), 3).astype(np.float32)
    depth[0, :4] = 0.0  # no hit
    return CameraObservation(
        rgb=rng.integers(0, 256, (*size, 3), dtype=np.uint8), depth=depth,
        segmentation=rng.integers(-1, 5, size).astype(np.int32),
        intrinsics=np.array([30.0, 31.0, 15.5, 16.0]) * size[1] / 32, extrinsics=extrinsics,
    )


def synthetic_robot(rng: np.random.Generator, gripper_open: float | None = None) -> RobotState:
    """Random joints and gripper pose (either quaternion sign); the gripper open or closed at random unless given."""
    pose = np.concatenate([rng.uniform(-1, 1, 3), Rotation.random(random_state=int(rng.integers(1 << 30))).as_quat()])
    opening = float(rng.integers(0, 2)) if gripper_open is None else gripper_open
    return RobotState(rng.uniform(-2, 2, 7), pose, opening, 0.04)


def _info(task: str, split: str, variation, seed: int, cameras, size, dense_fps: float, scene=None) -> EpisodeInfo:
    return EpisodeInfo(FORMAT_VERSION, task, split, variation.id, list(variation.words), seed,
                       get_task(task).instruction(variation, seed), list(cameras), size, dense_fps, extra=scene or {})


def _path(folder: Path, task: str, split: str, variation, seed: int) -> Path:
    return Path(folder) / f"{task}_{split}_var{variation.id:04d}_seed{seed:010d}.mcap"


def _write_recording(folder: Path, task: str, split: str, variation, seed: int, keyframes: int,
                     dense_fps: float = 0.0, cameras=RECORDING_CAMERAS, scene: dict | None = None,
                     size: tuple[int, int] = (32, 32)) -> Path:
    """A keyframe recording: ``keyframes`` keyframes one second apart, a dense frame between two keyframes when
    ``dense_fps``, two planned transitions' attempts; ``scene``: its scene facts."""
    rng = np.random.default_rng(seed)
    writer = EpisodeWriter(_path(folder, task, split, variation, seed),
                           _info(task, split, variation, seed, cameras, size, dense_fps, scene))
    for k in range(keyframes):
        t = k * SECOND
        writer.write_frame(Frame(t, True, False, k, synthetic_robot(rng), {c: synthetic_camera(rng, size) for c in cameras}))
        writer.write_keyframe(Keyframe(k, t, synthetic_robot(rng).gripper_pose, float(k % 2),
                                       synthetic_robot(rng).gripper_pose, "start" if k == 0 else "planned"))
        if dense_fps and k < keyframes - 1:
            writer.write_frame(Frame(t + SECOND // 2, False, True, k, synthetic_robot(rng),
                                     {c: synthetic_camera(rng, size) for c in cameras}))
    attempts = [PlannerAttempt(k, a, seed + a, "exact" if a == n - 1 else "timeout", 1.0)
                for k, n in ((1, 1), (2, 3)) for a in range(n)]
    return writer.close(keyframes * SECOND, True, attempts, {"demo_factory": "test"})


def _write_dense_recording(folder: Path, split: str, variation, seed: int, ticks: int, fps: int = 4,
                           size: tuple[int, int] = (16, 16)) -> Path:
    """A push_buttons recording of ``ticks`` dense frames at ``fps``, keyframes at the first and the last tick, the
    gripper closing half way."""
    rng = np.random.default_rng(seed)
    writer = EpisodeWriter(_path(folder, "push_buttons", split, variation, seed),
                           _info("push_buttons", split, variation, seed, RECORDING_CAMERAS, size, float(fps)))
    tick = SECOND // fps
    for i in range(ticks):
        keyframe, index = i in (0, ticks - 1), int(i == ticks - 1)
        robot = synthetic_robot(rng, gripper_open=float(i < ticks // 2))
        writer.write_frame(Frame(i * tick, keyframe, True, index, robot,
                                 {c: synthetic_camera(rng, size) for c in RECORDING_CAMERAS}))
        if keyframe:
            writer.write_keyframe(Keyframe(index, i * tick, robot.gripper_pose, robot.gripper_open, robot.gripper_pose,
                                           "start" if i == 0 else "planned"))
    return writer.close(ticks * tick, True, [], {"demo_factory": "test"})


@pytest.fixture(scope="session")
def write_recording():
    """Writes a synthetic keyframe recording (random images and poses) into a folder: ``write_recording(folder,
    task, split, variation, seed, keyframes, dense_fps=0.0, cameras=..., scene=None, size=(32, 32))`` → its path."""
    return _write_recording


@pytest.fixture(scope="session")
def write_dense_recording():
    """Writes a synthetic dense push_buttons recording: ``write_dense_recording(folder, split, variation, seed,
    ticks, fps=4, size=(16, 16))`` → its path."""
    return _write_dense_recording
