"""The UNet around the transformer: the per-camera encoder that turns the stem's input into a grid of tokens, and
the decoder that turns tokens and the encoder's skips back into one logit per pixel.

Built channels-last: oneDNN's convolutions with few channels run much faster on that layout, and every feature map
and gradient keeps it. The GroupNorm + LeakyReLU layer and the 2x bilinear upsampling are PyTorch's here; the
compiled CPU loops (`cpu_kernels.py`) replace them when `cpu_kernels` is on (`operations.py`).
"""

from collections.abc import Callable

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

ENCODER_CHANNELS = 16
LEAKY_SLOPE = 0.02


class GroupNormLeakyReLU(nn.GroupNorm):
    """`nn.GroupNorm` followed by `LeakyReLU(negative_slope)` (in place) as one layer."""

    def __init__(self, num_groups: int, num_channels: int, negative_slope: float):
        super().__init__(num_groups, num_channels)
        self.negative_slope = negative_slope

    def forward(self, x: Tensor) -> Tensor:
        return F.leaky_relu(F.group_norm(x, self.num_groups, self.weight, self.bias, self.eps), self.negative_slope,
                            inplace=True)

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, negative_slope={self.negative_slope}"


def bilinear_upsample(x: Tensor, size: tuple[int, int]) -> Tensor:
    """`F.interpolate(x, size, mode="bilinear", align_corners=False)`."""
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False)


class ConvBlock(nn.Sequential):
    """3x3 convolution + GroupNorm + LeakyReLU, as in the supplement's UNet."""

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1,
                 norm: type[GroupNormLeakyReLU] = GroupNormLeakyReLU):
        super().__init__(
            nn.Conv2d(in_channels, out_channels, kernel_size=3, stride=stride, padding=1),
            norm(num_groups=4, num_channels=out_channels, negative_slope=LEAKY_SLOPE),
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

    def __init__(self, in_channels: int, norm: type[GroupNormLeakyReLU] = GroupNormLeakyReLU):
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(in_channels, 8, kernel_size=3, padding=1),
            nn.LeakyReLU(LEAKY_SLOPE, inplace=True),
            nn.Conv2d(8, ENCODER_CHANNELS, kernel_size=1),
            nn.LeakyReLU(LEAKY_SLOPE, inplace=True),
        )
        self.down = nn.ModuleList([ConvBlock(ENCODER_CHANNELS, ENCODER_CHANNELS, 2, norm) for _ in range(4)])

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

    def __init__(self, token_dim: int, norm: type[GroupNormLeakyReLU] = GroupNormLeakyReLU,
                 upsample: Callable[[Tensor, tuple[int, int]], Tensor] = bilinear_upsample):
        super().__init__()
        self.upsample = upsample
        self.bottleneck = ConvBlock(token_dim + ENCODER_CHANNELS, ENCODER_CHANNELS, norm=norm)
        self.up = nn.ModuleList([ConvBlock(2 * ENCODER_CHANNELS, ENCODER_CHANNELS, norm=norm) for _ in range(3)])
        self.to_logit = nn.Conv2d(ENCODER_CHANNELS, 1, kernel_size=1)

    def forward(self, token_grid: Tensor, skips: list[Tensor]) -> Tensor:
        """token_grid: (N, D, H/16, W/16); skips from UNetEncoder. Returns (N, H, W)."""
        x = conv_block_of_concatenation(self.bottleneck, [token_grid, skips[-1]])  # (N, 16, H/16, W/16)
        for block, skip in zip(self.up, reversed(skips[:-1]), strict=True):
            x = self.upsample(x, skip.shape[-2:])
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

