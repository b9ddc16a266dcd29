"""The time budget's clock: wall time per stage of the calibrate flow and CPU per thread."""
import json
import math
import subprocess
import sys
import threading
import time

import pytest

from gls_calibration.common.time_budget import StageClock, ValidationCpuMark, thread_cpu_s


def stamped(stages_and_times):
    ticks = iter(t for _, t in stages_and_times)
    seen = []
    clock = StageClock(clock_s=lambda: next(ticks))
    report = clock.wrap(lambda stage, part, text: seen.append(stage))
    for stage, _ in stages_and_times:
        report(stage, 0.5, "text")
    return clock.times(), seen


def test_stage_times_sum_over_plates_and_end_at_the_result():
    times, seen = stamped([("sweep_plain", 0.0), ("sweep_marked", 2.0), ("measurement", 5.0),
                           ("sweep_marked", 6.0), ("measurement", 10.0), ("training", 11.0),
                           ("sweep_plain", 12.0), ("sweep_marked", 13.0), ("measurement", 17.0),
                           ("done", 19.5)])
    assert seen[-1] == "done"          # the wrapped callback still gets every message
    assert times.wall_s == {"sweep_plain": 3.0, "sweep_marked": 11.0, "measurement": 4.5, "training": 1.0}
    assert times.last_sweep_to_result_s == 2.5      # from the end of the last sweep (17 s) to the result
    assert times.last_sweep_end_s == 17.0           # the clock's reading then, for the activation's time


def test_without_a_finished_marked_sweep_there_is_no_last_sweep_time():
    assert math.isnan(stamped([("sweep_plain", 0.0), ("plate_pose", 1.0)])[0].last_sweep_to_result_s)
    assert math.isnan(stamped([("sweep_plain", 0.0), ("sweep_marked", 1.0)])[0].last_sweep_to_result_s)
    empty = StageClock().times()
    assert empty.wall_s == {} and math.isnan(empty.last_sweep_to_result_s) and math.isnan(empty.last_sweep_end_s)


PLATE = ("sweep_plain", "sweep_plain", "plate_pose", "marking", "sweep_marked", "measurement", "sweep_marked",
         "measurement", "deviations")


@pytest.mark.parametrize("stages, reading", [
    # one training plate, then the validation plate: read as the validation plate begins
    (PLATE + ("training",) + PLATE + ("done",), 2),
    # two training plates: the reading at the second plate is replaced by the validation plate's
    (PLATE + ("training",) + PLATE + ("training",) + PLATE + ("done",), 3),
    # the active calibration's plate after the validation plate follows "deviations", not "training"
    (PLATE + ("training",) + PLATE + PLATE + ("done",), 2),
    # nothing follows the training: no reading
    (PLATE + ("training", "done"), None),
])
def test_the_cpu_is_read_when_the_validation_plate_begins(stages, reading):
    calls = []

    def read_cpu_s():
        calls.append(len(calls) + 2)
        return {"fiducial_measurement": float(calls[-1])}
    mark = ValidationCpuMark(read_cpu_s)
    for stage in stages:
        mark.observe(stage)
    expected = None if reading is None else {"fiducial_measurement": float(reading)}
    assert mark.at_validation_s == expected


def test_thread_cpu_counts_a_busy_thread_and_not_an_idle_one():
    stop = threading.Event()

    def busy():
        while not stop.is_set():
            sum(range(1000))

    workers = [threading.Thread(target=busy), threading.Thread(target=stop.wait)]
    for worker in workers:
        worker.start()
    time.sleep(0.3)
    busy_cpu, idle_cpu = (thread_cpu_s(worker) for worker in workers)
    stop.set()
    for worker in workers:
        worker.join()
    assert busy_cpu > 0.05 and idle_cpu < 0.02
    assert math.isnan(thread_cpu_s(workers[0]))       # ended: its clock is gone


# Run in a fresh interpreter: in a whole test run, threads left by earlier tests (executors, DDS) may
# end during the reading, and an ended thread's CPU leaves the sum.
UNOWNED_CPU_PROBE = """
import json, os, threading, time
from gls_calibration.common.time_budget import thread_cpu_s, unowned_threads_cpu_s
stop = threading.Event()

def busy():
    while not stop.is_set():
        sum(range(1000))

owned, unowned = threading.Thread(target=busy), threading.Thread(target=busy)
before_s = unowned_threads_cpu_s([owned])
for worker in (owned, unowned):
    worker.start()
time.sleep(0.6)
counted_s = unowned_threads_cpu_s([owned]) - before_s
unowned_s, owned_s = thread_cpu_s(unowned), thread_cpu_s(owned)
alive_s = unowned_threads_cpu_s([])
stop.set()
for worker in (owned, unowned):
    worker.join()
# join() returns when Python is done with a thread, a moment before the kernel lists it no more
ids = {str(worker.native_id) for worker in (owned, unowned)}
deadline = time.monotonic() + 5.0
while ids & set(os.listdir("/proc/self/task")) and time.monotonic() < deadline:
    time.sleep(0.01)
print(json.dumps(dict(before_s=before_s, counted_s=counted_s, unowned_s=unowned_s, owned_s=owned_s,
                      alive_s=alive_s, listed=sorted(ids & set(os.listdir("/proc/self/task"))),
                      ended_s=unowned_threads_cpu_s([]))))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/task")
def test_unowned_thread_cpu_counts_the_threads_no_node_owns_and_not_the_owned_ones():
    done = subprocess.run([sys.executable, "-c", UNOWNED_CPU_PROBE], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    read = json.loads(done.stdout)
    assert read["listed"] == []
    # the kernel's clock ticks (10 ms) make the /proc reading coarser than the thread clocks
    assert read["unowned_s"] > 0.1 and read["owned_s"] > 0.1
    assert read["counted_s"] == pytest.approx(read["unowned_s"], abs=0.05)
    # nothing owned: both busy threads count
    assert read["alive_s"] - read["before_s"] >= read["counted_s"] + read["owned_s"] - 0.1
    # ended threads no longer count: the total falls by about their CPU
    assert read["ended_s"] < read["alive_s"] - 0.5 * (read["unowned_s"] + read["owned_s"])


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_gls_sim_cell_writes_and_prints_the_time_budget(tmp_path):
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, "-m", "gls_calibration.cli.sim_cell", "--out", str(out), "--grid", "3",
                           "--no-validate", "--sweep-plan", "0+", "--measurement", "ideal", "--no-reference-check"],
                          capture_output=True, text=True, timeout=800)
    assert done.returncode == 0, done.stderr[-3000:]
    budget = json.loads((out / "time_budget.json").read_text())
    summary = json.loads((out / "summary.json").read_text())
    assert budget["stage_wall_s"] == summary["stage_wall_s"] and budget["cell_time_s"] == summary["cell_time_s"]
    assert {"sweep_plain", "plate_pose", "marking", "sweep_marked", "measurement", "training"} <= set(
        budget["stage_wall_s"])
    assert budget["last_sweep_to_result_s"] == summary["last_sweep_to_result_s"] > 0.0
    # the activation comes after the result and the report: summary.json is written again with it
    assert summary["last_profile_to_activation_s"] > summary["last_sweep_to_result_s"]
    assert budget["last_profile_to_activation_s"] == summary["last_profile_to_activation_s"]
    cpu = budget["cpu_s_by_node"]
    # every node of the cell has its thread's CPU; the ones that did work have some
    assert {"calibration_manager", "stream_acquisition", "fiducial_measurement", "sim_robot",
            "sim_line_scanner"} <= set(cpu)     # the split cell, gls-sim-cell's default
    assert cpu["fiducial_measurement"] > 0.0 and cpu["sim_robot"] > 0.0 and cpu["sim_line_scanner"] > 0.0
    # the threads no node owns (OpenCV's pool, DDS) are read and counted with the pipeline
    assert "library threads" in cpu and cpu["library threads"] >= 0.0
    pipeline = sum(value for name, value in cpu.items() if not name.startswith("sim_"))
    assert budget["compute_cpu_s"] == pytest.approx(pipeline) == summary["compute_cpu_s"]
    assert budget["process_cpu_s"] >= budget["compute_cpu_s"] + budget["simulation_cpu_s"]
    # no validation plate: no split of the pipeline's CPU (it would be a second training plate's)
    assert budget["compute_cpu_s_before_validation"] is None and budget["compute_cpu_s_from_validation"] is None
    assert "time budget: cell time" in done.stdout and "CPU of the pipeline" in done.stdout
    assert "to the activation" in done.stdout
    assert "time budget (wall, this run): sweep_plain" in (out / "report.md").read_text()
