"""Episode recording to MCAP, and reading it back as typed episodes."""

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
