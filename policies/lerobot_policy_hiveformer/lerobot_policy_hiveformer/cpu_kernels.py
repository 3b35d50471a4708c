"""Loops compiled with numba for the CPU passes that PyTorch runs as many small operations or slowly: GroupNorm with
the LeakyReLU after it (the UNet's normalisation and activation), forward and backward; the policy's pixel maps
(colour and depth taken at the augmentation's pixels, the point cloud, the gripper mark, the encoder's channels-last
input and the patch points, in one pass where PyTorch took ~30 operations); the attended point's weight gradient;
the decoder's 2x bilinear upsampling, forward and backward. The kernels compile on first use (~3 s) and numba caches
them on disk (its `cache=True`), so later processes load them in ~0.5 s. Other inputs (another device, dtype or
layout) take PyTorch's operations. All but GroupNorm's compute PyTorch's values bit for bit (its CPU kernels' order
of operations, fused multiply-adds included, as PyTorch's x86 builds compile them), so a training run takes the same
path with or without them. Imported only when the policy's `cpu_kernels` is on (`operations.py`); each call runs
numba's parallel loops on as many threads as PyTorch's (numba's setting is per calling thread).

GroupNorm + LeakyReLU: on channels-last CPU maps each map is an (H*W, C) matrix. The forward pass sums each
channel's values and squares in one sweep over the map, then writes the normalised and activated values in a
second; the backward pass sums the activation's gradient and its product with the input in one sweep, then writes
the input's gradient in a second. One map (a 32x32 16-channel map is 64 KiB) stays in the core's cache between its
two sweeps, so each pass reads its inputs from memory about once, where PyTorch's operations took ~13 passes and
~35 operator calls per layer. The activation is not saved: the backward pass recomputes its sign from the input.
The sums run in float64 over the map centred on its mean (float32 sums of E[x²] - E[x]² lose the variance where
a map's mean dwarfs its spread).
"""

import functools

import numba
import numpy as np
import torch
from llvmlite import ir
from numba import njit, prange
from numba.core import types
from numba.extending import intrinsic
from torch import Tensor

from . import observations, unet
from . import operations

# Reassociating the sums lets LLVM vectorise them; NaN and infinity keep their IEEE behaviour.
_FASTMATH = {"reassoc", "contract"}


@njit(cache=True)
def _centre_and_scale(mean, rstd, weight, i, per_group):  # pragma: no cover (compiled)
    """Map i's per-channel centre and scale, (x - centre) * scale + bias being the normalised value: one function for
    both passes, so that the backward pass recomputes the activation's sign exactly as the forward pass computed it."""
    channels = weight.shape[0]
    centre = np.empty(channels, np.float32)
    scale = np.empty(channels, np.float32)
    for c in range(channels):
        centre[c] = mean[i, c // per_group]
        scale[c] = rstd[i, c // per_group] * weight[c]
    return centre, scale


@njit(inline="always")
def _centred_and_gradient(x, grad, centre, scale, bias, slope, i, p, c):  # pragma: no cover (compiled)
    """x's value centred on its group's mean, and the gradient at its normalised value: through the LeakyReLU,
    whose sign is recomputed from x as the forward pass computed it. Inlined: the loops keep their fastmath."""
    centred = x[i, p, c] - centre[c]
    dy = grad[i, p, c]
    if centred * scale[c] + bias[c] <= 0:
        dy *= slope
    return centred, dy


@njit(parallel=True, cache=True, fastmath=_FASTMATH)
def _forward(x, weight, bias, groups, eps, slope, out, mean, rstd):  # pragma: no cover (compiled)
    """x, out (N, P, C); weight, bias (C,); mean and rstd (N, groups) written for the backward pass.

    The sums run in float64 and the map is centred before scaling, as PyTorch's Welford statistics are accurate
    where a map's mean is large against its spread (float32 sums of E[x²] - E[x]² are not)."""
    maps, pixels, channels = x.shape
    per_group = channels // groups
    count = pixels * per_group
    for i in prange(maps):
        total = np.zeros(channels, np.float64)
        squares = np.zeros(channels, np.float64)
        for p in range(pixels):
            for c in range(channels):
                value = np.float64(x[i, p, c])
                total[c] += value
                squares[c] += value * value
        for g in range(groups):
            group_total = 0.0
            group_squares = 0.0
            for c in range(g * per_group, (g + 1) * per_group):
                group_total += total[c]
                group_squares += squares[c]
            m = group_total / count
            mean[i, g] = m
            rstd[i, g] = 1.0 / np.sqrt(max(group_squares / count - m * m, 0.0) + eps)
        centre, scale = _centre_and_scale(mean, rstd, weight, i, per_group)
        for p in range(pixels):
            for c in range(channels):
                y = (x[i, p, c] - centre[c]) * scale[c] + bias[c]
                out[i, p, c] = y if y > 0 else y * slope


@njit(parallel=True, cache=True, fastmath=_FASTMATH)
def _backward(grad, x, weight, bias, groups, slope, mean, rstd,
              grad_x, grad_sum, grad_dot_normalised):  # pragma: no cover (compiled)
    """grad, x, grad_x (N, P, C); the forward pass's mean and rstd; grad_sum and grad_dot_normalised (N, C)
    written for the bias's and weight's gradients (their sums over the maps). Sums in float64, the map centred."""
    maps, pixels, channels = x.shape
    per_group = channels // groups
    count = pixels * per_group
    for i in prange(maps):
        centre, scale = _centre_and_scale(mean, rstd, weight, i, per_group)
        dy_sum = np.zeros(channels, np.float64)
        dy_dot_centred = np.zeros(channels, np.float64)
        for p in range(pixels):
            for c in range(channels):
                centred, dy = _centred_and_gradient(x, grad, centre, scale, bias, slope, i, p, c)
                dy_sum[c] += dy
                dy_dot_centred[c] += np.float64(dy) * centred
        # dx = rstd * (dy * weight - mean(dy * weight) - x_hat * mean(dy * weight * x_hat)), means per group:
        # dx = (x - mean) * centred_coefficient + dy * dy_coefficient + constant, per (map, channel).
        centred_coefficient = np.empty(channels, np.float32)
        dy_coefficient = np.empty(channels, np.float32)
        constant = np.empty(channels, np.float32)
        for g in range(groups):
            r = np.float64(rstd[i, g])
            mean_grad = 0.0
            mean_grad_normalised = 0.0
            for c in range(g * per_group, (g + 1) * per_group):
                dot_normalised = r * dy_dot_centred[c]  # sum of dy * x_hat
                grad_sum[i, c] = dy_sum[c]
                grad_dot_normalised[i, c] = dot_normalised
                mean_grad += weight[c] * dy_sum[c]
                mean_grad_normalised += weight[c] * dot_normalised
            mean_grad /= count
            mean_grad_normalised /= count
            for c in range(g * per_group, (g + 1) * per_group):
                centred_coefficient[c] = -r * r * mean_grad_normalised
                dy_coefficient[c] = scale[c]
                constant[c] = -r * mean_grad
        for p in range(pixels):
            for c in range(channels):
                centred, dy = _centred_and_gradient(x, grad, centre, scale, bias, slope, i, p, c)
                grad_x[i, p, c] = centred * centred_coefficient[c] + dy * dy_coefficient[c] + constant[c]


def _channels_last_array(x: Tensor) -> np.ndarray:
    """A channels-last (N, C, H, W) tensor as the (N, H, W, C) array over its memory (no copy)."""
    return x.detach().permute(0, 2, 3, 1).numpy()


def _matrix(x: Tensor) -> np.ndarray:
    """A channels-last (N, C, H, W) tensor as the (N, H*W, C) array over its memory (no copy)."""
    n, c, h, w = x.shape
    return x.detach().permute(0, 2, 3, 1).view(n, h * w, c).numpy()  # a view, or an error: never a silent copy


def _use_torch_threads() -> None:
    numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))


def _normalise(x: Tensor, groups: int, weight: Tensor, bias: Tensor, eps: float,
               slope: float) -> tuple[Tensor, Tensor, Tensor]:
    """The layer's output, and the mean and rstd (N, groups) its backward pass needs."""
    out = torch.empty_like(x)
    mean, rstd = x.new_empty(x.shape[0], groups), x.new_empty(x.shape[0], groups)
    _use_torch_threads()
    _forward(_matrix(x), weight.detach().numpy(), bias.detach().numpy(), groups, eps, np.float32(slope),
             _matrix(out), mean.numpy(), rstd.numpy())
    return out, mean, rstd


class _GroupNormLeakyReLU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, groups: int, weight: Tensor, bias: Tensor, eps: float, slope: float) -> Tensor:
        out, mean, rstd = _normalise(x, groups, weight, bias, eps, slope)
        ctx.save_for_backward(x, weight, bias, mean, rstd)
        ctx.groups, ctx.slope = groups, slope
        return out

    @staticmethod
    def backward(ctx, grad: Tensor):
        x, weight, bias, mean, rstd = ctx.saved_tensors
        grad = grad.contiguous(memory_format=torch.channels_last)
        grad_x = torch.empty_like(x)
        grad_sum, grad_dot_normalised = x.new_empty(x.shape[:2]), x.new_empty(x.shape[:2])
        _use_torch_threads()
        _backward(_matrix(grad), _matrix(x), weight.detach().numpy(), bias.detach().numpy(), ctx.groups,
                  np.float32(ctx.slope), mean.numpy(), rstd.numpy(), _matrix(grad_x), grad_sum.numpy(),
                  grad_dot_normalised.numpy())
        return grad_x, None, grad_dot_normalised.sum(0), grad_sum.sum(0), None, None


class GroupNormLeakyReLU(unet.GroupNormLeakyReLU):
    """The PyTorch layer (same parameters, same values within 1e-5) with compiled forward and backward passes for
    float32 channels-last CPU maps; other inputs take the PyTorch layer's operations."""

    def forward(self, x: Tensor) -> Tensor:
        if (x.device.type != "cpu" or x.dtype != torch.float32 or x.dim() != 4 or self.weight.dtype != torch.float32
                or not x.is_contiguous(memory_format=torch.channels_last)):
            return super().forward(x)
        args = (x, self.num_groups, self.weight, self.bias, self.eps, self.negative_slope)
        if torch.is_grad_enabled() and (x.requires_grad or self.weight.requires_grad or self.bias.requires_grad):
            return _GroupNormLeakyReLU.apply(*args)
        return _normalise(*args)[0]


@intrinsic
def _fma(typingctx, a, b, c):  # pragma: no cover (compiled)
    """float32 a * b + c rounded once, as PyTorch's CPU `addcmul` computes it (numba has no fused multiply-add)."""
    def codegen(context, builder, signature, args):
        function = ir.FunctionType(ir.FloatType(), [ir.FloatType()] * 3)
        return builder.call(builder.module.declare_intrinsic("llvm.fma", [ir.FloatType()], function), args)
    return types.float32(types.float32, types.float32, types.float32), codegen


@njit(parallel=True, cache=True)
def _camera_maps(rgb, depth, camera, steps, rows, columns, calibration, mark_pixel,
                 stem, points, valid, patch_xyz):  # pragma: no cover (compiled)
    """One camera's maps of M rows, each taken from step `steps[m]` of rgb (S, 3, H, W) and depth (S, 1, H, W)
    (millimetres) at the camera pixels (rows[m, y], columns[m, x]), written to the `camera` slot of stem
    (M, C, H, W, 3 + P + 1) (colour in [-1, 1], the point cloud unless P = 0, the gripper mark), points
    (M, C, 3, H, W), valid (M, C, H, W) and patch_xyz (M, C, 3, h, w) (each (H/h)x(W/w) patch's mean point over its
    valid pixels). calibration (M, 20) is this camera's; mark_pixel (M,) the gripper's flat camera pixel, -1 where
    it is not seen. The arithmetic is `depth_to_world_points`' and `patch_mean_points`', operation for operation
    (float32, no reassociation, a patch summed row by row as `avg_pool2d` sums it), so the values are PyTorch's
    bit for bit."""
    height, width = rows.shape[1], columns.shape[1]
    point_channels = stem.shape[4] - 4
    patches = patch_xyz.shape[4]
    patch_height, patch_width = height // patch_xyz.shape[3], width // patches
    patch_pixels = np.float32(patch_height * patch_width)
    thousand = np.float32(1000.0)
    for m in prange(steps.shape[0]):
        s = steps[m]
        fx, fy, cx, cy = calibration[m, 0], calibration[m, 1], calibration[m, 2], calibration[m, 3]
        column_rays = np.empty(width, np.float32)
        for x in range(width):
            column_rays[x] = (np.float32(columns[m, x]) - cx) / fx
        row_term = np.empty(3, np.float32)
        point_sums = np.zeros((3, patches), np.float32)  # the current row of patches
        valid_counts = np.zeros(patches, np.float32)
        for y in range(height):
            source_row = rows[m, y]
            row_ray = (np.float32(source_row) - cy) / fy
            for i in range(3):
                row_term[i] = calibration[m, 5 + 4 * i] * row_ray + calibration[m, 6 + 4 * i]
            for patch in range(patches):
                for x in range(patch * patch_width, (patch + 1) * patch_width):
                    source_column = columns[m, x]
                    for k in range(3):
                        stem[m, camera, y, x, k] = rgb[s, k, source_row, source_column] * 2 - 1
                    depth_mm = depth[s, 0, source_row, source_column]
                    is_valid = depth_mm > 0
                    valid[m, camera, y, x] = is_valid
                    keep = np.float32(1.0) if is_valid else np.float32(0.0)
                    depth_m = depth_mm / thousand
                    for i in range(3):
                        ray = calibration[m, 4 + 4 * i] * column_rays[x] + row_term[i]
                        point = _fma(ray, depth_m, calibration[m, 7 + 4 * i]) * keep  # addcmul's rounding
                        points[m, camera, i, y, x] = point
                        point_sums[i, patch] += point
                        if i < point_channels:
                            stem[m, camera, y, x, 3 + i] = point
                    valid_counts[patch] += keep
                    seen = source_row * width + source_column == mark_pixel[m]
                    stem[m, camera, y, x, 3 + point_channels] = np.float32(1.0) if seen else np.float32(0.0)
            if (y + 1) % patch_height == 0:  # a row of patches done
                for patch in range(patches):
                    fraction = max(valid_counts[patch] / patch_pixels, np.float32(1e-6))
                    for i in range(3):
                        patch_xyz[m, camera, i, y // patch_height, patch] = point_sums[i, patch] / patch_pixels / fraction
                        point_sums[i, patch] = 0
                    valid_counts[patch] = 0


def keyframe_maps(rgb: list[Tensor], depth: list[Tensor], steps: Tensor, rows: Tensor, columns: Tensor,
                  calibration: Tensor, mark_pixel: Tensor, stem_point_cloud: bool, patch: int,
                  resampled: bool) -> tuple[Tensor, ...]:
    """`keyframe_observations`' pixel maps in one pass over each camera's pixels: per camera, colour (S, 3, H, W) and
    depth (S, 1, H, W) in millimetres for S steps; `steps` (M,) the step of each of the M rows, `rows` (M, H) and
    `columns` (M, W) the camera pixels each row's maps show; calibration (M, C, 20); mark_pixel (M, C) the gripper's
    flat camera pixel, -1 where it is not seen. Returns the stem's input (M, C, H, W, 4 or 7), points (M, C, 3, H, W),
    valid pixels (M, C, H, W) and each `patch` x `patch` patch's mean point (M, C, 3, H / patch, W / patch), with
    the values of PyTorch's operations (`observations.keyframe_maps`, which computes inputs the kernel does not take:
    another device or dtype). `resampled` is that function's: the kernel reads the given pixels either way."""
    if any(x.device.type != "cpu" or x.dtype != torch.float32 or x.requires_grad for x in [*rgb, *depth, calibration]):
        return observations.keyframe_maps(rgb, depth, steps, rows, columns, calibration, mark_pixel, stem_point_cloud,
                                          patch, resampled)
    (maps, cameras), (height, width) = mark_pixel.shape, rgb[0].shape[-2:]
    stem = rgb[0].new_empty(maps, cameras, height, width, 7 if stem_point_cloud else 4)
    points = rgb[0].new_empty(maps, cameras, 3, height, width)
    valid = torch.empty(maps, cameras, height, width, dtype=torch.bool)
    patch_xyz = rgb[0].new_empty(maps, cameras, 3, height // patch, width // patch)
    _use_torch_threads()
    arrays = [x.numpy() for x in (steps, rows, columns)]
    for camera in range(cameras):
        _camera_maps(rgb[camera].numpy(), depth[camera].numpy(), camera, *arrays, calibration[:, camera].numpy(),
                     mark_pixel[:, camera].numpy(), stem.numpy(), points.numpy(), valid.numpy(), patch_xyz.numpy())
    return stem, points, valid, patch_xyz


@njit(parallel=True, cache=True)
def _weights_gradient(points, grad, out):  # pragma: no cover (compiled)
    """points (N, K, P), grad (N, K) -> out (N, P) = sum over k of points * grad, added left to right in float32
    (as the batched product computes it for a few terms)."""
    terms = points.shape[1]
    for n in prange(points.shape[0]):
        for p in range(points.shape[2]):
            total = points[n, 0, p] * grad[n, 0]
            for k in range(1, terms):
                total += points[n, k, p] * grad[n, k]
            out[n, p] = total


class _WeightedPoints(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points: Tensor, weights: Tensor) -> Tensor:
        ctx.save_for_backward(points)
        return points @ weights

    @staticmethod
    def backward(ctx, grad: Tensor):
        (points,) = ctx.saved_tensors
        flat_points = points.reshape(-1, *points.shape[-2:])
        out = grad.new_empty(flat_points.shape[0], flat_points.shape[2])
        _use_torch_threads()
        _weights_gradient(flat_points.numpy(), grad.reshape(out.shape[0], -1).contiguous().numpy(), out.numpy())
        return None, out.view(*points.shape[:-2], points.shape[-1], 1)


def weighted_points(points: Tensor, weights: Tensor) -> Tensor:
    """`points @ weights` for points (..., 3, P) and weights (..., P, 1), the weights' gradient in one compiled pass
    on CPU: the batched product's backward pass (a product with 3 terms per value) ran ~4x slower than reading the
    points once. The same values as the product's; its gradients bit for bit where MKL adds the 3 terms in the
    loop's order (AMD EPYC), else within float32 rounding (Intel Xeon with AMX). The points take no gradient."""
    if (points.requires_grad or points.device.type != "cpu" or points.dtype != torch.float32
            or weights.dtype != torch.float32 or not torch.is_grad_enabled() or not weights.requires_grad):
        return operations.weighted_points(points, weights)
    return _WeightedPoints.apply(points, weights)


@functools.lru_cache
def _twice_sources(length: int) -> tuple[np.ndarray, ...]:
    """For each of 2 * `length` output pixels along an axis, its two input pixels and their weights under
    `F.interpolate(scale 2, mode="bilinear", align_corners=False)`: PyTorch's source index and lambda."""
    source = np.maximum((np.arange(2 * length) + 0.5) * 0.5 - 0.5, 0.0)
    first = np.minimum(source.astype(np.int64), length - 1)
    second_weight = np.clip(source - first, 0.0, 1.0).astype(np.float32)
    return first, first + (first < length - 1), (1 - second_weight).astype(np.float32), second_weight


@njit(cache=True)
def _corners(rows, columns, oy, ox):  # pragma: no cover (compiled)
    """Output pixel (oy, ox)'s four input pixels' rows and columns (y0, y1, x0, x1) and weights (w00, w01, w10, w11),
    from `_twice_sources` of each axis, the weights multiplied in float32 as PyTorch's kernels multiply them."""
    row_first, row_second, row_first_weight, row_second_weight = rows
    column_first, column_second, column_first_weight, column_second_weight = columns
    return (row_first[oy], row_second[oy], column_first[ox], column_second[ox],
            row_first_weight[oy] * column_first_weight[ox], row_first_weight[oy] * column_second_weight[ox],
            row_second_weight[oy] * column_first_weight[ox], row_second_weight[oy] * column_second_weight[ox])


@njit(parallel=True, cache=True)
def _upsample_twice(x, out, rows, columns):  # pragma: no cover (compiled)
    """x (N, H, W, C) -> out (N, 2H, 2W, C), PyTorch's channels-last bilinear kernel's arithmetic: the four weighted
    corners as nested fused multiply-adds in its order."""
    for n in prange(x.shape[0]):
        for oy in range(out.shape[1]):
            for ox in range(out.shape[2]):
                y0, y1, x0, x1, w00, w01, w10, w11 = _corners(rows, columns, oy, ox)
                for c in range(x.shape[3]):
                    out[n, oy, ox, c] = _fma(x[n, y0, x0, c], w00, _fma(x[n, y0, x1, c], w01,
                                             _fma(x[n, y1, x1, c], w11, x[n, y1, x0, c] * w10)))


@njit(parallel=True, cache=True)
def _upsample_twice_backward(grad, grad_x, rows, columns):  # pragma: no cover (compiled)
    """grad (N, 2H, 2W, C) -> grad_x (N, H, W, C), accumulated output pixel by output pixel and corner by corner with
    fused multiply-adds, as PyTorch's channels-last kernel does."""
    for n in prange(grad.shape[0]):
        grad_x[n] = 0
        for oy in range(grad.shape[1]):
            for ox in range(grad.shape[2]):
                y0, y1, x0, x1, w00, w01, w10, w11 = _corners(rows, columns, oy, ox)
                g = grad[n, oy, ox]
                for y, x, w in ((y0, x0, w00), (y0, x1, w01), (y1, x0, w10), (y1, x1, w11)):  # one corner at a time
                    target = grad_x[n, y, x]
                    for c in range(g.shape[0]):
                        target[c] = _fma(g[c], w, target[c])


class _BilinearTwice(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        n, c, h, w = x.shape
        ctx.input_shape = x.shape
        out = torch.empty(n, c, 2 * h, 2 * w, dtype=x.dtype, memory_format=torch.channels_last)
        _use_torch_threads()
        _upsample_twice(_channels_last_array(x), _channels_last_array(out), _twice_sources(h), _twice_sources(w))
        return out

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        shape = ctx.input_shape
        if not grad.is_contiguous(memory_format=torch.channels_last):  # PyTorch's other kernel, its own order
            return torch.ops.aten.upsample_bilinear2d_backward(grad, grad.shape[-2:], shape, False)
        grad_x = torch.empty(shape, dtype=grad.dtype, memory_format=torch.channels_last)
        _use_torch_threads()
        _upsample_twice_backward(_channels_last_array(grad), _channels_last_array(grad_x), _twice_sources(shape[2]),
                                 _twice_sources(shape[3]))
        return grad_x


def bilinear_upsample(x: Tensor, size: tuple[int, int]) -> Tensor:
    """`F.interpolate(x, size, mode="bilinear", align_corners=False)`; for channels-last CPU float32 maps doubled in
    size whose channels fill PyTorch's vectors (multiples of 16), two compiled loops with the values and gradients of
    PyTorch's kernels bit for bit (forward and backward ~1.6x faster at the decoder's maps)."""
    if (x.device.type != "cpu" or x.dtype != torch.float32 or x.dim() != 4 or x.shape[1] % 16
            or tuple(size) != (2 * x.shape[2], 2 * x.shape[3]) or not x.is_contiguous(memory_format=torch.channels_last)):
        return unet.bilinear_upsample(x, size)
    return _BilinearTwice.apply(x)


OPERATIONS = operations.Operations(GroupNormLeakyReLU, bilinear_upsample, weighted_points, keyframe_maps)
