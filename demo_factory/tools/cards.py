"""``make cards``: regenerate the committed cards of the standard datasets in ``dataset_cards/``.

Each standard dataset is generated small (a few episodes per split at the default image size) in a
temporary folder, with the same relative paths a user would type (``data/raw/<name>``,
``data/lerobot/<name>``), converted, and only its card and contact sheet are kept:
``dataset_cards/<name>/README.md`` and ``contact_sheet.png``. The ten-task suite and the categories
suite (one task per category of the HiveFormer paper) are each one multi-task dataset
(``generate --suite NAME``), so each has one card like the others.

    python -m demo_factory.tools.cards --out dataset_cards [--datasets push_buttons tower ten_tasks categories]   (or `make cards`)
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import sys
import tempfile
from pathlib import Path

from demo_factory.convert import ConvertOptions, convert
from demo_factory.convert.card import CONTACT_SHEET
from demo_factory.generate import GenerationJob, run_job
from demo_factory.suites import SUITES, suite_tasks

OWNER = "demo-factory"  # the Hub namespace the standard datasets' repo ids name
STANDARD = ("push_buttons", "tower", "ten_tasks", "categories")
MAX_SHEET_BYTES = 100_000


@contextlib.contextmanager
def _inside(folder: Path):
    before = Path.cwd()
    os.chdir(folder)
    try:
        yield
    finally:
        os.chdir(before)


def make_card(name: str, out: Path, train_episodes: int, test_episodes: int, seed: int = 0) -> Path:
    """Generate, convert and keep the card of standard dataset ``name`` (a task, or a suite as one
    multi-task dataset): ``out/README.md`` + contact sheet."""
    with tempfile.TemporaryDirectory(prefix=f"cards-{name}-") as tmp, _inside(Path(tmp)):
        raw, converted = Path("data/raw") / name, Path("data/lerobot") / name
        for split, episodes in (("train", train_episodes), ("test", test_episodes)):
            folder = raw / split
            for task in suite_tasks(name) if name in SUITES else [name]:
                job = GenerationJob(task=task, split=split, episodes=episodes, seed=seed,
                                    out=folder / task if name in SUITES else folder, workers=os.cpu_count() or 1)
                if run_job(job)["kept"] == 0:
                    raise RuntimeError(f"generating {task}/{split} for the card of {name} kept no episode")
        convert(ConvertOptions(inputs=[raw], out=converted, repo_id=f"{OWNER}/{name}", progress=False), log=lambda _: None)
        out.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(converted / "README.md", out / "README.md")
        shutil.copyfile(converted / CONTACT_SHEET, out / CONTACT_SHEET)
    size = (out / CONTACT_SHEET).stat().st_size
    if size > MAX_SHEET_BYTES:
        print(f"warning: {out / CONTACT_SHEET} is {size} bytes (> {MAX_SHEET_BYTES})", file=sys.stderr)
    return out / "README.md"


def make_cards(out: Path, datasets: list[str], train_episodes: int, test_episodes: int) -> list[Path]:
    return [make_card(name, out / name, train_episodes, test_episodes) for name in datasets]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m demo_factory.tools.cards", description=__doc__.split("\n\n")[0])
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
