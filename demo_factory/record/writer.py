"""Writes one episode to one MCAP file, deterministically (log times from the simulation clock)."""

from __future__ import annotations

import dataclasses
import functools
import os
from importlib import metadata
from pathlib import Path

import cv2
import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import register_schema
from scipy.spatial.transform import Rotation

from demo_factory.record import schema
from demo_factory.record.episode import EpisodeInfo, Frame, Keyframe, PlannerAttempt

MAX_DEPTH_MM = np.iinfo(np.uint16).max
VERSIONED_PACKAGES = ("demo_factory", "pybullet", "ompl", "mcap", "numpy")  # recorded with every episode


def library_versions() -> dict[str, str]:
    """The versions of the packages that decide an episode's content, for the recording's result."""
    return dict(_installed_versions())


@functools.cache
def _installed_versions() -> tuple[tuple[str, str], ...]:
    # Read once per process: parsing the packages' metadata cost ~5 ms an episode.
    return tuple((name, metadata.version(name)) for name in VERSIONED_PACKAGES)


def _stamp(time_ns: int) -> Timestamp:
    return Timestamp(seconds=time_ns // 1_000_000_000, nanos=time_ns % 1_000_000_000)


def _rounded(values, digits: int = 7) -> list[float]:
    """Floats as JSON-friendly rounded values (0.1 µm / 1e-7 rad), identical across runs."""
    return [round(float(v), digits) for v in np.asarray(values).ravel()]


def depth_to_mm(depth_m: np.ndarray) -> np.ndarray:
    """Metric depth → uint16 millimetres (0 stays 0 = no hit)."""
    return np.clip(np.rint(depth_m * 1000.0), 0, MAX_DEPTH_MM).astype(np.uint16)


class EpisodeWriter:
    """Streams an episode into ``path``; the file appears under its name only on ``close(...)``.

    Until then it is written to a hidden ``.partial`` name in the same folder, so an interrupted
    run never leaves a file that looks complete. ``abort()`` removes the partial file.
    """

    def __init__(self, path: str | os.PathLike, info: EpisodeInfo):
        self.path = Path(path)
        self.partial_path = self.path.with_name(f".{self.path.name}.partial")
        self.info = info
        self._file = open(self.partial_path, "wb")
        self._writer = Writer(self._file, chunk_size=4 * 1024 * 1024, compression=CompressionType.ZSTD)
        self._writer.start(profile=schema.PROFILE, library="demo_factory")
        self._channels: dict[str, int] = {}
        self._sequence = 0
        self._write_json(schema.INFO_TOPIC, 0, self._info_payload())
        self._write_proto(
            schema.INSTRUCTION_TOPIC, 0, Log(timestamp=_stamp(0), level=Log.INFO, message=info.instruction, name="instruction")
        )

    # -- channels -------------------------------------------------------------------------
    def _channel(self, topic: str, message=None) -> int:
        if topic not in self._channels:
            if message is None:
                schema_id = self._writer.register_schema(
                    name=schema.JSON_SCHEMAS[topic]["title"],
                    encoding=SchemaEncoding.JSONSchema,
                    data=schema.encode_json(schema.JSON_SCHEMAS[topic]),
                )
                encoding = "json"
            else:
                schema_id = register_schema(self._writer, type(message))
                encoding = MessageEncoding.Protobuf
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=encoding, schema_id=schema_id
            )
        return self._channels[topic]

    def _add(self, channel_id: int, time_ns: int, data: bytes) -> None:
        self._writer.add_message(
            channel_id=channel_id, log_time=time_ns, publish_time=time_ns, data=data, sequence=self._sequence
        )
        self._sequence += 1

    def _write_json(self, topic: str, time_ns: int, payload: dict) -> None:
        self._add(self._channel(topic), time_ns, schema.encode_json(payload))

    def _write_proto(self, topic: str, time_ns: int, message) -> None:
        self._add(self._channel(topic, message), time_ns, message.SerializeToString(deterministic=True))

    def _info_payload(self) -> dict:
        info = dataclasses.asdict(self.info)
        for key in ("success", "planner_attempts", "versions"):
            info.pop(key)
        return info

    # -- content --------------------------------------------------------------------------
    def write_frame(self, frame: Frame) -> None:
        """All cameras, transforms and the robot state of one frame, at ``frame.time_ns``."""
        t = frame.time_ns
        stamp = _stamp(t)
        for name, cam in frame.cameras.items():
            frame_id = schema.optical_frame(name)
            height, width = cam.rgb.shape[:2]
            ok, png = cv2.imencode(".png", cv2.cvtColor(cam.rgb, cv2.COLOR_RGB2BGR))
            assert ok, "PNG encoding failed"
            self._write_proto(
                schema.camera_topic(name, "rgb"), t,
                CompressedImage(timestamp=stamp, frame_id=frame_id, data=png.tobytes(), format="png"),
            )
            depth = depth_to_mm(cam.depth)
            self._write_proto(
                schema.camera_topic(name, "depth"), t,
                RawImage(timestamp=stamp, frame_id=frame_id, width=width, height=height,
                         encoding=schema.DEPTH_ENCODING, step=2 * width, data=depth.tobytes()),
            )
            seg = (cam.segmentation.astype(np.int64) + 1).clip(0, MAX_DEPTH_MM).astype(np.uint16)
            self._write_proto(
                schema.camera_topic(name, "segmentation"), t,
                RawImage(timestamp=stamp, frame_id=frame_id, width=width, height=height,
                         encoding=schema.SEGMENTATION_ENCODING, step=2 * width, data=seg.tobytes()),
            )
            fx, fy, cx, cy = (float(v) for v in cam.intrinsics)
            self._write_proto(
                schema.camera_topic(name, "calibration"), t,
                CameraCalibration(
                    timestamp=stamp, frame_id=frame_id, width=width, height=height,
                    distortion_model="plumb_bob", D=[0.0] * 5,
                    K=[fx, 0, cx, 0, fy, cy, 0, 0, 1], R=[1, 0, 0, 0, 1, 0, 0, 0, 1],
                    P=[fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0],
                ),
            )
            self._write_transform(t, frame_id, cam.extrinsics[:3, 3], _matrix_to_quat(cam.extrinsics[:3, :3]))
        robot = frame.robot
        self._write_transform(t, schema.GRIPPER_FRAME, robot.gripper_pose[:3], robot.gripper_pose[3:])
        self._write_json(schema.STATE_TOPIC, t, {
            "joint_positions": _rounded(robot.joint_positions),
            "gripper_pose": _rounded(robot.gripper_pose),
            "gripper_open": float(robot.gripper_open),
            "finger_width": round(float(robot.finger_width), 7),
            "is_keyframe": frame.is_keyframe,
            "is_dense": frame.is_dense,
            "keyframe_index": frame.keyframe_index,
        })

    def _write_transform(self, time_ns: int, child: str, translation, quaternion) -> None:
        tx, ty, tz = (float(v) for v in translation)
        qx, qy, qz, qw = (float(v) for v in quaternion)
        message = FrameTransform(timestamp=_stamp(time_ns), parent_frame_id=schema.WORLD_FRAME, child_frame_id=child)
        message.translation.x, message.translation.y, message.translation.z = tx, ty, tz
        message.rotation.x, message.rotation.y, message.rotation.z, message.rotation.w = qx, qy, qz, qw
        self._write_proto(schema.TF_TOPIC, time_ns, message)

    def write_keyframe(self, keyframe: Keyframe) -> None:
        """The marker of a reached keyframe, at the time it was reached."""
        self._write_json(schema.KEYFRAME_TOPIC, keyframe.time_ns, {
            "index": keyframe.index,
            "target_pose": _rounded(keyframe.target_pose),
            "reached_pose": _rounded(keyframe.reached_pose),
            "gripper_open": float(keyframe.gripper_open),
            "motion": keyframe.motion,
        })

    def close(self, end_time_ns: int, success: bool, planner_attempts: list[PlannerAttempt],
              versions: dict[str, str]) -> Path:
        """Write the result, finish the file and move it to its final name."""
        self._write_json(schema.RESULT_TOPIC, end_time_ns, {
            "success": bool(success),
            "planner_attempts": [dataclasses.asdict(a) for a in planner_attempts],
            "versions": dict(versions),
        })
        self._writer.finish()
        self._file.close()
        os.replace(self.partial_path, self.path)
        return self.path

    def abort(self) -> None:
        """Drop the partial file (failed or interrupted episode)."""
        if not self._file.closed:
            self._file.close()
        self.partial_path.unlink(missing_ok=True)


def _matrix_to_quat(rotation: np.ndarray) -> np.ndarray:
    return _quat_of_matrix_bytes(np.ascontiguousarray(rotation, dtype=np.float64).tobytes())


@functools.lru_cache(maxsize=64)
def _quat_of_matrix_bytes(rotation: bytes) -> np.ndarray:
    """Memoised on the exact matrix: a fixed camera's rotation repeats in every frame (~0.14 ms each)."""
    quaternion = Rotation.from_matrix(np.frombuffer(rotation).reshape(3, 3)).as_quat()
    quaternion.flags.writeable = False
    return quaternion
