"""A human-readable summary of one episode recording (``demo-factory inspect``)."""

from __future__ import annotations

from pathlib import Path

from mcap.reader import make_reader

from demo_factory.record.episode import Episode


def topic_counts(path: Path) -> dict[str, tuple[str, int]]:
    """``{topic: (schema name, message count)}`` from the file's summary section."""
    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    if summary is None or summary.statistics is None:
        return {}
    counts = summary.statistics.channel_message_counts
    return {
        channel.topic: (summary.schemas[channel.schema_id].name if channel.schema_id in summary.schemas else "", counts.get(cid, 0))
        for cid, channel in sorted(summary.channels.items(), key=lambda item: item[1].topic)
    }


def describe(path: Path, episode: Episode) -> str:
    info = episode.info
    duration = episode.frames[-1].time_ns / 1e9 if episode.frames else 0.0
    lines = [
        f"{path}",
        f"  task {info.task}, split {info.split}, variation {info.variation_id} ({', '.join(info.variation)}), seed {info.episode_seed}",
        f"  instruction: {info.instruction!r}",
        f"  success: {info.success}; {len(episode.keyframes)} keyframes, {len(episode.dense_frames())} dense frames "
        f"({info.dense_fps:g} fps), {duration:.2f} s simulated",
        f"  cameras: {', '.join(info.cameras)} at {info.image_size[0]}x{info.image_size[1]}",
        *([f"  perturbations: {', '.join(info.perturbations)}"] if info.perturbations else []),
        f"  planner attempts: {len(info.planner_attempts)} over "
        f"{len({a.keyframe_index for a in info.planner_attempts})} planned transitions",
        f"  format version {info.format_version}; " + ", ".join(f"{k} {v}" for k, v in sorted(info.versions.items())),
        "  topics:",
    ]
    for topic, (schema_name, count) in topic_counts(path).items():
        lines.append(f"    {topic:<36} {schema_name:<32} {count:>5} messages")
    lines.append("  keyframes:")
    for kf in episode.keyframes:
        x, y, z = kf.target_pose[:3]
        lines.append(f"    {kf.index:>3}  t={kf.time_ns / 1e9:6.2f} s  {kf.motion:<9} target ({x:+.3f}, {y:+.3f}, {z:+.3f})  "
                     f"gripper {'open' if kf.gripper_open else 'closed'}")
    return "\n".join(lines)
