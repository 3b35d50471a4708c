"""MCAP topics and schemas of an episode recording: the one place reader and writer agree on.

Per frame (all messages of one frame share its log time, from the simulation clock):
- ``/cameras/<cam>/rgb``          foxglove.CompressedImage, PNG (lossless)
- ``/cameras/<cam>/depth``        foxglove.RawImage, 16UC1, millimetres (0 = no hit)
- ``/cameras/<cam>/segmentation`` foxglove.RawImage, 16UC1, PyBullet body id + 1 (0 = background)
- ``/cameras/<cam>/calibration``  foxglove.CameraCalibration (K, P; frame ``<cam>_optical``)
- ``/tf``                         foxglove.FrameTransform world → ``<cam>_optical`` and world → gripper
- ``/robot/state``                JSON: joints, gripper pose and opening, frame kind flags
Per episode:
- ``/episode/info``      JSON at time 0: task, split, variation, seed, instruction, cameras, format
- ``/instruction``       foxglove.Log at time 0 (shows the instruction in viewers' log panels)
- ``/keyframes``         JSON, one per keyframe when it is reached: index, target, gripper command
- ``/episode/result``    JSON at the end: success, planner attempt log, library versions
"""

from __future__ import annotations

import json

from mcap.decoder import DecoderFactory as McapDecoderFactory

PROFILE = "demo_factory"
WORLD_FRAME = "world"
GRIPPER_FRAME = "gripper"
DEPTH_ENCODING = "16UC1"
SEGMENTATION_ENCODING = "16UC1"

STATE_TOPIC = "/robot/state"
TF_TOPIC = "/tf"
INFO_TOPIC = "/episode/info"
RESULT_TOPIC = "/episode/result"
KEYFRAME_TOPIC = "/keyframes"
INSTRUCTION_TOPIC = "/instruction"


def camera_topic(camera: str, stream: str) -> str:
    """Topic of one camera stream: ``rgb``, ``depth``, ``segmentation`` or ``calibration``."""
    return f"/cameras/{camera}/{stream}"


def optical_frame(camera: str) -> str:
    return f"{camera}_optical"


# JSON schemas of the JSON channels (shown by viewers; kept loose where the content is a log).
_POSE = {"type": "array", "items": {"type": "number"}, "minItems": 7, "maxItems": 7}
JSON_SCHEMAS: dict[str, dict] = {
    STATE_TOPIC: {
        "title": "demo_factory.RobotState",
        "type": "object",
        "properties": {
            "joint_positions": {"type": "array", "items": {"type": "number"}},
            "gripper_pose": _POSE,
            "gripper_open": {"type": "number"},
            "finger_width": {"type": "number"},
            "is_keyframe": {"type": "boolean"},
            "is_dense": {"type": "boolean"},
            "keyframe_index": {"type": "integer"},
        },
    },
    KEYFRAME_TOPIC: {
        "title": "demo_factory.Keyframe",
        "type": "object",
        "properties": {
            "index": {"type": "integer"},
            "target_pose": _POSE,
            "reached_pose": _POSE,
            "gripper_open": {"type": "number"},
            "motion": {"type": "string"},
        },
    },
    INFO_TOPIC: {"title": "demo_factory.EpisodeInfo", "type": "object"},
    RESULT_TOPIC: {"title": "demo_factory.EpisodeResult", "type": "object"},
}


def encode_json(payload: dict) -> bytes:
    """Deterministic JSON bytes (sorted keys, compact), so recordings are byte-identical."""
    return json.dumps(payload, sort_keys=True, separators=(",", ":")).encode()


class JsonDecoderFactory(McapDecoderFactory):
    """Decodes the JSON channels for ``mcap``'s ``iter_decoded_messages``."""

    def decoder_for(self, message_encoding, schema):
        if message_encoding != "json":
            return None
        return lambda data: json.loads(data)
