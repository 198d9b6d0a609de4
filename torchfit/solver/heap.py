"""Keep glibc's malloc from handing the heap back to the kernel between LM iterations.

A batched solve on the CPU allocates and frees the same few large temporaries (residuals,
dual-tensor tangents, the Jacobian) on every iteration. glibc serves blocks above its mmap
threshold with fresh ``mmap`` calls and trims the top of the heap once more than its trim
threshold lies free there, so each iteration can fault the same pages in again. Whether that
happens depends on glibc's dynamic thresholds, which is why the time of a large batch can be
bimodal from one process to the next (``benchmarks/RESULTS.md``, solver section).

:func:`keep_heap` fixes both thresholds for the running process through ``mallopt`` (the same
as starting Python with ``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_`` set). It
changes memory reuse only, never results; freed memory stays with the process (up to the trim
threshold) instead of going back to the system. Elsewhere than glibc (macOS, Windows, musl) it
does nothing and returns ``False``; jemalloc or tcmalloc preloaded have the same effect.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

__all__ = ["keep_heap"]

# mallopt parameters, from glibc's <malloc.h>.
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def keep_heap(mmap_threshold: int = 16 << 20, trim_threshold: int = 64 << 20) -> bool:
    """Fix glibc's mmap and trim thresholds for this process; ``True`` if both were set.

    Args:
        mmap_threshold: blocks up to this many bytes come from the heap (glibc refuses
            values above its largest heap size, 32 MiB on most 64-bit systems).
        trim_threshold: the heap is trimmed only when more than this many bytes lie free at
            its top.

    Call it once, early (before the first large solve). Returns ``False`` without changing
    anything where the C library is not glibc.
    """
    if mmap_threshold <= 0 or trim_threshold <= 0:
        raise ValueError(
            f"keep_heap: thresholds must be positive, got mmap_threshold={mmap_threshold}, "
            f"trim_threshold={trim_threshold}"
        )
    if not sys.platform.startswith("linux"):
        return False
    name = ctypes.util.find_library("c") or "libc.so.6"
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # noqa: B018 (glibc only; AttributeError elsewhere)
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok_mmap = mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold)) == 1
    ok_trim = mallopt(_M_TRIM_THRESHOLD, int(trim_threshold)) == 1
    return ok_mmap and ok_trim
