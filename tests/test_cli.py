"""The demo-factory command as a user runs it: listing, generating, inspecting, and bad input."""

import json
import os
import subprocess
import sys

import pytest

from demo_factory.cli import main


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "demo_factory.cli", *args], capture_output=True, text=True, cwd=cwd)


def test_tasks_lists_variation_counts_and_splits(capsys):
    assert main(["tasks"]) == 0
    out = capsys.readouterr().out
    assert "push_buttons" in out and "tower" in out and "5220" in out and "100" in out


@pytest.mark.parametrize("args, message", [
    (["--task", "nope"], "invalid choice: 'nope' (choose from 'push_buttons', 'tower', 'reach_target'"),
    (["--task", "tower", "--split", "val"], "invalid choice: 'val' (choose from 'train', 'test')"),
    (["--task", "tower", "--episodes", "0"], "0 is not allowed; must be at least 1"),
    (["--task", "tower", "--image-size", "big"], "'big' is not an image size"),
])
def test_bad_options_exit_2_with_one_clear_line_and_write_nothing(tmp_path, args, message):
    out = tmp_path / "out"
    result = run_cli("generate", *args, "--out", str(out))
    assert result.returncode == 2
    assert message in result.stderr
    assert not out.exists()


def test_output_folder_with_other_files_is_refused(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    result = run_cli("generate", "--task", "tower", "--episodes", "1", "--out", str(tmp_path))
    assert result.returncode == 2
    assert "holds other files (notes.txt)" in result.stderr.strip().splitlines()[-1]
    assert sorted(os.listdir(tmp_path)) == ["notes.txt"]


def test_unwritable_output_is_refused(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    result = run_cli("generate", "--task", "tower", "--episodes", "1", "--out", str(blocker / "sub"))
    assert result.returncode == 2 and "cannot create it" in result.stderr


def test_generate_then_inspect_then_resume(tmp_path):
    out = tmp_path / "raw"
    result = run_cli("generate", "--task", "push_buttons", "--split", "test", "--episodes", "2", "--seed", "7",
                     "--image-size", "32", "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "kept 2 of 2 episodes" in result.stdout and "seconds per episode" in result.stdout
    assert "planner attempts per planned transition" in result.stdout
    recordings = sorted(out.glob("*.mcap"))
    assert len(recordings) == 2
    summary = json.loads((out / "generation_summary_push_buttons_test.json").read_text())
    assert summary["kept"] == 2 and summary["failed"] == [] and summary["total_seconds"] > 0
    assert summary["command"].endswith("--image-size 32x32")  # enough to regenerate exactly
    log = [json.loads(line) for line in (out / "generation_log_push_buttons_test.jsonl").read_text().splitlines()]
    attempts = [a for episode in log for a in episode["planner_attempts"]]
    assert len(log) == 2 and attempts and all({"seed", "status", "solve_seconds", "path_length"} <= set(a) for a in attempts)
    report = json.loads((out / "report.json").read_text())["jobs"]
    assert [(r["task"], r["split"], r["kept"]) for r in report] == [("push_buttons", "test", 2)]
    assert "| push_buttons | test | 2 | 2 | 0 | 100.0% |" in (out / "report.md").read_text()
    assert (out / "report.png").read_bytes()[:4] == b"\x89PNG"

    shown = run_cli("inspect", str(recordings[0]))
    assert shown.returncode == 0, shown.stderr
    for expected in ("/cameras/wrist/rgb", "/keyframes", "instruction:", "success: True", "split test"):
        assert expected in shown.stdout

    before = {p: p.stat().st_mtime_ns for p in recordings}
    again = run_cli("generate", "--task", "push_buttons", "--split", "test", "--episodes", "2", "--seed", "7",
                    "--image-size", "32", "--out", str(out))
    assert again.returncode == 0 and "(2 already present)" in again.stdout
    assert {p: p.stat().st_mtime_ns for p in recordings} == before


def test_inspect_reports_a_damaged_file_in_one_line(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n" + b"garbage")
    result = run_cli("inspect", str(bad))
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1].startswith("demo-factory inspect: error:")
    assert "bad.mcap" in result.stderr
