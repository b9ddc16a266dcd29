"""Keep freed memory in the process for the next sweep: glibc's allocator set once, before the nodes start.

A sweep travels as clouds of 64 MB (2 000 x 2 000 points, float32 x, y, z, intensity) and becomes
arrays of 100-130 MB. By default glibc serves every such block with a fresh ``mmap`` and returns it
with ``munmap`` when freed; in any thread but the main one it must, whatever its threshold, since a
thread's own arena grows in heaps of at most 64 MB. The kernel then zeroes every page again on first
touch: in the main job about a quarter of the process's CPU was system time (figures: docs/benchmarks.md,
"Memory kept for the next sweep"). One arena (the main one, which grows without that limit), blocks up to
:data:`MMAP_THRESHOLD_BYTES` taken from it, and at most :data:`TRIM_THRESHOLD_BYTES` kept free at
its top keep those pages mapped from one sweep to the next.

Hazards: the process keeps its peak of freed memory mapped (its resident size does not fall back
after a sweep; in the main job the peak itself fell); every thread, DDS's
included, allocates from one arena under one lock (Python's lock already serialises the nodes'
work; no loss was measured). Set ``GLS_KEEP_FREED_MEMORY=0`` in the environment to leave glibc's
defaults. No maintained Python library sets these options; the standard library's ``ctypes`` calls
glibc's ``mallopt`` directly. On a C library other than glibc nothing is changed.
"""
from __future__ import annotations

import ctypes
import os

# mallopt's parameter numbers (glibc's malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8

# Blocks up to 1 GiB come from the heap (a sweep's largest array is about 130 MB), and up to 1 GiB
# may stay free at its top: beyond that the allocator behaves as before.
MMAP_THRESHOLD_BYTES = 1 << 30
TRIM_THRESHOLD_BYTES = 1 << 30
ENVIRONMENT_SWITCH = "GLS_KEEP_FREED_MEMORY"


def keep_freed_memory() -> bool:
    """Set glibc's allocator to keep freed sweep-sized blocks mapped; return whether it was set.

    Call it once at the start of a process, before its node threads start (an arena a thread has
    already made stays in use by it). Returns False, changing nothing, when the environment sets
    ``GLS_KEEP_FREED_MEMORY=0``, when the C library is not glibc, or when glibc refuses an option.

    Returns
    -------
    bool
        True when all three options (one arena, the mmap threshold, the trim threshold) were set.

    Examples
    --------
    >>> import os
    >>> os.environ["GLS_KEEP_FREED_MEMORY"] = "0"
    >>> keep_freed_memory()
    False
    >>> del os.environ["GLS_KEEP_FREED_MEMORY"]
    """
    if os.environ.get(ENVIRONMENT_SWITCH, "1").strip() == "0":
        return False
    try:
        process = ctypes.CDLL(None)         # the symbols already loaded, the C library's among them
        process.gnu_get_libc_version        # glibc's own: another C library's options differ
        mallopt = process.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # each returns 1 when glibc took the value
    return all([mallopt(_M_ARENA_MAX, 1) == 1,
                mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1,
                mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1])
