"""Where a calibration's time goes: wall time per stage of the calibrate flow, and CPU per node.

The calibrate flow reports its stage with every progress message (``procedure.Progress``:
``sweep_plain``, ``plate_pose``, ``marking``, ``sweep_marked``, ``measurement``, ``deviations``,
``training``, ``done``). :class:`StageClock` wraps that callback and stamps each message; a stage's
wall time is the time from its first message to the next message of another stage, summed over the
plates. ``last_sweep_to_result_s`` is the time from the end of the last marked-plate sweep (the
first message after the last ``sweep_marked`` one) to the flow's result (its last message): what a
user waits for once the cell has stopped moving, before the report is written and the calibration
activated.

CPU per node is only visible where the nodes share a process (``gls-sim-cell``): each node spins in
a thread of its own (``ros.runtime.NodeThreads``) whose CPU clock :func:`thread_cpu_s` reads. Work done
in threads no node owns (OpenCV's pool, which did 2.7 s of the fiducial node's 20 s in the main job,
a node's worker threads, DDS) is read apart by :func:`unowned_threads_cpu_s`.

Example
-------
>>> ticks = iter([0.0, 1.0, 4.0, 4.5, 6.0])
>>> clock = StageClock(clock_s=lambda: next(ticks))
>>> report = clock.wrap(lambda stage, part, text: None)
>>> for stage in ("sweep_plain", "sweep_marked", "measurement", "training", "done"):
...     report(stage, 0.0, "")
>>> times = clock.times()
>>> times.wall_s["sweep_marked"], times.last_sweep_to_result_s
(3.0, 2.0)
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
import os
import threading
import time
from typing import Callable, Iterable, Mapping

SWEEP_STAGE = "sweep_marked"


@dataclass(frozen=True)
class StageTimes:
    """Return the wall time per stage (s) and from the last marked-plate sweep to the result (s).

    Wall time per stage (s, in the order the stages first came) and from the last marked-plate
    sweep to the result (s; NaN without a marked-plate sweep followed by another message);
    ``last_sweep_end_s`` is the clock's reading at that sweep's end (NaN likewise).
    """

    wall_s: Mapping[str, float] = field(default_factory=dict)
    last_sweep_to_result_s: float = math.nan
    # the clock's reading (time.monotonic by default) as the last marked-plate sweep ended: what a later
    # step (the activation) measures its own "since the last profile" from
    last_sweep_end_s: float = math.nan


class StageClock:
    """Stamps the progress messages of one calibrate flow (``clock_s``: a monotonic clock in s)."""

    def __init__(self, clock_s: Callable[[], float] = time.monotonic) -> None:
        self._clock_s = clock_s
        self._events: list[tuple[str, float]] = []
        self._lock = threading.Lock()

    def wrap(self, progress: Callable[[str, float, str], None]) -> Callable[[str, float, str], None]:
        """``progress`` that first stamps each message's stage."""
        def stamped(stage: str, fraction: float, text: str) -> None:
            with self._lock:
                self._events.append((stage, self._clock_s()))
            progress(stage, fraction, text)
        return stamped

    def times(self) -> StageTimes:
        """Return the stage times of the messages so far."""
        with self._lock:
            events = list(self._events)
        wall: dict[str, float] = {}
        for (stage, began), (_, ended) in zip(events, events[1:]):
            wall[stage] = wall.get(stage, 0.0) + (ended - began)
        sweeps = [index for index, (stage, _) in enumerate(events) if stage == SWEEP_STAGE]
        last = ended = math.nan
        if sweeps and sweeps[-1] + 1 < len(events):
            ended = events[sweeps[-1] + 1][1]
            last = events[-1][1] - ended
        return StageTimes(wall, last, ended)


class ValidationCpuMark:
    """Reads the nodes' CPU when the calibrate flow turns from training to its validation plate.

    Fed the stage of every progress message in order (:meth:`observe`); each turn from ``training``
    to ``sweep_plain`` (the next plate's first sweep) reads ``read_cpu_s()``, so with a validation
    plate the last reading is taken as that plate begins: the CPU of the training plates and their
    training is that reading, the rest (the validation plate, the report, the activation) is the
    total minus it. Without a validation plate the readings mean nothing (a second training plate
    also follows ``training``): use :attr:`at_validation_s` only when the run validates.

    Parameters
    ----------
    read_cpu_s : callable
        ``read_cpu_s() -> dict[str, float]``: CPU (s) per node so far.

    Examples
    --------
    >>> readings = iter([{"fiducial": 4.0}])
    >>> mark = ValidationCpuMark(lambda: next(readings))
    >>> for stage in ("sweep_plain", "sweep_marked", "training", "sweep_plain", "sweep_marked", "done"):
    ...     mark.observe(stage)
    >>> mark.at_validation_s
    {'fiducial': 4.0}
    """

    def __init__(self, read_cpu_s: Callable[[], Mapping[str, float]]) -> None:
        self._read_cpu_s = read_cpu_s
        self._last_stage = ""
        self.at_validation_s: Mapping[str, float] | None = None

    def observe(self, stage: str) -> None:
        """Take the stage of the next progress message (a repeated stage is one message more of it)."""
        if self._last_stage == "training" and stage == "sweep_plain":
            self.at_validation_s = dict(self._read_cpu_s())
        self._last_stage = stage


def thread_cpu_s(thread: threading.Thread) -> float:
    """Return the CPU time (s) a running thread has used so far; NaN when it cannot be told.

    CPU time (s) a running thread has used so far; NaN when it has ended or the platform cannot
    tell (``time.pthread_getcpuclockid``).
    """
    if not thread.is_alive():    # the ident of an ended thread names no clock (pthread: undefined)
        return math.nan
    try:
        return time.clock_gettime(time.pthread_getcpuclockid(thread.ident))
    except (AttributeError, OSError, TypeError, ProcessLookupError):
        return math.nan


def unowned_threads_cpu_s(owned: Iterable[threading.Thread]) -> float:
    """Return the CPU time (s) used so far by this process's threads other than ``owned`` and the main thread.

    Those threads are the libraries' (OpenCV's pool, BLAS's, DDS's) and any Python thread not in
    ``owned``; a thread that has ended no longer counts. Read from ``/proc/self/task`` (Linux).

    Parameters
    ----------
    owned : iterable of threading.Thread
        Threads whose CPU is counted elsewhere (the nodes' executor threads).

    Returns
    -------
    float
        Their CPU time (user and system, s, at the kernel's clock-tick resolution); NaN where the
        platform does not tell.

    Examples
    --------
    >>> unowned_threads_cpu_s([threading.current_thread()]) >= 0.0
    True
    """
    skip = {thread.native_id for thread in owned} | {threading.main_thread().native_id}
    try:
        tick_s = 1.0 / os.sysconf("SC_CLK_TCK")
        tasks = os.listdir("/proc/self/task")
    except (OSError, ValueError, AttributeError):
        return math.nan
    total_s = 0.0
    for task in tasks:
        if int(task) in skip:
            continue
        try:
            with open(f"/proc/self/task/{task}/stat", encoding="ascii") as stat:
                # fields after the command (which may hold spaces): state is the 1st, utime the 12th, stime the 13th
                fields = stat.read().rsplit(")", 1)[1].split()
        except OSError:     # the thread ended meanwhile
            continue
        total_s += (int(fields[11]) + int(fields[12])) * tick_s
    return total_s
