"""The one place where this plugin changes how the process allocates memory: glibc's malloc keeps the
memory that tensors free, instead of giving it back to the kernel and faulting it in again.

PyTorch takes CPU tensors from malloc. With glibc's defaults every block over the mmap threshold (128 KiB,
rising to at most 32 MiB as such blocks are freed) is a fresh `mmap`, unmapped again on `free`, and free
space at the top of the heap is given back, so each new activation, gradient or image batch page-faults
its memory in (zero-filled by the kernel) every step. HiveFormer's CPU steps are full of such tensors
(the history's (B, T, C, 7, H, W) maps, the (heads, 193, 1170) attention scores): a train step (batch 8,
history 6, 3 cameras 128², 2 threads) took 5.6 s with 40 % of the process's CPU time in the kernel, and
2.8 s once malloc keeps freed memory, for 2 GiB more peak RSS (`measure_compute.py`; the figures are in
docs/plugin.md).

`retain_freed_memory()` sets two of glibc's documented `mallopt` parameters for the whole process:
no `mmap` for large blocks (M_MMAP_MAX = 0, so they come from the heap) and no trimming of the heap
(M_TRIM_THRESHOLD at its maximum). The process then keeps its peak heap size until it exits, as
PyTorch's own CUDA caching allocator does on the GPU. DataLoader workers forked afterwards inherit it.
Nothing is done on a C library other than glibc (macOS, musl), where `mallopt` differs or is missing.
`HiveformerPolicy` calls it unless `--policy.retain_freed_memory=false`.
"""

import ctypes
import functools
import platform

# From glibc's <malloc.h>.
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
_LARGEST_INT = 2**31 - 1  # mallopt takes an int


@functools.cache
def retain_freed_memory() -> bool:
    """Make glibc's malloc keep freed memory for reuse (once per process); False where it cannot."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return mallopt(M_MMAP_MAX, 0) == 1 and mallopt(M_TRIM_THRESHOLD, _LARGEST_INT) == 1
