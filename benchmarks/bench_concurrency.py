"""Single-target latency of the correction node while a 1 000 000-target batch is being served.

Four clients (each its own node, one process) send single-target requests to correct_setpoints in
a loop; p99 of their round trips without a batch, then while a fifth client in another process sends
1 000 000-target requests back to back to correct_setpoints_batch (``--same-service``: to
correct_setpoints, where Fast DDS delivers each 42 MB answer to every client before the answers
written after it). The correction node computes a batch in chunks (parameter chunk_targets) and
serves other requests between chunks. Goal (issue 16): p99 with the batch within 3x the p99 without.

The batch client has its own process because receiving a 42 MB answer is work of the client: in
the single clients' process it held their interpreter (gaps up to ~300 ms measured there), which
the node cannot change.

Run: .venv/bin/python benchmarks/bench_concurrency.py [--requests 300] [--batch 1000000] [--same-service]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import threading
import time

import numpy as np
import rclpy

from gls_calibration.ros.base import CLIENT_QOS
from gls_calibration.ros.conversions import flag_array, float64_sequence
from gls_calibration_msgs.srv import CorrectSetpoints

from correction_peer import call, correction_peer

CLIENTS = 4


LOST_AFTER_S = 5.0
lost_answers: list[float] = []   # round trips given up (1 in ~4000-8000 with the default answer queue of 10)


def round_trips(client, count: int, out: list) -> None:
    """``count`` round trips; a lost answer counts with the time waited for it (``LOST_AFTER_S``)."""
    request = CorrectSetpoints.Request(x=[10.0], y=[-20.0])
    for _ in range(count):
        began = time.perf_counter()
        try:
            response = call(client, request, timeout_s=LOST_AFTER_S)
        except RuntimeError:
            lost_answers.append(time.perf_counter())
            out.append(time.perf_counter() - began)
            continue
        out.append(time.perf_counter() - began)
        assert response.success, response.message


def concurrent_singles(clients, count: int) -> np.ndarray:
    results: list[list[float]] = [[] for _ in clients]
    threads = [threading.Thread(target=round_trips, args=(client, count, out)) for client, out in zip(clients, results)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if any(len(out) != count for out in results):
        raise RuntimeError("a single-target client failed (see its traceback above)")
    return np.concatenate(results)


def first_answers(clients) -> None:
    """One answer per client, re-sent until it comes: a request sent just after discovery can be
    answered before the service has matched the client's reader, and that answer is lost."""
    request = CorrectSetpoints.Request(x=[10.0], y=[-20.0])
    for client in clients:
        for attempt in range(10):
            try:
                call(client, request, timeout_s=3.0)
                break
            except RuntimeError:
                if attempt == 9:
                    raise


def serve_batches(size: int, service: str) -> None:
    """Batch client (child process): ``size``-target requests back to back until stdin closes; prints
    "started" once the service is there, then each round trip (s)."""
    rclpy.init()
    node = rclpy.create_node("batch_client", namespace="gls")
    client = node.create_client(CorrectSetpoints, service, qos_profile=CLIENT_QOS)
    if not client.wait_for_service(timeout_sec=60.0):
        raise RuntimeError("the correction node did not come up")
    xy = np.random.default_rng(0).uniform(-95.0, 95.0, (2, size))
    request = CorrectSetpoints.Request(x=float64_sequence(xy[0]), y=float64_sequence(xy[1]))
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    print("started", flush=True)
    while not stop.is_set():
        began = time.perf_counter()
        future = client.call_async(request)
        rclpy.spin_until_future_complete(node, future, timeout_sec=120.0)
        if not future.done():
            raise RuntimeError(f"no answer to a {size}-target request on {service} within 120 s")
        response = future.result()
        assert response.success and len(response.alpha_x) == size, response.message
        assert flag_array(response.within_limits).all() and len(response.inside_calibrated_field) == size
        print(time.perf_counter() - began, flush=True)
    rclpy.shutdown()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=300, help="single-target requests per client and phase")
    parser.add_argument("--batch", type=int, default=1_000_000)
    parser.add_argument("--same-service", action="store_true",
                        help="send the batches to correct_setpoints too (instead of correct_setpoints_batch)")
    parser.add_argument("--serve-batches", help=argparse.SUPPRESS)  # the child's role: the batch service
    args = parser.parse_args()
    if args.serve_batches:
        serve_batches(args.batch, args.serve_batches)
        return
    batch_service = "correct_setpoints" if args.same_service else "correct_setpoints_batch"
    names = tuple(f"single_{index}" for index in range(CLIENTS))
    with correction_peer(names) as (_, nodes, expected):
        singles = [node.create_client(CorrectSetpoints, "correct_setpoints", qos_profile=CLIENT_QOS) for node in nodes]
        for client in singles:
            if not client.wait_for_service(timeout_sec=60.0):
                raise RuntimeError("the correction node did not come up")
        first_answers(singles)
        concurrent_singles(singles, 20)                          # warm-up
        lost_answers.clear()
        alone = concurrent_singles(singles, args.requests)
        lost_alone = len(lost_answers)

        batcher = subprocess.Popen([sys.executable, __file__, "--serve-batches", batch_service,
                                    "--batch", str(args.batch)],
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        if batcher.stdout.readline().strip() != "started":
            raise RuntimeError("the batch client did not start")
        time.sleep(0.5)                                          # the first batch is being served
        during = concurrent_singles(singles, args.requests)
        output, _ = batcher.communicate("", timeout=300)        # stdin closed: the batch in flight ends the loop
        if batcher.returncode:
            raise RuntimeError(f"the batch client failed (exit {batcher.returncode})")
        batch_times = [float(line) for line in output.split()]
        check = expected.correct(np.array([10.0]), np.array([-20.0]))
        assert check.within_limits.all()
    p99_alone, p99_during = np.percentile(alone, 99), np.percentile(during, 99)
    print(f"single target from {CLIENTS} clients, {args.requests} requests each: p99 {1e3 * p99_alone:.2f} ms alone, "
          f"{1e3 * p99_during:.2f} ms while {args.batch}-target batches are served on {batch_service} "
          f"({p99_during / p99_alone:.1f}x; "
          f"goal <= 3x); median {1e3 * np.median(alone):.2f} / {1e3 * np.median(during):.2f} ms")
    print(f"  answers lost (given up after {LOST_AFTER_S:.0f} s, counted with that time): {lost_alone} alone, "
          f"{len(lost_answers) - lost_alone} during the batches")
    print(f"  slowest round trips during the batches (ms): {np.round(1e3 * np.sort(during)[-12:], 1).tolist()}; "
          f"{int(np.sum(during > 3 * p99_alone))} of {during.size} over 3x the p99 alone")
    print(f"  {len(batch_times)} batches of {args.batch} targets, median {np.median(batch_times):.2f} s each")


if __name__ == "__main__":
    main()
