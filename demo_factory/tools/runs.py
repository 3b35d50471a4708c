"""The table of every training run (``docs/results/runs.csv``) and the README's results table built from it.

Every reference run, experiment and failure is one row: date, commit, command, recipe, task, seed, steps,
seconds a step, wall minutes, success per split, the machine, a status and a short note. The rows marked
``current`` state each recipe's present figure; the README's results table is made from them, so a figure
lives in one place.

    python -m demo_factory.tools.runs add outputs/reference/reference_run.json --note "..."   # append a run
    python -m demo_factory.tools.runs table              # print the README's results table
    python -m demo_factory.tools.runs table --write README.md   # replace it between the README's markers
    python -m demo_factory.tools.runs ablations --write docs/reference/unseen.md   # the paper's ablation rows
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import platform
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from demo_factory.errors import UsageError

ROOT = Path(__file__).resolve().parents[2]
RUNS = ROOT / "docs" / "results" / "runs.csv"
COLUMNS = ("date", "commit", "command", "recipe", "task", "seed", "steps", "s_per_step", "wall_min", "seen",
           "unseen_synthetic", "unseen_corrupted", "unseen_paraphrased", "unseen_human", "machine", "status", "current",
           "note")
SPLIT_COLUMNS = {"seen": "train", "unseen_synthetic": "test_unseen_synthetic",
                 "unseen_corrupted": "test_unseen_corrupted", "unseen_paraphrased": "test_unseen_paraphrased",
                 "unseen_human": "test_unseen_human"}
STATUSES = ("completed", "stopped", "failed")
BEGIN, END = "<!-- results table: python -m demo_factory.tools.runs table --write README.md -->", "<!-- end of results table -->"
ABLATION_BEGIN = "<!-- ablation table: python -m demo_factory.tools.runs ablations --write docs/reference/unseen.md -->"
ABLATION_END = "<!-- end of ablation table -->"


@dataclass(frozen=True)
class Recipe:
    """A reference command as the README's results table shows it, with the paper's figures for its task."""

    trains: str
    page: str
    paper: str = ""  # the label of the paper's row, e.g. "HiveFormer paper, CLIP (push buttons)"
    paper_figures: tuple[str, ...] = ()  # seen, unseen synthetic, corrupted, paraphrased, human (%)


TOWER_PAPER = ("HiveFormer paper, CLIP (tower)", ("77.4", "56.2", "53.6", "", "24.1"))
# The README shows a paper row once, under the first recipe of its task that has current runs.
RECIPES = {
    "make reference": Recipe("push_buttons, 3 seen variations, one-hot", "docs/reference/push_buttons.md"),
    "make reference-unseen": Recipe("push_buttons, 100 variations, MiniLM", "docs/reference/unseen.md",
                                    "HiveFormer paper, CLIP (push buttons)", ("100", "86.3", "85.6", "", "74.2")),
    "make reference-tower-unseen": Recipe("tower, 100 variations, MiniLM", "docs/reference/tower.md", *TOWER_PAPER),
    "make reference-tower": Recipe("tower, 3 seen variations, one-hot", "docs/reference/tower.md", *TOWER_PAPER),
    "make reference-suite": Recipe("ten_tasks, one variation a task, one-hot", "docs/reference/suite.md",
                                   "HiveFormer paper, multi-task (Table 1)", ("83.3", "", "", "", "")),
    "make reference-act": Recipe("ACT, 1 push_buttons variation, dense", "docs/reference/act.md"),
}


# The paper's ablation rows that `reference_run --unseen --ablation NAME` measures against `make reference-unseen`; their
# rows' recipe is `ablation NAME`.
ABLATION_ROWS = {"no_history": "without history", "averaged_instruction": "instruction averaged (Avg.)",
                 "no_ex": "without E_x", "no_ex_ey": "without E_x and E_y", "one_hot": "one-hot instructions"}
ABLATION_RECIPES = {f"ablation {name}": label for name, label in ABLATION_ROWS.items()}
ABLATION_SPLITS = ("seen", "unseen_synthetic", "unseen_corrupted", "unseen_human")


def read_runs(path: Path = RUNS) -> list[dict[str, str]]:
    """The table's rows, checked: its columns, a known recipe or `experiment`, a status, numbers where numbers go."""
    with path.open(newline="") as file:
        reader = csv.DictReader(file)
        if tuple(reader.fieldnames or ()) != COLUMNS:
            raise UsageError(f"{path}: columns {reader.fieldnames} are not {list(COLUMNS)}")
        rows = list(reader)
    for line, row in enumerate(rows, start=2):
        if row["recipe"] not in (*RECIPES, *ABLATION_RECIPES, "experiment"):
            raise UsageError(f"{path}:{line}: recipe {row['recipe']!r} is none of "
                             f"{[*RECIPES, *ABLATION_RECIPES, 'experiment']}")
        if row["status"] not in STATUSES or row["current"] not in ("0", "1"):
            raise UsageError(f"{path}:{line}: status {row['status']!r} (accepted: {', '.join(STATUSES)}) or "
                             f"current {row['current']!r} (accepted: 0, 1)")
        for column in ("seed", "steps", "s_per_step", "wall_min", *SPLIT_COLUMNS):
            try:
                row[column] and float(row[column])
            except ValueError:
                raise UsageError(f"{path}:{line}: {column} {row[column]!r} is not a number") from None
    return rows


def _figures(rows: list[dict[str, str]], column: str) -> str:
    """One split's figures over the seeds, `90 / 80 / 92.5`; `—` where a run did not measure it."""
    values = [row[column] for row in rows]
    return " / ".join(f"{float(v):g}" if v else "—" for v in values) if any(values) else "—"


def _span(values: list[str]) -> str:
    numbers = sorted(round(float(v)) for v in values if v)
    if not numbers:
        return ""
    return f"{numbers[0]}" if numbers[0] == numbers[-1] else f"{numbers[0]}–{numbers[-1]}"


def _current_runs(rows: list[dict[str, str]], recipe: str) -> list[dict[str, str]]:
    """The recipe's rows marked current, the default seed first."""
    return sorted((row for row in rows if row["recipe"] == recipe and row["current"] == "1"),
                  key=lambda row: (int(row["seed"]) != 1000, int(row["seed"])))


def results_table(rows: list[dict[str, str]]) -> str:
    """The README's results table: a row per reference command from its `current` runs (the default seed first),
    success in % per split over the seeds, and the paper's row for the same task below it."""
    lines = ["| command | trains | seeds | seen | unseen synthetic | corrupted | held-out phrasings | human | wall (min) |",
             "|---|---|---|---|---|---|---|---|---|"]
    shown = set()
    for name, recipe in RECIPES.items():
        current = _current_runs(rows, name)
        if not current:
            continue
        figures = " | ".join(_figures(current, column) for column in SPLIT_COLUMNS)
        lines.append(f"| [`{name}`]({recipe.page}) | {recipe.trains} | {' / '.join(row['seed'] for row in current)} "
                     f"| {figures} | {_span([row['wall_min'] for row in current])} |")
        if recipe.paper and recipe.paper not in shown:
            lines.append(f"| *{recipe.paper}* | | | {' | '.join(recipe.paper_figures)} | |")
            shown.add(recipe.paper)
    return "\n".join(lines)


def ablation_table(rows: list[dict[str, str]]) -> str:
    """The paper's ablation rows for push buttons: `make reference-unseen` (the full model) and each ablation row from
    their `current` runs (success in % per split over the seeds, `not run` where none is), the paper's row below ours
    where the paper's figures are recorded here."""
    full = RECIPES["make reference-unseen"]
    lines = ["| model | command | seeds | seen | unseen synthetic | corrupted | human |", "|---|---|---|---|---|---|---|"]
    for recipe, label, command in [("make reference-unseen", "full model", "make reference-unseen"),
                                   *((f"ablation {name}", label, f"reference_run --unseen --ablation {name}")
                                     for name, label in ABLATION_ROWS.items())]:
        current = _current_runs(rows, recipe)
        figures = (" | ".join(_figures(current, column) for column in ABLATION_SPLITS) if current
                   else " | ".join(["not run"] * len(ABLATION_SPLITS)))
        lines.append(f"| {label} | `{command}` | {' / '.join(row['seed'] for row in current) or '—'} | {figures} |")
        if recipe == "make reference-unseen":
            paper = dict(zip(SPLIT_COLUMNS, full.paper_figures))
            lines.append(f"| *{full.paper}* | | | {' | '.join(paper[column] for column in ABLATION_SPLITS)} |")
    return "\n".join(lines)


def marked_table(text: str, begin: str = BEGIN, end: str = END) -> str:
    """The table as it stands between a page's markers."""
    if begin not in text or end not in text:
        raise UsageError(f"no table between {begin!r} and {end!r}")
    return text.split(begin, 1)[1].split(end, 1)[0].strip("\n")


def readme_table(readme: str) -> str:
    """The results table as it stands between the README's markers."""
    return marked_table(readme)


def write_table(path: Path, rows: list[dict[str, str]], ablations: bool = False) -> bool:
    """Replace the page's results table (`ablations`: its ablation table) with the one built from `rows`; True when
    it changed."""
    begin, end, table = (ABLATION_BEGIN, ABLATION_END, ablation_table) if ablations else (BEGIN, END, results_table)
    text = path.read_text()
    old, new = marked_table(text, begin, end), table(rows)
    if old != new:
        before, rest = text.split(begin, 1)
        path.write_text(f"{before}{begin}\n{new}\n{end}{rest.split(end, 1)[1]}")
    return old != new


def _git_commit() -> str:
    done = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return done.stdout.strip() if done.returncode == 0 else ""


def _machine() -> str:
    model = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        names = [line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines()
                 if line.startswith("model name")]
        model = names[0] if names else model
    return f"{os.cpu_count()}-core {model}"


def run_row(summary: dict, note: str, recipe: str | None = None, status: str = "completed") -> dict[str, str]:
    """A table row from a reference run's `reference_run.json`."""
    config = summary["configuration"]
    splits = summary["results"]["splits"]
    if recipe is None:
        recipe = ("make reference-act" if config.get("policy") == "act" else "make reference-suite"
                  if config.get("suite") else f"ablation {config['ablation']}" if config.get("ablation")
                  else "make reference-tower-unseen" if config.get("unseen") and config.get("task") == "tower"
                  else "make reference-unseen" if config.get("unseen")
                  else "make reference-tower" if config.get("task") == "tower" else "make reference")
    # The command as it was typed; a summary written before it was recorded gives the options that name the recipe.
    command = [summary.get("command") or "python -m demo_factory.tools.reference_run"]
    if "command" not in summary:
        command += [f"--suite {config['suite']}"] if config.get("suite") else []
        command += [f"--task {config['task']}"] if config.get("task", "push_buttons") != "push_buttons" else []
        command += ["--unseen"] if config.get("unseen") else []
        command += [f"--policy {config['policy']}"] if config.get("policy", "hiveformer") != "hiveformer" else []
        command += [f"--ablation {config['ablation']}"] if config.get("ablation") else []
        command += [f"--perturb {config['perturb']}"] if config.get("perturb") else []
        command += ["--robustness"] if config.get("robustness") else []
        command += [f"--seed {config['seed']}", *(f"--train-arg={arg}" for arg in config.get("train_arg") or [])]
    step = summary.get("train_step", {}).get("updt_s")
    return {
        "date": datetime.date.today().isoformat(), "commit": _git_commit(), "command": " ".join(command),
        "recipe": recipe, "task": config.get("suite") or config.get("task", "push_buttons"), "seed": str(config["seed"]),
        "steps": str(config["steps"]), "s_per_step": f"{step:.3f}" if step else "",
        "wall_min": f"{sum(summary['stage_seconds'].values()) / 60:.0f}",
        **{column: f"{100 * splits[split]['success_rate']:.1f}" if split in splits else ""
           for column, split in SPLIT_COLUMNS.items()},
        "machine": _machine(), "status": status, "current": "0", "note": note,
    }


def add_run(path: Path, row: dict[str, str]) -> None:
    """Insert `row` first (the table is newest first), keeping every other row as it was."""
    rows = read_runs(path) if path.exists() else []
    with path.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows([row, *rows])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m demo_factory.tools.runs", description=__doc__.split("\n\n")[0],
                                     epilog=__doc__.split("\n\n")[2], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=Path, default=RUNS, help=f"the table (default: {RUNS.relative_to(ROOT)})")
    commands = parser.add_subparsers(dest="command", required=True)
    add = commands.add_parser("add", help="append a reference run from its reference_run.json")
    add.add_argument("summary", type=Path, help="OUT/reference_run.json of a finished reference run")
    add.add_argument("--note", required=True, help="what the run varied or showed, in one phrase")
    add.add_argument("--recipe", choices=[*RECIPES, *ABLATION_RECIPES, "experiment"],
                     help="default: the reference command the run's options name; `experiment` for variants")
    table = commands.add_parser("table", help="print the README's results table, built from the current runs")
    table.add_argument("--write", type=Path, metavar="README", help="replace the table between the README's markers")
    ablations = commands.add_parser("ablations", help="print the paper's ablation rows, built from the "
                                    "current runs of `make reference-unseen` and `reference_run --unseen --ablation`")
    ablations.add_argument("--write", type=Path, metavar="PAGE", help="replace the table between the page's markers")
    args = parser.parse_args(argv)
    try:
        if args.command == "add":
            if not args.summary.is_file():
                raise UsageError(f"no reference run summary at {args.summary}: give OUT/reference_run.json")
            try:
                summary = json.loads(args.summary.read_text())
                row = run_row(summary, args.note, args.recipe)
            except (json.JSONDecodeError, KeyError, TypeError) as error:
                raise UsageError(f"{args.summary} is not a reference run summary ({error!r})") from None
            add_run(args.runs, row)
            print(f"added to {args.runs}: {row['command']} ({row['date']}, seen {row['seen']} %)")
        elif args.write:
            changed = write_table(args.write, read_runs(args.runs), args.command == "ablations")
            print(f"{args.write}: {'ablation' if args.command == 'ablations' else 'results'} table "
                  f"{'rewritten' if changed else 'already up to date'}")
        else:
            print((ablation_table if args.command == "ablations" else results_table)(read_runs(args.runs)))
    except UsageError as error:
        print(f"error: {error}", file=sys.stderr)
        return error.exit_code
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
