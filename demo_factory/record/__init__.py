"""Recording: episodes to MCAP, and back as typed episodes.

Owns the recorded types (`episode`: frames, keyframes, planner attempts, episode info, the format version),
the MCAP topics and schemas (`schema`), the writer, the reader and ``demo-factory inspect``. Reads and writes
``.mcap`` files (a recording is written under a partial name and renamed when complete).
"""

from demo_factory.record.episode import (
    FORMAT_VERSION,
    CameraObservation,
    Episode,
    EpisodeInfo,
    Frame,
    Keyframe,
    PlannerAttempt,
    RobotState,
)
from demo_factory.record.reader import RecordingError, iter_episode_paths, read_episode
from demo_factory.record.writer import EpisodeWriter, library_versions

__all__ = [
    "library_versions",
    "FORMAT_VERSION",
    "CameraObservation",
    "Episode",
    "EpisodeInfo",
    "EpisodeWriter",
    "Frame",
    "Keyframe",
    "PlannerAttempt",
    "RecordingError",
    "RobotState",
    "iter_episode_paths",
    "read_episode",
]
