"""Soak of the correction node: 10 000 single-target and 100 large requests in a row, every answer
checked against the same calibration evaluated here, and the node's resident memory before and after
(goal: no growth beyond 5 %).

Run: .venv/bin/python benchmarks/bench_soak.py [--singles 10000] [--large 100] [--large-size 100000]
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from gls_calibration.ros.conversions import float64_sequence
from gls_calibration_msgs.srv import CorrectSetpoints

from correction_peer import call, correction_peer, rss_bytes


def checked(client, expected, x, y) -> float:
    """Round trip (s) of one request; AssertionError unless the answer equals the local evaluation."""
    began = time.perf_counter()
    response = call(client, CorrectSetpoints.Request(x=float64_sequence(x), y=float64_sequence(y)))
    elapsed = time.perf_counter() - began
    assert response.success, response.message
    reference = expected.correct(x, y)
    np.testing.assert_array_equal(np.asarray(response.alpha_x), reference.alpha_x)
    np.testing.assert_array_equal(np.asarray(response.alpha_y), reference.alpha_y)
    np.testing.assert_array_equal(np.asarray(response.focus_shift), reference.focus_shift)
    assert len(response.within_limits) == len(x)
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--singles", type=int, default=10_000)
    parser.add_argument("--large", type=int, default=100)
    parser.add_argument("--large-size", type=int, default=100_000)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    with correction_peer() as (child, (node,), expected):
        client = node.create_client(CorrectSetpoints, "correct_setpoints")
        if not client.wait_for_service(timeout_sec=60.0):
            raise RuntimeError("the correction node did not come up")
        for _ in range(50):   # warm-up: discovery, first allocations, one large request
            checked(client, expected, rng.uniform(-95, 95, 1), rng.uniform(-95, 95, 1))
        checked(client, expected, *rng.uniform(-95, 95, (2, args.large_size)))
        before = rss_bytes(child.pid)
        began = time.perf_counter()
        singles = [checked(client, expected, rng.uniform(-95, 95, 1), rng.uniform(-95, 95, 1))
                   for _ in range(args.singles)]
        middle = rss_bytes(child.pid)
        large = [checked(client, expected, *rng.uniform(-95, 95, (2, args.large_size))) for _ in range(args.large)]
        after = rss_bytes(child.pid)
        total = time.perf_counter() - began
    growth = 100.0 * (after - before) / before
    print(f"soak: {args.singles} single-target + {args.large} x {args.large_size} targets, every answer equal to "
          f"the local evaluation; {total:.1f} s in all")
    print(f"  single target: median {1e3 * statistics.median(singles):.2f} ms, "
          f"p99 {1e3 * np.percentile(singles, 99):.2f} ms")
    print(f"  {args.large_size} targets: median {1e3 * statistics.median(large):.1f} ms, "
          f"max {1e3 * max(large):.1f} ms")
    print(f"  correction node RSS: {before / 2**20:.1f} MiB before, {middle / 2**20:.1f} MiB after the singles, "
          f"{after / 2**20:.1f} MiB after the large ones: {growth:+.2f} % (goal: < 5 %)")


if __name__ == "__main__":
    main()
