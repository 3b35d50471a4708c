"""HiveFormer's inputs: a LeRobot batch turned into the model's units (`KeyframeObservations`), with the geometry
that rebuilds world point clouds from depth and calibration, the gripper's pixel, and the rescale augmentation.

Pure functions of tensors; `keyframe_maps` is PyTorch's definition of the pixel maps, which the compiled CPU loop
(`cpu_kernels.keyframe_maps`) computes bit for bit in one pass.
"""

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.utils.constants import OBS_STATE
from torch import Tensor

from .configuration_hiveformer import ENCODER_STRIDE, HiveformerConfig
from .dataset_format import CALIBRATION_PREFIX, DEPTH_PREFIX, GRIPPER_STATE_DIM, IMAGES_PREFIX

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
                          rescale: tuple[float, float] | None = None,
                          build_maps: Callable[..., tuple[Tensor, ...]] | None = None) -> KeyframeObservations:
    """Gather the policy's inputs from a LeRobot batch, with history (B, T, ...) or without (B, ...).

    The pixel maps (the stem's input, point cloud, validity, patch points) are built for the real steps and those
    where `keep` (B, T) is True, or for every step without `keep`. With `rescale` (min_scale, max_scale), each
    sample's maps are augmented as `random_rescale_sources` draws: colour and depth are resampled, and the point
    cloud and the mark are built from the resampled depth at the camera pixels it came from, the same values as
    resampling the camera's point cloud and mark. The maps are `build_maps`' (default: `keyframe_maps`, PyTorch's
    operations; `cpu_kernels.keyframe_maps` gives the same values in one compiled pass per camera).
    """
    build_maps = build_maps or keyframe_maps
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
    maps = build_maps(
        [with_time(batch[IMAGES_PREFIX + cam]).flatten(0, 1) for cam in cameras],
        [with_time(batch[DEPTH_PREFIX + cam]).flatten(0, 1) for cam in cameras],
        pixel_steps.flatten().nonzero().squeeze(1), rows, columns, pixel_calibration, mark_pixel,
        config.stem_point_cloud, ENCODER_STRIDE, rescale is not None,
    )  # stem, points, valid pixels, patch points

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


def keyframe_maps(rgb: list[Tensor], depth: list[Tensor], steps: Tensor, rows: Tensor, columns: Tensor,
                  calibration: Tensor, mark_pixel: Tensor, stem_point_cloud: bool, patch: int,
                  resampled: bool) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """`keyframe_observations`' pixel maps of M steps: per camera, colour (S, 3, H, W) and depth (S, 1, H, W)
    (millimetres) of every step, taken at the steps `steps` (M,) and, when `resampled`, at the camera pixels
    (rows[m, y], columns[m, x]) (rows (M, H), columns (M, W); else they are 0..H-1 and 0..W-1). calibration (M, C, 20)
    and mark_pixel (M, C) the gripper's flat camera pixel, -1 where it is not seen. Returns the stem's input
    (M, C, H, W, 4 or 7) channels last (colour in [-1, 1], the point cloud with `stem_point_cloud`, the gripper mark),
    points (M, C, 3, H, W) (0 where no depth), valid pixels (M, C, H, W) and each `patch` x `patch` patch's mean point
    (M, C, 3, H / patch, W / patch)."""
    height, width = rgb[0].shape[-2:]

    def per_camera(maps: list[Tensor]) -> Tensor:  # (M, C, ...)
        return torch.stack([x if len(steps) == len(x) else x.index_select(0, steps) for x in maps], dim=1)

    source = (rows[:, :, None] * width + columns[:, None, :]).view(-1, 1, height * width)  # (M, 1, H*W)
    rgb, depth_mm = per_camera(rgb), per_camera(depth)
    if resampled:  # unscaled maps show their own pixels: no gather
        rgb, depth_mm = resample(rgb, source), resample(depth_mm, source)
    depth_mm = depth_mm[..., 0, :, :].float()  # LeRobot's native depth: (.., 1, H, W) millimetres, 0 = no hit
    valid_pixels = depth_mm > 0
    pixel_rows = rows[:, None, None, :, None].float()  # as depth_to_world_points broadcasts them
    pixel_columns = columns[:, None, None, None, :].float()
    points = depth_to_world_points(depth_mm / 1000.0, calibration, pixel_columns, pixel_rows)
    points = points * valid_pixels.unsqueeze(-3)
    mark = (source == mark_pixel.unsqueeze(-1)).to(points.dtype).view(*mark_pixel.shape, 1, height, width)
    stem = torch.cat([rgb.float() * 2 - 1, *([points] if stem_point_cloud else []), mark], dim=2)
    return stem.movedim(2, -1).contiguous(), points, valid_pixels, patch_mean_points(points, valid_pixels, patch)


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


def patch_mean_points(points: Tensor, valid: Tensor, patch: int = ENCODER_STRIDE) -> Tensor:
    """Each encoder patch's mean point over its valid pixels, as the authors' patch position: points (M, C, 3, H, W)
    and valid (M, C, H, W) -> (M, C, 3, H / patch, W / patch)."""
    point_mean = F.avg_pool2d(points.flatten(0, 1), patch)
    valid_fraction = F.avg_pool2d(valid.flatten(0, 1).unsqueeze(1).to(points.dtype), patch)
    return (point_mean / valid_fraction.clamp_min(1e-6)).unflatten(0, points.shape[:2])


def take_steps(x: Tensor, steps: Tensor, leading_dims: int = 2) -> Tensor:
    """x[steps] for a bool mask over x's leading dims, e.g. (B, T, ...) -> (M, ...).

    Without a copy when every step is taken (the common case of a window without padding). The rows are taken
    with `index_select`, whose gradient is an `index_add` (a boolean mask's is a serial scatter on CPU).
    """
    rows = x.flatten(0, leading_dims - 1)
    return rows if bool(steps.all()) else rows.index_select(0, steps.flatten().nonzero().squeeze(1))

