"""Loops compiled with numba for the CPU passes that PyTorch runs as many small operations: GroupNorm with the
LeakyReLU after it (the UNet's normalisation and activation), forward and backward, and the assembly of the
encoder's channels-last input. The kernels compile on first use (~3 s) and numba caches them on disk (its
`cache=True`), so later processes load them in ~0.5 s. Other inputs (another device, dtype or layout) take
PyTorch's operations.

GroupNorm + LeakyReLU: on channels-last CPU maps each map is an (H*W, C) matrix. The forward pass sums each
channel's values and squares in one sweep over the map, then writes the normalised and activated values in a
second; the backward pass sums the activation's gradient and its product with the input in one sweep, then writes
the input's gradient in a second. One map (a 32x32 16-channel map is 64 KiB) stays in the core's cache between its
two sweeps, so each pass reads its inputs from memory about once, where PyTorch's operations took ~13 passes and
~35 operator calls per layer. The activation is not saved: the backward pass recomputes its sign from the input.
The sums run in float64 over the map centred on its mean (float32 sums of E[x²] - E[x]² lose the variance where
a map's mean dwarfs its spread).
"""

import numba
import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from numba import njit, prange
from torch import Tensor, nn

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
        # dy: the gradient at the normalised value, i.e. through the LeakyReLU, whose sign is recomputed from x
        # as the forward pass computed it.
        dy_sum = np.zeros(channels, np.float64)
        dy_dot_centred = np.zeros(channels, np.float64)
        for p in range(pixels):
            for c in range(channels):
                centred = x[i, p, c] - centre[c]
                dy = grad[i, p, c]
                if centred * scale[c] + bias[c] <= 0:
                    dy *= slope
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
                centred = x[i, p, c] - centre[c]
                dy = grad[i, p, c]
                if centred * scale[c] + bias[c] <= 0:
                    dy *= slope
                grad_x[i, p, c] = centred * centred_coefficient[c] + dy * dy_coefficient[c] + constant[c]


def _matrix(x: Tensor) -> np.ndarray:
    """A channels-last (N, C, H, W) tensor as the (N, H*W, C) array over its memory (no copy)."""
    n, c, h, w = x.shape
    return x.detach().permute(0, 2, 3, 1).view(n, h * w, c).numpy()


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


class GroupNormLeakyReLU(nn.GroupNorm):
    """`nn.GroupNorm` (same parameters, same values) followed by `LeakyReLU(negative_slope)`."""

    def __init__(self, num_groups: int, num_channels: int, negative_slope: float):
        super().__init__(num_groups, num_channels)
        self.negative_slope = negative_slope

    def forward(self, x: Tensor) -> Tensor:
        if (x.device.type != "cpu" or x.dtype != torch.float32 or x.dim() != 4 or self.weight.dtype != torch.float32
                or not x.is_contiguous(memory_format=torch.channels_last)):
            return F.leaky_relu(F.group_norm(x, self.num_groups, self.weight, self.bias, self.eps),
                                self.negative_slope, inplace=True)
        args = (x, self.num_groups, self.weight, self.bias, self.eps, self.negative_slope)
        if torch.is_grad_enabled() and (x.requires_grad or self.weight.requires_grad or self.bias.requires_grad):
            return _GroupNormLeakyReLU.apply(*args)
        return _normalise(*args)[0]

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, negative_slope={self.negative_slope}"


@njit(parallel=True, cache=True)
def _interleave(rgb, points, mark, out):  # pragma: no cover (compiled)
    """rgb (M, C, 3, H, W) in [0, 1], points (M, C, P, H, W) with P = 3 or 0, mark (M, C, 1, H, W) -> out
    (M*C, H, W, 3 + P + 1): colour scaled to [-1, 1], then the point cloud, then the mark, per pixel."""
    steps, cameras, _, height, width = rgb.shape
    point_channels = points.shape[2]
    for map_index in prange(steps * cameras):
        m, c = map_index // cameras, map_index % cameras
        for y in range(height):
            for x in range(width):
                for k in range(3):
                    out[map_index, y, x, k] = rgb[m, c, k, y, x] * 2 - 1
                for k in range(point_channels):
                    out[map_index, y, x, 3 + k] = points[m, c, k, y, x]
                out[map_index, y, x, 3 + point_channels] = mark[m, c, 0, y, x]


def stem_input(rgb: Tensor, points: Tensor | None, mark: Tensor) -> Tensor:
    """The encoder's input: colour in [-1, 1], the point cloud (unless None) and the gripper mark of (M, C, k, H, W)
    maps, as (M*C, 4 or 7, H, W) channels-last. One interleaving pass on CPU; `torch.cat` of the maps moved
    channels-last, after scaling the colour, elsewhere (and where a gradient is needed)."""
    parts = [rgb, *([] if points is None else [points]), mark]
    if any(x.device.type != "cpu" or x.dtype != torch.float32 or x.requires_grad for x in parts):
        parts[0] = rgb * 2 - 1
        return torch.cat([x.movedim(-3, -1) for x in parts], dim=-1).flatten(0, 1).permute(0, 3, 1, 2)
    steps, cameras, _, height, width = rgb.shape
    if points is None:
        points = rgb.new_empty(steps, cameras, 0, height, width)
    out = rgb.new_empty(steps * cameras, height, width, 4 + points.shape[2])
    _use_torch_threads()
    _interleave(rgb.numpy(), points.numpy(), mark.numpy(), out.numpy())
    return out.permute(0, 3, 1, 2)
