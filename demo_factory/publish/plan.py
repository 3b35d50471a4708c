"""What publishing a converted dataset uploads: one Hub repo per split, its files and its card (local only).

A converted folder (``demo-factory convert``) holds one LeRobot v3.0 dataset per split, ``README.md``
(the dataset card) and ``contact_sheet.png``. Split ``s`` goes to repo ``<repo_id>_<s>`` in LeRobot's
standard layout (the split folder's own files at the repo root), with the card rewritten for that
repo (``card.hub_card``) and the contact sheet beside it.
"""

from __future__ import annotations

import json
import shlex
from dataclasses import dataclass
from pathlib import Path

from demo_factory.convert.card import CONTACT_SHEET, hub_card
from demo_factory.convert.converter import ConvertError, read_dataset_provenance
from demo_factory.convert.splits import DATASET_SPLITS
from demo_factory.errors import UsageError

CARD = "README.md"
LEROBOT_IGNORED = ("images",)  # top-level folders LeRobotDataset.push_to_hub never uploads
EXIT_USAGE = 2
EXIT_HUB = 1


class PublishError(UsageError):
    """A problem the user can fix, reported as one line; ``exit_code`` 2 for usage, 1 for the Hub."""

    def __init__(self, message: str, exit_code: int = EXIT_USAGE):
        super().__init__(message)
        self.exit_code = exit_code


@dataclass(frozen=True)
class LocalFile:
    path: str  # posix path inside the repo
    source: Path
    size: int


@dataclass
class SplitUpload:
    """One split: the repo it goes to, its dataset files and its card files."""

    split: str
    repo_id: str
    root: Path
    data_files: list[LocalFile]
    card: str  # README.md text for this repo
    contact_sheet: Path | None

    def card_files(self) -> dict[str, bytes]:
        """Repo path → content of the card and its picture."""
        files = {CARD: self.card.encode("utf-8")}
        if self.contact_sheet is not None:
            files[CONTACT_SHEET] = self.contact_sheet.read_bytes()
        return files

    @property
    def size(self) -> int:
        return sum(f.size for f in self.data_files) + sum(len(b) for b in self.card_files().values())


@dataclass
class PublishPlan:
    dataset: Path
    repo_id: str
    private: bool
    splits: list[SplitUpload]

    @property
    def size(self) -> int:
        return sum(s.size for s in self.splits)


def check_repo_id(repo_id: str, splits: list[str]) -> None:
    """``owner/name`` whose per-split ids ``owner/name_<split>`` the Hub accepts."""
    from huggingface_hub.utils import HFValidationError, validate_repo_id

    owner, _, name = repo_id.partition("/")
    if not owner or not name or "/" in name:
        raise PublishError(f"--repo-id {repo_id!r} is not a Hub repo id; expected owner/name "
                           "(letters, digits, '-', '_', '.'), e.g. me/push_buttons")
    for split in splits:
        try:
            validate_repo_id(f"{repo_id}_{split}")
        except HFValidationError:
            raise PublishError(f"--repo-id {repo_id!r} is not a Hub repo id once suffixed with _{split}; expected "
                               "owner/name of letters, digits, '-', '_', '.' (no '--' or '..', at most 96 characters)") from None


def find_splits(dataset: Path) -> dict[str, Path]:
    """The split folders of a converted dataset (folders holding ``meta/info.json``), converter order first."""
    if not dataset.is_dir():
        raise PublishError(f"--dataset {dataset} is not a folder; expected the output folder of demo-factory convert")
    found = {p.name: p for p in sorted(dataset.iterdir()) if (p / "meta" / "info.json").is_file()}
    if not found:
        raise PublishError(f"--dataset {dataset} holds no split folders (folders with meta/info.json); "
                           "expected the output folder of demo-factory convert")
    for name, root in found.items():
        try:
            info, _ = read_dataset_provenance(root)
        except ConvertError as error:
            raise PublishError(str(error)) from None
        if info.get("codebase_version") != "v3.0":
            raise PublishError(f"{root} is a LeRobot dataset of format {info.get('codebase_version')!r}; "
                               "only v3.0 (LeRobot 0.4) is published")
    order = list(DATASET_SPLITS)
    return {n: found[n] for n in sorted(found, key=lambda n: (order.index(n) if n in order else len(order), n))}


def dataset_files(root: Path) -> list[LocalFile]:
    """The files LeRobot's ``push_to_hub`` uploads from a split folder, with their repo paths."""
    files = []
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        relative = path.relative_to(root)
        if relative.parts[0] in LEROBOT_IGNORED or any(part.startswith(".") for part in relative.parts):
            continue
        files.append(LocalFile(relative.as_posix(), path, path.stat().st_size))
    return files


def publish_command(dataset: Path, repo_id: str, private: bool) -> str:
    return " ".join(["demo-factory publish", "--dataset", shlex.quote(str(dataset)), "--repo-id", repo_id,
                     *(["--private"] if private else [])])


def plan_publish(dataset: Path, repo_id: str, private: bool = False) -> PublishPlan:
    """Every repo, file and card a publish would upload (reads local files only)."""
    splits = find_splits(dataset)
    check_repo_id(repo_id, list(splits))
    card_path = dataset / CARD
    if not card_path.is_file():
        raise PublishError(f"--dataset {dataset} has no dataset card {CARD}; re-run demo-factory convert")
    card_text = card_path.read_text(encoding="utf-8")
    sheet = dataset / CONTACT_SHEET
    uploads = []
    for split, root in splits.items():
        info = json.loads((root / "meta" / "info.json").read_text(encoding="utf-8"))
        cameras = list(info.get("cameras", []))
        shape = info["features"][f"observation.images.{cameras[0]}"]["shape"] if cameras else [0, 0, 3]
        try:
            card = hub_card(card_text, repo_id, split, list(splits), cameras, (shape[0], shape[1]),
                            publish_command(dataset, repo_id, private))
        except ValueError as exc:
            raise PublishError(f"{card_path}: {exc}") from None
        uploads.append(SplitUpload(split, f"{repo_id}_{split}", root, dataset_files(root), card,
                                   sheet if sheet.is_file() else None))
    return PublishPlan(dataset, repo_id, private, uploads)


def human_size(size: int) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if size < 1000 or unit == "GB":
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1000
    raise AssertionError


def describe_plan(plan: PublishPlan) -> str:
    """The dry-run listing: each repo, each file with its size, the total, then the first repo's card."""
    lines = [f"dry run: would publish {plan.dataset} as {len(plan.splits)} {'private' if plan.private else 'public'} "
             "Hugging Face dataset repos (nothing is sent)", ""]
    for upload in plan.splits:
        lines.append(f"{upload.repo_id}  (split {upload.split}, {human_size(upload.size)}, tag v3.0)")
        for f in upload.data_files:
            lines.append(f"  {human_size(f.size):>10}  {f.path}")
        for name, content in upload.card_files().items():
            lines.append(f"  {human_size(len(content)):>10}  {name}  (card)")
    files = sum(len(u.data_files) + len(u.card_files()) for u in plan.splits)
    lines += ["", f"total: {files} files, {human_size(plan.size)} in {len(plan.splits)} repos", ""]
    first = plan.splits[0]
    lines += [f"card of {first.repo_id} (the other repos' cards differ only in their title, links and commands):",
              "", first.card]
    return "\n".join(lines)
