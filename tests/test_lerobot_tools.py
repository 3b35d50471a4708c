"""LeRobot's own tools on demo-factory datasets.

* multi-process training with LeRobot's engine: ``accelerate launch`` of ``lerobot-train
  --policy.type=hiveformer`` in two processes (on CPU: gloo; on GPUs the same launcher starts one process per
  GPU with nccl, not exercised here);
* ``lerobot-dataset-viz`` writes a Rerun recording of an episode, depth logged as depth;
* ``lerobot-edit-dataset`` info, split and merge give datasets whose features (depth as LeRobot's native
  depth feature, the calibration feature's info) and frames are the source's, that train, and whose
  checkpoints evaluate. The edited datasets lose ``meta/demo_factory.json`` (LeRobot writes a new dataset
  and copies only its own files), so ``demo-factory eval --dataset`` refuses them; the checkpoint trained on
  one evaluates on the task's own variations (``--task``).
"""

import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import psutil
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

BIN = Path(sys.executable).parent
OFFLINE = {**os.environ, "HF_HUB_OFFLINE": "1"}
SOURCE_REPO_ID = "me/push_buttons_{split}"  # the repo ids the `converted_push_buttons` fixture converts to
RENUMBERED = ("index", "episode_index", "task_index")  # what split and merge number afresh


def run(command: list, env: dict | None = None, timeout: int = 600, finished: str | None = None,
        exit_grace: int = 120) -> subprocess.CompletedProcess:
    """The command's result; past `timeout` s, the Python stacks of every process it started, then a failure.

    faulthandler is on in the command and its children: SIGABRT makes each print where every thread of it
    stands, so a hang (a stuck rendezvous, say) names its place. torchrun starts its ranks in sessions of their
    own, so they are found as the command's descendants, not by process group.

    `finished`: a line the command logs once its work is done. A command still running `exit_grace` s after it
    is stopped the same way, with a warning that carries the stacks instead of a failure, and returns code None:
    the caller checks the work it left (test_accelerate_launch_trains_hiveformer_in_two_processes says why)."""
    with tempfile.TemporaryDirectory() as logs:
        out, err = Path(logs, "stdout"), Path(logs, "stderr")
        with out.open("a") as stdout, err.open("a") as stderr:  # the command's own file descriptors
            process = subprocess.Popen([str(c) for c in command], stdout=stdout, stderr=stderr, text=True,
                                       env={**(env or OFFLINE), "PYTHONFAULTHANDLER": "1"})
        start, finished_at = time.monotonic(), None
        while process.poll() is None:
            time.sleep(0.5)
            now = time.monotonic()
            if finished and finished_at is None and finished in out.read_text() + err.read_text():
                finished_at = now
            if now - start > timeout or (finished_at is not None and now - finished_at > exit_grace):
                stop_with_stacks(process)
                stdout, stderr = out.read_text(), err.read_text()
                report = f"{' '.join(map(str, command))}\n{stdout[-2000:]}\n{stderr[-40000:]}"
                if finished_at is None:
                    pytest.fail(f"still running after {timeout} s: {report}")
                warnings.warn(f"stopped {exit_grace} s after it logged {finished!r}: {report}", stacklevel=2)
                return subprocess.CompletedProcess(process.args, None, stdout, stderr)
        return subprocess.CompletedProcess(process.args, process.returncode, out.read_text(), err.read_text())


def stop_with_stacks(process: subprocess.Popen) -> None:
    """SIGABRT to the process and every descendant (each prints its stacks), then SIGKILL to any alive 30 s later.

    One process at a time, so that stacks written to the shared stderr do not interleave, and parents first, so that
    no launcher outlives a rank to react to its death (torchrun would SIGTERM the other ranks before they print).
    """
    launcher = psutil.Process(process.pid)
    for each in [launcher, *launcher.children(recursive=True)]:
        with contextlib.suppress(psutil.NoSuchProcess, psutil.TimeoutExpired):
            each.send_signal(signal.SIGABRT)
            each.wait(timeout=30)
        with contextlib.suppress(psutil.NoSuchProcess, psutil.TimeoutExpired):
            each.kill()
    process.wait()


def test_a_command_past_its_timeout_fails_with_the_stacks_of_its_processes():
    """`run`'s timeout report reaches a child in a session of its own, as torchrun starts its ranks, and kills it."""
    child = "import time; time.sleep(600)"
    parent = ("import subprocess, sys, time; "
              f"print(subprocess.Popen([sys.executable, '-c', {child!r}], start_new_session=True).pid, flush=True); "
              "time.sleep(600)")
    with pytest.raises(pytest.fail.Exception) as failure:
        run([sys.executable, "-c", parent], timeout=5)
    report = str(failure.value)
    assert report.startswith("still running after 5 s: ")
    assert report.count("Fatal Python error: Aborted") == 2 and report.count('File "<string>", line 1') == 2
    child_pid = int(report.splitlines()[1])
    assert not psutil.pid_exists(child_pid) or psutil.Process(child_pid).status() == psutil.STATUS_ZOMBIE


def test_a_command_that_hangs_after_its_work_is_stopped_with_a_warning():
    """`finished`: past `exit_grace` s after that line, the command is stopped with its stacks in a warning."""
    command = [sys.executable, "-c", "import time; print('End of training', flush=True); time.sleep(600)"]
    with pytest.warns(UserWarning, match="stopped 2 s after it logged 'End of training'") as caught:
        result = run(command, timeout=60, finished="End of training", exit_grace=2)
    assert result.returncode is None and result.stdout == "End of training\n"
    assert "Fatal Python error: Aborted" in str(caught[0].message)


def train_arguments(root: Path, repo_id: str, output_dir: Path, text_encoder: str) -> list:
    """`lerobot-train` arguments for a two-step offline CPU smoke training of HiveFormer."""
    return [
        "--policy.type=hiveformer", f"--dataset.repo_id={repo_id}", f"--dataset.root={root}",
        "--policy.device=cpu", "--policy.push_to_hub=false", f"--policy.text_encoder={text_encoder}",
        "--policy.n_history=3", "--steps=2", "--batch_size=2", "--num_workers=0", "--save_freq=2", "--log_freq=1",
        "--wandb.enable=false", f"--output_dir={output_dir}",
    ]


def source(converted_push_buttons: Path, split: str) -> LeRobotDataset:
    return LeRobotDataset(SOURCE_REPO_ID.format(split=split), root=converted_push_buttons / split)


# --- multi-process training -------------------------------------------------------------------------------


@pytest.mark.slow
def test_accelerate_cpu_flag_alone_starts_a_single_process(tmp_path):
    """Why the multi-process command below is not `accelerate launch --cpu --num_processes 2`: with `--cpu`
    Accelerate's simple launcher starts ONE process (several need mpirun and `--mpirun_hostfile`), so
    lerobot-train would silently train alone ("Effective batch size: B x 1")."""
    probe = tmp_path / "probe.py"
    probe.write_text("from accelerate import PartialState\nprint('processes:', PartialState(cpu=True).num_processes)\n")
    env = {**OFFLINE, "HF_HOME": str(tmp_path / "hf_home")}  # no accelerate config file of the machine's
    result = run([BIN / "accelerate", "launch", "--cpu", "--num_processes", "2", "--num_machines", "1",
                  "--mixed_precision", "no", "--dynamo_backend", "no", probe], env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.splitlines() == ["processes: 1"]


@pytest.mark.slow
@pytest.mark.timeout(1000)  # 45 s on an idle fast machine, 80 s beside two busy processes
def test_accelerate_launch_trains_hiveformer_in_two_processes(converted_push_buttons, tmp_path):
    """`accelerate launch --multi_gpu --num_processes 2 lerobot-train ... --policy.device=cpu`: Accelerate's
    torchrun launcher starts two ranks; lerobot-train's Accelerator(cpu=True) joins them with gloo (DDP)."""
    from lerobot_policy_hiveformer import HiveformerPolicy
    from safetensors.torch import load_file

    output_dir = tmp_path / "train"
    command = [
        BIN / "accelerate", "launch", "--multi_gpu", "--num_processes", "2", "--num_machines", "1",
        "--mixed_precision", "no", "--dynamo_backend", "no", "--main_process_port", "0",
        BIN / "lerobot-train",
        *train_arguments(converted_push_buttons / "train", "me/push_buttons_train", output_dir, "one_hot"),
    ]
    # An HF_HOME of its own: no accelerate default_config.yaml of the machine's takes part. Gloo on the
    # loopback interface: by default it takes the address the host name resolves to, which a sandbox may
    # leave unreachable, and then its ranks wait for each other until gloo's 30-minute timeout.
    env = {**OFFLINE, "HF_HOME": str(tmp_path / "hf_home"), "GLOO_SOCKET_IFNAME": "lo"}
    # In 3 of 123 runs here a rank never exits after "End of training", its checkpoint written: as train()
    # returns, the main thread, holding the GIL, frees DDP's reducer, whose ProcessGroupGloo destructor joins
    # gloo's work thread, which waits for the GIL to free the last barrier's tensors (gdb; torch 2.11; the
    # pattern of pytorch/pytorch#56297). run() stops it 120 s on, with a warning; the checkpoint is checked.
    result = run(command, env=env, timeout=900, finished="End of training")
    log = result.stdout + result.stderr
    assert result.returncode in (0, None), log[-4000:]
    assert "Effective batch size: 2 x 2 = 4" in log and "step:2 " in log

    checkpoint = output_dir / "checkpoints" / "last"
    training_step = json.loads((checkpoint / "training_state" / "training_step.json").read_text())
    assert training_step == {"step": 2, "num_processes": 2, "batch_size": 2}

    weights = load_file(checkpoint / "pretrained_model" / "model.safetensors")
    assert not any(k.startswith("module.") for k in weights)  # saved unwrapped from DDP
    policy = HiveformerPolicy.from_pretrained(checkpoint / "pretrained_model")
    assert policy.config.text_encoder == "one_hot" and policy.config.n_history == 3
    state = policy.state_dict()
    assert set(weights) <= set(state)
    assert all(torch.equal(state[k], v) for k, v in weights.items())
    assert all(torch.isfinite(v).all() for v in weights.values() if v.is_floating_point())


# --- lerobot-dataset-viz ----------------------------------------------------------------------------------


@pytest.mark.slow
def test_dataset_viz_writes_a_recording_with_depth_as_depth(converted_push_buttons, tmp_path):
    out = tmp_path / "viz"
    result = run([BIN / "lerobot-dataset-viz", "--repo-id", "me/push_buttons_train",
                  "--root", converted_push_buttons / "train", "--episode-index", "0", "--mode", "local",
                  "--save", "1", "--output-dir", out, "--num-workers", "0"])
    assert result.returncode == 0, result.stderr[-3000:]
    recording = out / "me_push_buttons_train_episode_0.rrd"
    assert recording.read_bytes()[:4] == b"RRF2" and recording.stat().st_size > 10_000

    try:
        from rerun.experimental import RrdReader  # rerun-sdk >= 0.32
    except ImportError:
        pytest.skip("this rerun-sdk cannot read a recording back (no rerun.experimental.RrdReader)")
    rows: dict[str, dict[int, dict]] = {}  # entity -> frame_index -> the logged row's columns
    for chunk in RrdReader(str(recording)).store().stream():
        if not chunk.is_static:
            for row in chunk.to_record_batch().to_pylist():
                rows.setdefault(str(chunk.entity_path).lstrip("/"), {})[row["frame_index"]] = row
    dataset = source(converted_push_buttons, "train")
    episode_length = int(dataset.meta.episodes["length"][0])
    for key in dataset.meta.camera_keys:
        assert sorted(rows[key]) == list(range(episode_length)), key
        archetype = "DepthImage" if key in dataset.meta.depth_keys else "Image"
        assert f"{archetype}:buffer" in rows[key][0], key
    last = dataset[episode_length - 1]
    for key in dataset.meta.depth_keys:  # e.g. observation.depth.wrist
        row = rows[key][episode_length - 1]
        assert row["DepthImage:meter"] == [1000.0]  # frames are in mm
        expected = last[key][0].numpy()  # float32 mm, (H, W)
        assert (row["DepthImage:format"][0]["height"], row["DepthImage:format"][0]["width"]) == expected.shape
        depth = np.frombuffer(bytes(row["DepthImage:buffer"][0]), dtype=np.float32).reshape(expected.shape)
        np.testing.assert_array_equal(depth, expected)
        assert expected.max() > 1.0


# --- lerobot-edit-dataset ---------------------------------------------------------------------------------


@pytest.mark.slow
def test_edit_dataset_info_describes_our_split(converted_push_buttons):
    root = converted_push_buttons / "train"
    result = run([BIN / "lerobot-edit-dataset", "--repo_id", "me/push_buttons_train", "--root", root,
                  "--operation.type", "info", "--operation.show_features", "true"])
    assert result.returncode == 0, result.stderr[-3000:]
    info = json.loads((root / "meta" / "info.json").read_text())
    assert f"Total episode: {info['total_episodes']} " in result.stdout
    assert f"Total frame(Actual Count): {info['total_frames']}({info['total_frames']})" in result.stdout
    features = json.loads(result.stdout.split("Features:\n", 1)[1])
    assert features == info["features"]
    assert features["observation.depth.wrist"]["info"] == {"is_depth_map": True, "depth_unit": "mm"}
    assert "unproject" in features["observation.calibration.wrist"]["info"]


@pytest.fixture(scope="module")
def edited(converted_push_buttons, tmp_path_factory):
    """Our train split split in two by episode (``a``: episode 0, ``b``: episode 1) and our train and val
    splits merged, with `lerobot-edit-dataset`: ``{name: (root, repo_id, [(source split, episode), ...])}``."""
    base = tmp_path_factory.mktemp("edited")
    edit = BIN / "lerobot-edit-dataset"
    split = run([edit, "--repo_id", "me/push_buttons_train", "--root", converted_push_buttons / "train",
                 "--new_root", base / "split", "--operation.type", "split",
                 "--operation.splits", '{"a": [0], "b": [1]}'])
    assert split.returncode == 0, split.stderr[-3000:]
    merge = run([edit, "--new_repo_id", "me/push_buttons_trainval", "--new_root", base / "trainval",
                 "--operation.type", "merge",
                 "--operation.repo_ids", "['me/push_buttons_train', 'me/push_buttons_val']",
                 "--operation.roots", str([str(converted_push_buttons / s) for s in ("train", "val")])])
    assert merge.returncode == 0, merge.stderr[-3000:]
    return {
        "split_a": (base / "split" / "a", "me/push_buttons_train_a", [("train", 0)]),
        "split_b": (base / "split" / "b", "me/push_buttons_train_b", [("train", 1)]),
        "merged": (base / "trainval", "me/push_buttons_trainval", [("train", 0), ("train", 1), ("val", 0)]),
    }


@pytest.mark.slow
@pytest.mark.parametrize("name", ["split_a", "split_b", "merged"])
def test_split_and_merge_keep_features_depth_and_frames(edited, converted_push_buttons, name):
    root, repo_id, origins = edited[name]
    dataset = LeRobotDataset(repo_id, root=root)
    sources = {split: source(converted_push_buttons, split) for split in {s for s, _ in origins}}
    train = sources["train"]

    # Every feature as we wrote it: depth is still LeRobot's depth feature (16-bit PNG, mm), the
    # calibration feature keeps its info.
    assert dataset.meta.features == train.meta.features
    assert dataset.meta.depth_keys == train.meta.depth_keys == [f"observation.depth.{c}" for c in
                                                                 ("left_shoulder", "right_shoulder", "wrist")]
    assert dataset.depth_output_unit == "mm"
    assert dataset.meta.total_episodes == len(origins)

    # Every frame is its source frame (depth as float mm), but for the renumbered indices.
    edited_index = 0
    for episode, (split, source_episode) in enumerate(origins):
        src = sources[split]
        start, end = (int(src.meta.episodes[k][source_episode]) for k in ("dataset_from_index", "dataset_to_index"))
        for source_index in range(start, end):
            frame, expected = dataset[edited_index], src[source_index]
            assert frame["episode_index"].item() == episode and frame["task"] == expected["task"]
            for key, value in expected.items():
                if isinstance(value, torch.Tensor) and key not in RENUMBERED:
                    assert torch.equal(frame[key], value), (name, edited_index, key)
            edited_index += 1
    assert edited_index == len(dataset)
    depth = dataset[0]["observation.depth.wrist"]
    assert depth.dtype == torch.float32 and depth.shape == (1, 32, 32) and depth.max() > 1.0  # mm, not metres

    # Depth statistics stay in mm: a merge weighs its sources' means by their frame counts.
    stats = dataset.meta.stats["observation.depth.wrist"]
    counts = [s.meta.stats["observation.depth.wrist"]["count"][0] for s in sources.values()]
    if name == "merged":
        assert stats["count"][0] == sum(counts)
        means = [float(s.meta.stats["observation.depth.wrist"]["mean"].item()) for s in sources.values()]
        assert float(stats["mean"].item()) == pytest.approx(np.average(means, weights=counts), rel=1e-5)
    assert float(stats["max"].item()) > 1.0

    # demo-factory's own provenance is not carried over (LeRobot copies only its own files).
    assert not (root / "meta" / "demo_factory.json").exists()


@pytest.mark.slow
def test_demo_factory_eval_refuses_an_edited_split_without_provenance(edited, tmp_path):
    """`demo-factory eval --dataset` takes its (variation, instruction) pairs from meta/demo_factory.json, which
    lerobot-edit-dataset does not carry over: a one-line error, exit 2 (the data's variation_id column and
    task strings survive, see the test above)."""
    folder = tmp_path / "dataset"
    folder.mkdir()
    (folder / "trainval").symlink_to(edited["merged"][0], target_is_directory=True)
    result = run([sys.executable, "-m", "demo_factory.cli", "eval", "--expert", "--dataset", folder,
                  "--episodes", "1", "--out", tmp_path / "eval"])
    assert result.returncode == 2
    assert "not a demo-factory dataset (no meta/demo_factory.json; " in result.stderr
    assert "evaluate with --task TASK" in result.stderr
    assert not (tmp_path / "eval").exists()


@pytest.mark.slow
def test_merged_dataset_trains_and_its_checkpoint_evaluates(edited, tmp_path):
    root, repo_id, _ = edited["merged"]
    output_dir = tmp_path / "train"
    result = run([BIN / "lerobot-train", *train_arguments(root, repo_id, output_dir, "clip_tiny_random")])
    log = result.stdout + result.stderr
    assert result.returncode == 0, log[-3000:]
    assert "dataset.num_episodes=3" in log and "step:2 " in log
    checkpoint = output_dir / "checkpoints" / "last" / "pretrained_model"

    # Evaluated on the task's own variations: the merged dataset has no provenance to take pairs from.
    out = tmp_path / "eval"
    result = run([sys.executable, "-m", "demo_factory.cli", "eval", "--policy.path", checkpoint,
                  "--task", "push_buttons", "--splits", "train", "--episodes", "1", "--image-size", "32",
                  "--out", out])
    assert result.returncode == 0, result.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    assert results["policy"].startswith("hiveformer") and results["control"]["action_space"] == "keyframe"
    summary = results["splits"]["train"]
    assert summary["episodes"] == 1 and 0.0 <= summary["success_rate"] <= 1.0 and summary["mean_steps"] >= 1
