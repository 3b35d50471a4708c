"""What a conversion wrote (`ConvertResult`, one `SplitSummary` per split): the converter returns it, the
CLI summary and the dataset card read it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from demo_factory.convert.splits import SourceEpisode
from demo_factory.instructions import HumanInstruction
from demo_factory.instructions.human import HumanAssignment


@dataclass
class SplitSummary:
    name: str
    repo_id: str
    instruction_source: str
    episodes: int
    frames: int
    variations: int
    shortest_episode: int = 0  # frames of the split's shortest episode


@dataclass
class ConvertResult:
    out: Path
    repo_id: str
    task: str
    granularity: str
    fps: int
    cameras: list[str]
    image_size: tuple[int, int]
    splits: list[SplitSummary]
    skipped_splits: list[tuple[str, str]]  # (split, why)
    invalid: list[tuple[Path, str]]  # recordings left out with --skip-invalid
    sources: list[SourceEpisode]
    human_file: Path | None
    human_assignment: HumanAssignment | None
    human_rows: list[HumanInstruction] | None  # every row of the file for the task, blank ones included
    seconds: float
    frames_written: int
    command: str  # the convert command line that reproduces this output
    action_space: str | None = None  # dense exports: "joints" or "ee"
    recorded_fps: float = 0.0  # the recordings' dense rate (dense exports)
    generation_summaries: list[dict] = field(default_factory=list)  # from the input folders
    other_tasks: dict[str, int] = field(default_factory=dict)

    @property
    def multi_task(self) -> bool:
        """Whether the export holds several tasks' episodes."""
        return len({s.task for s in self.sources}) > 1

    @property
    def unseen_splits(self) -> bool:
        """Whether any split holds unseen (test) variations."""
        return any(s.name.startswith("test_unseen") for s in self.splits)
