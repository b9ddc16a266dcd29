"""Command-line tools: the simulated cell, the operator clients and the discrepancy workflow.

Importing this package sets the process's allocator options for sweep-sized arrays
(:func:`gls_calibration.ros.allocator.keep_freed_memory`; ``GLS_KEEP_FREED_MEMORY=0`` leaves glibc's
defaults): it must happen before numpy, OpenCV and rclpy start threads of their own, and a tool
imports its package before its module's imports.
"""
from __future__ import annotations

import argparse
import math

from gls_calibration.ros.allocator import keep_freed_memory

keep_freed_memory()


def timeout_seconds(text: str) -> float:
    """Parse a ``--timeout`` (an argparse ``type``): a positive finite number of seconds.

    A negative, zero, NaN or infinite wait is refused as a usage error, exit 2, before anything
    starts.
    """
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of seconds, got {text!r}") from None
    if not math.isfinite(value) or value <= 0.0:
        raise argparse.ArgumentTypeError(f"must be a positive number of seconds, got {text!r}")
    return value
