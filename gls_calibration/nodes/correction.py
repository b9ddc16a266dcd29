"""correction: serves ``correct_setpoints`` with the store's ACTIVE calibration.

And ``correction/load`` (reload the active calibration, e.g. after an activation); its companion
node ``correction_batch`` (same process, same calibration, its own executor thread) serves the same
as ``correct_setpoints_batch`` for large requests.

It never serves anything else: a calibration run evaluates its candidate inside the calibration
manager, so other nodes are never corrected by a calibration that has not passed. Every answer
names the calibration that gave it (content hash and creation time).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, Optional

import numpy as np

from gls_calibration.calibration.record import correction_from_record, record_identity
from gls_calibration.calibration.record_file import CalibrationFileError
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.common.validation import as_coordinate_arrays
from gls_calibration.correction.setpoints import Correction
from gls_calibration.ros import conversions
from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.diagnostics import NOMINAL_SUMMARY, Health, publish_diagnostics, record_summary, with_age
from gls_calibration.ros.head_parameters import HEAD_PARAMETERS, declare_head_geometry, head_geometry_from
from gls_calibration.ros.runtime import run_node
from gls_calibration.ros.service_errors import answers_errors
from gls_calibration_msgs.srv import CorrectSetpoints, LoadCalibration

NOMINAL_ID = "nominal"


@dataclass(frozen=True)
class Served:
    """What answers corrections, swapped as one value.

    The batch service reads it from another thread. It holds the correction (None: refused with
    ``problem``), its id and creation time, the file it came from ("" for the nominal model) and its
    description in the diagnostics.
    """

    correction: Optional[Correction]
    calibration_id: str = NOMINAL_ID
    created: Optional[datetime] = None
    problem: str = ""
    file: str = ""
    summary: Mapping[str, object] = field(default_factory=lambda: dict(NOMINAL_SUMMARY))


class CorrectionNode(GlsNode):
    """Corrects setpoints with the active calibration; the nominal model when there is none.

    Single-target requests are answered on this node's own single-threaded executor; large requests
    go to the companion node :class:`BatchCorrectionNode` on another thread, so that taking,
    computing and answering them never queues the single targets behind them. Large requests are
    computed in chunks either way, yielding between chunks.
    """

    def __init__(self, **kwargs) -> None:
        super().__init__("correction", **kwargs)
        self.geometry = declare_head_geometry(self, dynamic=True)
        self.store = CalibrationStore(Path(self.declare("calibration_dir", "calibrations",
                                                        "folder of the calibration store")))
        self.max_targets = self.declare(
            "max_targets", 1_000_000, "most targets in one correct_setpoints request (about 300 bytes of "
            "memory each while served)", minimum=1, maximum=10_000_000)
        self.chunk_targets = self.declare("chunk_targets", 50_000, "targets computed between two chances for "
                                          "other requests to be served", minimum=100, maximum=10_000_000)
        self.workers = self.declare("workers", 0, "threads that share a large request (0: every CPU the "
                                    "process may use; the answer is the same whatever their number)",
                                    minimum=0, maximum=256) or None
        self.served = Served(Correction(self.geometry))
        self._load(keep_serving=False)
        # A new head geometry changes every answer: reload the active calibration with it.
        self.apply_parameter_changes(HEAD_PARAMETERS, self._apply_head)
        # The same service twice: Fast DDS hands every answer of a service to all of its clients (each
        # drops those not its own) in order, so a 42 MB answer on correct_setpoints would hold up the
        # single-target answers of every other client for up to seconds (bench_concurrency.py).
        # Large requests go to correct_setpoints_batch, whose answers travel on their own writer and
        # are computed on the companion's thread: a multi-threaded executor here instead cost every
        # single-target call about 0.25 ms (bench_services.py).
        self.create_service(CorrectSetpoints, "correct_setpoints", self.on_correct, callback_group=self.reentrant_group)
        self.create_service(LoadCalibration, "correction/load", self.on_load)
        self.companions = (BatchCorrectionNode(self, context=self.context),)
        publish_diagnostics(self, self.health)

    def health(self) -> Health:
        """Return what /diagnostics says about this node."""
        served = self.served
        values = {"state": "failed" if served.problem else "serving",
                  "calibration_file": served.file or "none"} | with_age(served.summary)
        if served.problem:
            return Health("error", served.problem, values)
        return Health("ok", f"serving calibration {served.calibration_id}", values)

    def _apply_head(self, values: dict[str, Any]) -> Optional[str]:
        try:
            geometry = head_geometry_from(values)
        except ValueError as error:
            return str(error)
        previous = self.geometry
        self.geometry = geometry
        loaded, message = self._load(keep_serving=True)
        if not loaded:
            self.geometry = previous
            return f"head geometry refused: {message}"
        self.get_logger().info(f"head geometry changed: {geometry}; {message}")
        return None

    def _load(self, *, keep_serving: bool) -> tuple[bool, str]:
        """Load the store's active calibration; (loaded, message).

        With ``keep_serving``, a refused file leaves the calibration that was serving in use; at
        start-up (nothing serving yet) corrections are refused with the reason until a good load.
        """
        try:
            path = self.store.active_path()
            if path is None:
                self._serve(Correction(self.geometry), "", "")
                self.get_logger().info("no calibration in the store: nominal model")
                return True, "no calibration in the store: nominal model in use"
            record = self.store.load(path)
            correction = correction_from_record(record, self.geometry)
        except (CalibrationFileError, ValueError, OSError, RecursionError, MemoryError) as error:
            problem = f"active calibration refused: {error}"
            self.get_logger().error(problem)
            if keep_serving and self.served.correction is not None:
                return False, f"{problem}; still serving {self.served.file or 'the nominal model'}"
            self._serve(None, str(self.store.pointer_path), problem)
            return False, problem
        self._serve(correction, str(path), "", *record_identity(record), summary=record_summary(record))
        # Off the executor: a large request arriving meanwhile waits for it, nothing else does. An owned
        # thread, joined before the node is destroyed (a stop right after a calibration aborted the process).
        self.start_worker(correction.prepare, "correction-prepare")
        self.get_logger().info(f"calibration {self.served.calibration_id} loaded from {path}")
        return True, f"calibration {self.served.calibration_id} loaded from {path}"

    def _serve(self, correction: Optional[Correction], file: str, problem: str,
               calibration_id: str = NOMINAL_ID, created: Optional[datetime] = None,
               summary: Optional[dict] = None) -> None:
        """Serve ``correction`` (None: refuse corrections with ``problem``).

        ``summary`` describes it in the diagnostics (default: the nominal model's).
        """
        if correction is None:
            self.served = Served(None, "", None, problem, file, {"active_calibration_id": "none"})
        else:
            self.served = Served(correction, calibration_id, created, problem, file,
                                 summary if summary is not None else dict(NOMINAL_SUMMARY))

    def on_load(self, request, response):
        """Reload the active calibration. A ``file`` must name the active one: nothing else is served."""
        if request.file:
            try:
                active = self.store.active_path()
            except CalibrationFileError as error:
                active, response.message = None, f"calibration store pointer is unusable: {error}"
            if active is None or Path(request.file).resolve() != active.resolve():
                response.success = False
                response.message = (f"{request.file} is not the active calibration of {self.store.directory}; "
                                    "only the active calibration is served (activate it first)")
                response.file = self.served.file
                return response
        response.success, response.message = self._load(keep_serving=True)
        response.file = self.served.file
        return response

    @answers_errors(ValueError)
    async def on_correct(self, request, response):
        """Correct the targets; ``success=false`` and a message naming the problem on bad input."""
        return await self.answer(self, request, response)

    async def answer(self, worker: GlsNode, request, response):
        """Fill ``response`` for ``request``, letting ``worker`` serve others between chunks.

        Fill ``response`` for ``request``; between chunks, ``worker`` (the node whose executor runs
        this) serves what else is waiting.
        """
        # One snapshot: a reload between chunks must not mix two calibrations in one answer.
        served = self.served
        correction = served.correction
        response.calibration_id = served.calibration_id
        if served.created is not None:
            response.calibration_created = conversions.time_to_msg(served.created.timestamp())
        if correction is None:
            response.success = False
            response.message = f"corrections refused: {served.problem}"
            return response
        count = len(request.x)
        if count > self.max_targets:
            response.success = False
            response.message = (f"{count} targets refused: at most {self.max_targets} per request "
                                "(parameter max_targets); split the request")
            return response
        x, y, z = as_coordinate_arrays(request.x, request.y, request.z if len(request.z) else None)
        # Each chunk is appended to the answer's arrays: nothing of the whole size is converted at once.
        answer = conversions.start_setpoints_response(response)
        for start in range(0, count, self.chunk_targets):
            if start:
                await worker.yield_to_executor()
            end = start + self.chunk_targets
            part = correction.correct(x[start:end], y[start:end], z[start:end], workers=self.workers)
            conversions.append_setpoints(answer, part)
        reachable = conversions.flag_array(answer["within_limits"])
        unreachable = count - int(np.count_nonzero(reachable))
        if unreachable:
            first = int(np.argmin(reachable))
            response.success = False
            response.message = (f"{unreachable} target(s) beyond the mirror limits or the focus range "
                                f"(first at index {first}); see within_limits")
        else:
            response.success = True
            response.message = "corrected" if served.file else "no calibration loaded: nominal model"
        return response


class BatchCorrectionNode(GlsNode):
    """``correct_setpoints_batch``: the answers of ``correct_setpoints`` on an executor of its own.

    ``correct_setpoints_batch``: the same answers as ``correct_setpoints`` (same calibration, same
    limits, from its owner), on an executor of its own.
    """

    def __init__(self, owner: CorrectionNode, **kwargs) -> None:
        super().__init__(f"{owner.get_name()}_batch", namespace=owner.get_namespace(), **kwargs)
        self.owner = owner
        self.create_service(CorrectSetpoints, "correct_setpoints_batch", self.on_correct,
                            callback_group=self.reentrant_group)

    @answers_errors(ValueError)
    async def on_correct(self, request, response):
        """Correct the targets with the owner's calibration; ``success=false`` and a message on bad input."""
        return await self.owner.answer(self, request, response)


def main(args=None) -> int:
    """Console script ``gls-correction``."""
    return run_node(CorrectionNode, args)
