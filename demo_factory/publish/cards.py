"""``make cards``: regenerate the committed cards of the standard datasets in ``dataset_cards/``.

Each standard dataset is generated small (a few episodes per split at the default image size) in a
temporary folder, with the same relative paths a user would type (``data/raw/<name>``,
``data/lerobot/<name>``), converted, and only its card and contact sheet are kept:
``dataset_cards/<name>/README.md`` and ``contact_sheet.png``. The ten-task suite gets one card per
task under ``dataset_cards/ten_tasks/<task>/`` and an index; it is skipped while
``demo_factory.tasks`` has no ``TEN_TASKS`` list.

    python -m demo_factory.publish.cards --out dataset_cards [--datasets push_buttons tower ten_tasks]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import sys
import tempfile
from pathlib import Path

from demo_factory.convert.card import CONTACT_SHEET

OWNER = "demo-factory"  # the Hub namespace the standard datasets' repo ids name
STANDARD = ("push_buttons", "tower", "ten_tasks")
SUITE = "ten_tasks"
MAX_SHEET_BYTES = 100_000


def suite_tasks() -> list[str] | None:
    """The tasks of the ten-task suite, once ``demo_factory.tasks`` defines ``TEN_TASKS``."""
    import demo_factory.tasks

    tasks = getattr(demo_factory.tasks, "TEN_TASKS", None)
    return list(tasks) if tasks else None


@contextlib.contextmanager
def _inside(folder: Path):
    before = Path.cwd()
    os.chdir(folder)
    try:
        yield
    finally:
        os.chdir(before)


def make_card(task: str, name: str, out: Path, train_episodes: int, test_episodes: int, seed: int = 0) -> Path:
    """Generate, convert and keep the card of one task as dataset ``name``: ``out/README.md`` + contact sheet."""
    from demo_factory.cli import main

    with tempfile.TemporaryDirectory(prefix=f"cards-{name}-") as tmp, _inside(Path(tmp)):
        raw, converted = Path("data/raw") / name, Path("data/lerobot") / name
        for split, episodes in (("train", train_episodes), ("test", test_episodes)):
            code = main(["generate", "--task", task, "--split", split, "--episodes", str(episodes), "--seed", str(seed),
                         "--out", str(raw / split)])
            if code != 0:
                raise RuntimeError(f"generating {task}/{split} for the {name} card failed (exit code {code})")
        code = main(["convert", "--in", str(raw), "--out", str(converted), "--repo-id", f"{OWNER}/{name}", "--no-progress"])
        if code != 0:
            raise RuntimeError(f"converting {name} for its card failed (exit code {code})")
        out.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(converted / "README.md", out / "README.md")
        shutil.copyfile(converted / CONTACT_SHEET, out / CONTACT_SHEET)
    size = (out / CONTACT_SHEET).stat().st_size
    if size > MAX_SHEET_BYTES:
        print(f"warning: {out / CONTACT_SHEET} is {size} bytes (> {MAX_SHEET_BYTES})", file=sys.stderr)
    return out / "README.md"


def suite_index(tasks: list[str]) -> str:
    """The ten-task suite's index card: one dataset (and card) per task."""
    rows = "\n".join(f"| `{t}` | [card]({t}/README.md) | `{OWNER}/{SUITE}_{t}_<split>` |" for t in tasks)
    return f"""---
license: apache-2.0
task_categories:
- robotics
tags:
- LeRobot
- demo-factory
- simulation
- language-conditioned
pretty_name: "demo-factory ten-task suite"
---

# {OWNER}/{SUITE}: the ten-task suite

Expert demonstrations of {len(tasks)} tabletop tasks made by demo-factory (PyBullet, Franka Panda, OMPL), one
LeRobot v3.0 dataset per task and split, as in the HiveFormer multi-task benchmark. Each task's card
describes its variations, splits, instruction sources, features, generation statistics, how to load,
train, evaluate and regenerate it, the licence (Apache-2.0), limitations and citations.

| task | card | repo ids |
|---|---|---|
{rows}
"""


def make_cards(out: Path, datasets: list[str], train_episodes: int, test_episodes: int) -> list[Path]:
    written = []
    for name in datasets:
        if name != SUITE:
            written.append(make_card(name, name, out / name, train_episodes, test_episodes))
            continue
        tasks = suite_tasks()
        if tasks is None:
            print(f"{SUITE}: skipped, demo_factory.tasks defines no TEN_TASKS yet", file=sys.stderr)
            continue
        for task in tasks:
            written.append(make_card(task, f"{SUITE}_{task}", out / SUITE / task, train_episodes, test_episodes))
        (out / SUITE).mkdir(parents=True, exist_ok=True)
        (out / SUITE / "README.md").write_text(suite_index(tasks), encoding="utf-8")
        written.append(out / SUITE / "README.md")
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m demo_factory.publish.cards", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("dataset_cards"), help="folder of the committed cards")
    parser.add_argument("--datasets", nargs="+", choices=STANDARD, default=list(STANDARD))
    parser.add_argument("--train-episodes", type=int, default=4, help="train-variation episodes per task (default 4)")
    parser.add_argument("--test-episodes", type=int, default=3, help="test-variation episodes per task (default 3)")
    args = parser.parse_args(argv)
    out = args.out.resolve()
    for path in make_cards(out, args.datasets, args.train_episodes, args.test_episodes):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
