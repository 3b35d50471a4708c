"""The computations the compiled CPU loops can replace, and the one switch between them (`cpu_kernels`).

PyTorch's definitions are the default; `cpu_kernels=true` takes `cpu_kernels.py`'s numba loops, which give the same
values (GroupNorm's within 1e-5) and fall back to these definitions for inputs they do not take (another device,
dtype or layout). numba is imported only then.
"""

from collections.abc import Callable
from dataclasses import dataclass

from torch import Tensor

from .observations import keyframe_maps
from .unet import GroupNormLeakyReLU, bilinear_upsample


def weighted_points(points: Tensor, weights: Tensor) -> Tensor:
    """`points @ weights`: the attended point, points (..., 3, P) weighted by (..., P, 1)."""
    return points @ weights


@dataclass(frozen=True)
class Operations:
    """One implementation of each replaceable computation, with the signatures of PyTorch's definitions."""

    group_norm_leaky_relu: type[GroupNormLeakyReLU]
    bilinear_upsample: Callable[[Tensor, tuple[int, int]], Tensor]
    weighted_points: Callable[[Tensor, Tensor], Tensor]
    keyframe_maps: Callable[..., tuple[Tensor, ...]]


PYTORCH = Operations(GroupNormLeakyReLU, bilinear_upsample, weighted_points, keyframe_maps)


def operations(cpu_kernels: bool) -> Operations:
    """PyTorch's operations, or with `cpu_kernels` the compiled CPU loops (which need the `cpu` extra: numba)."""
    if not cpu_kernels:
        return PYTORCH
    try:
        from . import cpu_kernels as compiled
    except ImportError as error:
        raise ImportError(
            "cpu_kernels=true needs numba: pip install 'lerobot_policy_hiveformer[cpu]', or set "
            "--policy.cpu_kernels=false for PyTorch's operations."
        ) from error
    return compiled.OPERATIONS
