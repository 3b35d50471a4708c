"""Reads an episode recording back as a typed ``Episode`` (the converter's and inspector's input)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
from mcap.reader import NonSeekingReader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory
from scipy.spatial.transform import Rotation

from demo_factory.errors import UsageError
from demo_factory.record import schema
from demo_factory.record.episode import (
    FORMAT_VERSION,
    OLDEST_READABLE_FORMAT,
    CameraObservation,
    Episode,
    EpisodeInfo,
    Frame,
    Keyframe,
    PlannerAttempt,
    RobotState,
)


class RecordingError(UsageError):
    """A recording that cannot be read: truncated, corrupt, foreign, or from a future format."""


def iter_episode_paths(folder: str | os.PathLike) -> list[Path]:
    """The complete episode recordings in a folder, sorted by name (partial files are ignored)."""
    return sorted(p for p in Path(folder).glob("*.mcap") if not p.name.startswith("."))


def read_episode(path: str | os.PathLike, images: bool = True) -> Episode:
    """Read a whole episode; raises ``RecordingError`` naming the file and the problem.

    With ``images=False`` the camera streams are checked for presence but not decoded (frames have
    no ``cameras``): a fast read of everything else, e.g. to plan a conversion.
    """
    path = Path(path)
    try:
        messages = list(_iter_messages(path, images))
    except RecordingError:
        raise
    except Exception as exc:  # mcap raises many types for damaged files; all mean the same here
        raise RecordingError(f"{path}: corrupt or truncated recording ({type(exc).__name__}: {exc})") from exc
    return _assemble(path, messages, images)


def _iter_messages(path: Path, images: bool = True) -> Iterator[tuple[str, int, object]]:
    with open(path, "rb") as stream:
        profile = NonSeekingReader(stream).get_header().profile  # a non-seeking reader answers one query
        if profile != schema.PROFILE:
            raise RecordingError(f"{path}: not a demo-factory recording (MCAP profile {profile!r})")
        stream.seek(0)
        reader = NonSeekingReader(
            stream, validate_crcs=True, decoder_factories=[ProtobufDecoderFactory(), schema.JsonDecoderFactory()]
        )
        if images:
            for _schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
                yield channel.topic, message.log_time, decoded
            return
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            if channel.message_encoding == "json":
                yield channel.topic, message.log_time, json.loads(message.data)
            elif channel.topic.startswith("/cameras/"):
                yield channel.topic, message.log_time, None  # present, not decoded


def _assemble(path: Path, messages: list[tuple[str, int, object]], images: bool = True) -> Episode:
    info_payload = result = None
    keyframes: list[Keyframe] = []
    states: dict[int, dict] = {}
    cameras: dict[int, dict[str, dict]] = {}
    for topic, t, msg in messages:
        if topic == schema.INFO_TOPIC:
            info_payload = msg
        elif topic == schema.RESULT_TOPIC:
            result = msg
        elif topic == schema.KEYFRAME_TOPIC:
            keyframes.append(Keyframe(
                index=msg["index"], time_ns=t, target_pose=np.array(msg["target_pose"]),
                gripper_open=msg["gripper_open"], reached_pose=np.array(msg["reached_pose"]), motion=msg["motion"],
            ))
        elif topic == schema.STATE_TOPIC:
            states[t] = msg
        elif topic == schema.TF_TOPIC:
            if msg.child_frame_id != schema.GRIPPER_FRAME:
                camera = msg.child_frame_id.removesuffix("_optical")
                cameras.setdefault(t, {}).setdefault(camera, {})["tf"] = msg
        elif topic.startswith("/cameras/"):
            _, _, camera, stream = topic.split("/")
            cameras.setdefault(t, {}).setdefault(camera, {})[stream] = msg
    if info_payload is None:
        raise RecordingError(f"{path}: no {schema.INFO_TOPIC} message; not an episode recording")
    found = info_payload.get("format_version")
    if not isinstance(found, int) or found > FORMAT_VERSION:
        raise RecordingError(
            f"{path}: recording format version {found} is newer than this demo-factory reads "
            f"(up to {FORMAT_VERSION}); upgrade demo-factory"
        )
    if found < OLDEST_READABLE_FORMAT:
        raise RecordingError(
            f"{path}: recording format version {found} numbers variations the old way (before the HiveFormer "
            f"paper's ids); regenerate it with this demo-factory (format version {FORMAT_VERSION})"
        )
    if result is None:
        raise RecordingError(f"{path}: truncated recording (no {schema.RESULT_TOPIC} message)")
    info = EpisodeInfo(
        **{**info_payload, "image_size": tuple(info_payload["image_size"])},
        success=result["success"],
        planner_attempts=[PlannerAttempt(**a) for a in result["planner_attempts"]],
        versions=result["versions"],
    )
    frames = []
    for t in sorted(states):
        state = states[t]
        streams = cameras.get(t, {})
        expected = {"rgb", "depth", "segmentation", "calibration", "tf"} if images else {"rgb", "depth", "segmentation", "calibration"}
        missing = [c for c in info.cameras if set(streams.get(c, {})) != expected]
        if missing:
            raise RecordingError(f"{path}: frame at {t} ns lacks camera streams for {', '.join(missing)}")
        frames.append(Frame(
            time_ns=t,
            is_keyframe=state["is_keyframe"],
            is_dense=state["is_dense"],
            keyframe_index=state["keyframe_index"],
            robot=RobotState(
                joint_positions=np.array(state["joint_positions"]),
                gripper_pose=np.array(state["gripper_pose"]),
                gripper_open=state["gripper_open"],
                finger_width=state["finger_width"],
            ),
            cameras={c: _camera_observation(streams[c]) for c in info.cameras} if images else {},
        ))
    keyframes.sort(key=lambda k: k.index)
    return Episode(info=info, keyframes=keyframes, frames=frames)


def _camera_observation(streams: dict) -> CameraObservation:
    bgr = cv2.imdecode(np.frombuffer(streams["rgb"].data, np.uint8), cv2.IMREAD_COLOR)
    depth_msg, seg_msg, calib, tf = streams["depth"], streams["segmentation"], streams["calibration"], streams["tf"]
    shape = (depth_msg.height, depth_msg.width)
    depth_mm = np.frombuffer(depth_msg.data, np.uint16).reshape(shape)
    seg = np.frombuffer(seg_msg.data, np.uint16).reshape(shape).astype(np.int32) - 1
    extrinsics = np.eye(4)
    extrinsics[:3, :3] = Rotation.from_quat([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w]).as_matrix()
    extrinsics[:3, 3] = [tf.translation.x, tf.translation.y, tf.translation.z]
    k = calib.K
    return CameraObservation(
        rgb=cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB),
        depth=depth_mm.astype(np.float32) / 1000.0,
        segmentation=seg,
        intrinsics=np.array([k[0], k[4], k[2], k[5]]),
        extrinsics=extrinsics,
    )
