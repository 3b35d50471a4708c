"""Recording: episodes to MCAP, and back as typed episodes.

Owns the recorded types (`episode`: frames, keyframes, planner attempts, episode info, the format version),
the MCAP topics and schemas (`schema`), the writer, the reader and ``demo-factory inspect``. Reads and writes
``.mcap`` files (a recording is written under a partial name and renamed when complete).
"""

from demo_factory.record import episode
from demo_factory.record.episode import *  # noqa: F403  (the recorded types: episode.__all__)
from demo_factory.record.reader import RecordingError, iter_episode_paths, read_episode
from demo_factory.record.writer import EpisodeWriter, library_versions

__all__ = [*episode.__all__, "EpisodeWriter", "RecordingError", "iter_episode_paths", "library_versions", "read_episode"]
