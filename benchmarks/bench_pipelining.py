"""What measuring each sweep while the next is scanned saves (issue 33 item 2), on a cell whose sweeps take time.

``procedure.measure_marked_plate`` starts the fiducial measurement of sweep k (``Cell.start``) and
acquires sweep k + 1 before it takes the result. In ``gls-sim-cell`` every node shares one process
and two cores with the simulated scanner, so the overlap is not visible there. Here the same
function runs on a cell whose sweeps take their cell time (a sleep of the sweep's duration, the
robot doing the work) and whose measurements compute in a worker thread beside it, as a fiducial
node beside a moving robot does; the clouds are a real marked plate's, recorded once from
``DirectCell``. Two runs of the plan: ``pipelined`` (the measurement started when the sweep is in)
and ``sequential`` (a cell that runs each step when awaited), alternating, ``--repeats`` times each.
Prints per mode the wall time of the marked-plate stage and the time from the end of the last sweep
to the last centre (what pipelining leaves), medians.

The sweep duration is the plan's sweep length over the sweep speed (``--speed-mm-s``, 15 mm/s by
default: 13.3 s for 200 mm); ``--time-scale`` shortens every sleep alike for a quicker run (the
measurement is not scaled, so a smaller scale understates what the overlap hides, never overstates).

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_pipelining.py [--preset paper_like]
     [--seed 1] [--repeats 3] [--time-scale 1.0] [--speed-mm-s 15]
"""
from __future__ import annotations

import argparse
import asyncio
import dataclasses
import statistics
import tempfile
import time
from pathlib import Path

from direct_runs import direct_cell, plan_settings
from gls_calibration.calibration import procedure
from gls_calibration.fiducials.measure import measure_fiducials
from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.simulation.world import load_sim_config


class RecordingCell:
    """Wraps a ``DirectCell``: keeps the marked-plate clouds and the plate pose they were measured on."""

    def __init__(self, cell, marked_step_mm: float) -> None:
        self.cell = cell
        self.marked_step_mm = marked_step_mm
        self.clouds: list = []
        self.pose = None

    def __getattr__(self, name):
        return getattr(self.cell, name)

    async def acquire_sweep(self, step_mm: float, direction: int = 1, orientation_deg: float = 0.0):
        cloud = await self.cell.acquire_sweep(step_mm, direction, orientation_deg)
        if step_mm == self.marked_step_mm:
            self.clouds.append(cloud)
        return cloud

    async def measure_fiducials(self, cloud, pose, expected_count, ring_radii_mm):
        self.pose = pose
        return await self.cell.measure_fiducials(cloud, pose, expected_count, ring_radii_mm)


class TimedReplayCell:
    """The recorded clouds, each after its sweep's duration; measurements in a worker thread.

    ``pipelined``: ``start`` begins the measurement at once (a task); otherwise it returns the step,
    which then runs when the procedure awaits it (``CoreCell.start``).
    """

    def __init__(self, clouds: list, sweep_s: float, pipelined: bool) -> None:
        self.clouds = list(clouds)
        self.sweep_s = sweep_s
        self.pipelined = pipelined
        self.sweeps_done_at: list[float] = []

    async def acquire_sweep(self, step_mm: float, direction: int = 1, orientation_deg: float = 0.0):
        await asyncio.sleep(self.sweep_s)
        self.sweeps_done_at.append(time.perf_counter())
        return self.clouds[len(self.sweeps_done_at) - 1]

    async def measure_fiducials(self, cloud, pose, expected_count, ring_radii_mm):
        return await asyncio.to_thread(measure_fiducials, cloud[0], cloud[1], pose, ring_radii_mm=ring_radii_mm,
                                       expected_count=expected_count)

    def start(self, step):
        return asyncio.ensure_future(step) if self.pipelined else step


def record(preset: str, seed: int):
    """One marked plate of the calibration plan: its clouds, the pose, the settings and the fiducial count."""
    with tempfile.TemporaryDirectory() as folder:
        cell = direct_cell(dataclasses.replace(load_sim_config(preset=preset), seed=seed), Path(folder))
        settings = plan_settings(cell)
        recorder = RecordingCell(cell, settings.marked_sweep_step_mm)
        grid = grid_targets(settings.grid_per_side, settings.grid_size_mm)
        asyncio.run(procedure.run_plate(recorder, settings, grid, lambda *_: None, (0.0, 1.0), want_truth=False))
    return recorder.clouds, recorder.pose, settings, len(grid)


def timed_run(clouds, pose, settings, count: int, sweep_s: float, pipelined: bool) -> tuple[float, float]:
    """Wall time of the marked-plate stage and from the end of the last sweep to its result, s."""
    cell = TimedReplayCell(clouds, sweep_s, pipelined)
    began = time.perf_counter()
    found = asyncio.run(procedure.measure_marked_plate(cell, settings, pose, count, lambda *_: None))
    ended = time.perf_counter()
    if len(found) != len(clouds):
        raise RuntimeError(f"{len(found)} measurements for {len(clouds)} sweeps")
    return ended - began, ended - cell.sweeps_done_at[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="paper_like")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--time-scale", type=float, default=1.0)
    parser.add_argument("--speed-mm-s", type=float, default=15.0)
    args = parser.parse_args()
    if args.repeats < 1 or not args.time_scale > 0.0 or not args.speed_mm_s > 0.0:
        parser.error("--repeats must be at least 1, --time-scale and --speed-mm-s positive")
    clouds, pose, settings, count = record(args.preset, args.seed)
    config = load_sim_config(preset=args.preset)
    sweep_s = args.time_scale * config.sweep_length_mm / args.speed_mm_s
    print(f"{args.preset} seed {args.seed}: {len(clouds)} marked sweeps of {count} fiducials, each sweep "
          f"{sweep_s:.2f} s (time scale {args.time_scale:g}); medians of {args.repeats}")
    results: dict[bool, list[tuple[float, float]]] = {True: [], False: []}
    for _ in range(args.repeats):
        for pipelined in (True, False):
            results[pipelined].append(timed_run(clouds, pose, settings, count, sweep_s, pipelined))
    sweeps_s = len(clouds) * sweep_s
    print(f"{'mode':>10s} {'stage wall s':>12s} {'over the sweeps s':>17s} {'last sweep to result s':>22s}")
    for pipelined in (True, False):
        stage = statistics.median(r[0] for r in results[pipelined])
        tail = statistics.median(r[1] for r in results[pipelined])
        print(f"{'pipelined' if pipelined else 'sequential':>10s} {stage:12.2f} {stage - sweeps_s:17.2f} {tail:22.2f}")


if __name__ == "__main__":
    main()
