"""Command-line tools: the simulated cell, the operator clients and the discrepancy workflow."""
from __future__ import annotations

import argparse
import math


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
