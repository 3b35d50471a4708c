"""The documentation holds what it claims: a short README whose results table is the run table's, quick-start
commands that their own `--help` accepts, no over-long lines, no work diary."""

from __future__ import annotations

import csv
import os
import re
import shlex
import subprocess
import sys
from functools import cache
from pathlib import Path

import pytest
from lerobot.configs.parser import PATH_KEY, PLUGIN_DISCOVERY_SUFFIX

from demo_factory.tools import runs

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BIN = Path(sys.executable).parent
SKIPPED = {".git", ".venv", "data", "outputs", "bench", "build", "__pycache__", ".pytest_cache"}
TEXT_SUFFIXES = {".py", ".md", ".toml", ".csv", ".txt", ".cfg", ".json", ".html", ".js", ".yaml", ".yml"}


def tree_files(suffixes: set[str]) -> list[Path]:
    """The project's own text files: everything but environments, generated data and caches."""
    found = []
    for folder, subfolders, files in os.walk(ROOT):
        subfolders[:] = [name for name in subfolders if name not in SKIPPED and not name.endswith(".egg-info")
                         and not (name.startswith(".") and name not in (".ci", ".github"))]  # a user's own dot folders
        found += [Path(folder) / name for name in files if Path(name).suffix in suffixes or name in ("Makefile", "run")]
    return found


def test_readme_fits_on_a_few_screens_with_the_two_commands_first():
    lines = README.read_text().splitlines()
    assert len(lines) <= 300
    first = "\n".join(lines[:30])
    assert "make demo" in first and "make test" in first


def test_no_markdown_line_is_over_200_characters():
    long_lines = [f"{path.relative_to(ROOT)}:{number}" for path in tree_files({".md"})
                  for number, line in enumerate(path.read_text().splitlines(), start=1) if len(line) > 200]
    assert not long_lines


def test_no_numbered_work_session_is_named_anywhere():
    pattern = re.compile(r"\bsessions?[ _-]?\d", re.IGNORECASE)
    named = [f"{path.relative_to(ROOT)}:{number}: {line.strip()[:80]}" for path in tree_files(TEXT_SUFFIXES)
             for number, line in enumerate(path.read_text(errors="replace").splitlines(), start=1)
             if pattern.search(line)]
    assert not named


def test_every_docs_link_of_the_readme_exists():
    targets = re.findall(r"\]\(([^)#]+)\)", README.read_text())
    assert targets
    assert [target for target in targets if not target.startswith("http") and not (ROOT / target).exists()] == []


def test_the_readme_results_table_is_the_run_tables():
    table = runs.readme_table(README.read_text())
    assert table == runs.results_table(runs.read_runs())
    assert all(f"`{name}`" in table for name in ("make reference", "make reference-unseen", "make reference-tower"))


def test_the_run_table_holds_every_run_with_its_columns(tmp_path):
    rows = runs.read_runs()
    assert len(rows) >= 30  # every reference run so far, failures included
    assert {row["status"] for row in rows} >= {"completed", "stopped"}
    for recipe in ("make reference", "make reference-unseen", "make reference-tower"):
        assert any(row["recipe"] == recipe and row["current"] == "1" for row in rows), recipe
    # A malformed table is refused in one line naming the value.
    bad = tmp_path / "runs.csv"
    with bad.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=runs.COLUMNS)
        writer.writeheader()
        writer.writerow({**rows[0], "seen": "ninety"})
    with pytest.raises(runs.UsageError, match="seen 'ninety' is not a number"):
        runs.read_runs(bad)


def test_a_reference_run_summary_becomes_a_row_and_the_table_follows(tmp_path):
    summary = {"configuration": {"task": "push_buttons", "unseen": True, "policy": "hiveformer", "seed": 2,
                                 "steps": 8000, "train_arg": []},
               "stage_seconds": {"generate_train": 60.0, "train": 3000.0, "eval": 240.0},
               "train_step": {"updt_s": 0.371},
               "results": {"splits": {"train": {"success_rate": 1.0}, "test_unseen_synthetic": {"success_rate": 0.9},
                                      "test_unseen_corrupted": {"success_rate": 0.125},
                                      "test_unseen_paraphrased": {"success_rate": 0.5},
                                      "test_unseen_human": {"success_rate": 0.65}}}}
    table = tmp_path / "runs.csv"
    row = runs.run_row(summary, "a test run")
    runs.add_run(table, row)
    runs.add_run(table, {**row, "seed": "3", "current": "1"})
    rows = runs.read_runs(table)
    assert [r["seed"] for r in rows] == ["3", "2"]
    assert rows[1] | {"date": "", "commit": "", "machine": ""} == {
        **{column: "" for column in runs.COLUMNS}, "command": "python -m demo_factory.tools.reference_run --unseen --seed 2",
        "recipe": "make reference-unseen", "task": "push_buttons", "seed": "2", "steps": "8000", "s_per_step": "0.371",
        "wall_min": "55", "seen": "100.0", "unseen_synthetic": "90.0", "unseen_corrupted": "12.5",
        "unseen_paraphrased": "50.0", "unseen_human": "65.0", "status": "completed", "current": "0",
        "note": "a test run"}
    assert "MiniLM | 3 | 100 | 90 | 12.5 | 50 | 65 | 55 |" in runs.results_table(rows)
    randomised = {**summary, "configuration": {**summary["configuration"], "perturb": "all=0.3", "robustness": True}}
    assert runs.run_row(randomised, "x")["command"] == ("python -m demo_factory.tools.reference_run --unseen "
                                                        "--perturb all=0.3 --robustness --seed 2")
    # A summary that records its command gives it as typed; an ablation's row is filed under its ablation row.
    typed = "python -m demo_factory.tools.reference_run --unseen --ablation no_history --steps 400 --curve 2"
    ablation = {**summary, "command": typed, "configuration": {**summary["configuration"], "ablation": "no_history"}}
    runs.add_run(table, {**runs.run_row(ablation, "x"), "current": "1"})
    assert {"command": typed, "recipe": "ablation no_history"}.items() <= runs.read_runs(table)[0].items()
    layout = runs.ablation_table(runs.read_runs(table))
    assert "| full model | `make reference-unseen` | 3 | 100 | 90 | 12.5 | 65 |" in layout
    assert "| without history | `reference_run --unseen --ablation no_history` | 2 | 100 | 90 | 12.5 | 65 |" in layout
    assert "| without E_x | `reference_run --unseen --ablation no_ex` | — | not run | not run | not run | not run |" in layout


def test_the_ablation_table_of_the_unseen_page_is_the_run_tables():
    page = ROOT / "docs" / "reference" / "unseen.md"
    assert runs.marked_table(page.read_text(), runs.ABLATION_BEGIN, runs.ABLATION_END) == runs.ablation_table(
        runs.read_runs())


def test_runs_add_refuses_a_file_that_is_no_run_summary(tmp_path, capsys):
    bad = tmp_path / "reference_run.json"
    bad.write_text("{}")
    assert runs.main(["--runs", str(tmp_path / "runs.csv"), "add", str(bad), "--note", "x"]) == 2
    assert "is not a reference run summary" in capsys.readouterr().err
    assert not (tmp_path / "runs.csv").exists()


def quick_start_commands() -> list[list[str]]:
    """Every command of the README's code blocks, continuation lines joined, comments dropped."""
    blocks = re.findall(r"```\n(.*?)```", README.read_text(), re.DOTALL)
    commands = []
    for block in blocks:
        for line in block.replace("\\\n", " ").splitlines():
            if line.split(" ", 1)[0] in ("demo-factory", "lerobot-train", "lerobot-eval", "make", "python"):
                commands.append(shlex.split(line.split("#", 1)[0]))
    return commands


@cache
def help_text(*prefix: str) -> str:
    done = subprocess.run([str(BIN / prefix[0]) if prefix[0] != "python" else sys.executable, *prefix[1:], "--help"],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def make_targets() -> set[str]:
    return set(re.findall(r"^([a-z][a-z-]*):", (ROOT / "Makefile").read_text(), re.MULTILINE))


@pytest.mark.slow
def test_every_quick_start_command_is_accepted_by_its_help():
    commands = quick_start_commands()
    assert {words[0] for words in commands} >= {"demo-factory", "lerobot-train", "make"}
    for words in commands:
        if words[0] == "make":
            assert words[1] in make_targets(), words
            continue
        if words[0] == "demo-factory":
            prefix = tuple(words[:2])
        elif words[0] == "python":
            prefix = tuple(words[:3])  # python -m MODULE
        else:  # LeRobot's commands list a policy's or an env's options once its type (and package) is given
            prefix = (words[0], *(w for w in words if re.match(r"--\w+\.(type|discover_packages_path)=", w)))
        text = help_text(*prefix)
        # LeRobot reads a checkpoint's path and a plugin's package before its parser, which does not list them
        options = {word.split("=", 1)[0] for word in words if word.startswith("--")
                   and not word.split("=", 1)[0].endswith((f".{PATH_KEY}", f".{PLUGIN_DISCOVERY_SUFFIX}"))}
        assert [option for option in options if option not in text] == [], (words, prefix)
