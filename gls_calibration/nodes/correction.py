"""correction: serves ``correct_setpoints`` and ``correction/load`` (hot reload)."""
from __future__ import annotations

from dataclasses import fields
from pathlib import Path
from typing import Optional

import numpy as np

from gls_calibration.nodes import conversions
from gls_calibration.calibration_record import correction_from_record
from gls_calibration.correction import CorrectedSetpoints, Correction
from gls_calibration.nodes.base import GlsNode, answers_errors, run_node
from gls_calibration.nodes.head_parameters import declare_head_geometry
from gls_calibration.persistence import CalibrationFileError, CalibrationStore
from gls_calibration.validation import as_coordinate_arrays
from gls_calibration_msgs.srv import Calibrate, CorrectSetpoints, LoadCalibration

MANAGER_CHECK_PERIOD_S = 0.5


class CorrectionNode(GlsNode):
    """Corrects setpoints with the loaded calibration; the nominal model when there is none.

    Requests are served by several executor threads and large ones are computed in chunks,
    yielding between chunks, so that single-target requests of other clients are answered meanwhile.
    """

    def __init__(self, **kwargs) -> None:
        super().__init__("correction", **kwargs)
        self.geometry = declare_head_geometry(self)
        self.store = CalibrationStore(Path(self.declare("calibration_dir", "calibrations",
                                                        "folder of the calibration store")))
        self.max_targets = self.declare(
            "max_targets", 1_000_000, "most targets in one correct_setpoints request (about 300 bytes of "
            "memory each while served)", minimum=1, maximum=10_000_000, read_only=True)
        # See NodeThreads: with more than one thread, taking and answering a large batch does not hold up
        # single-target requests (bench_concurrency.py).
        self.executor_threads = self.declare("executor_threads", 4, "threads of the node's executor",
                                             minimum=1, maximum=16, read_only=True)
        self.chunk_targets = self.declare("chunk_targets", 20_000, "targets computed between two chances for "
                                          "other requests to be served", minimum=100, maximum=10_000_000)
        self.correction: Optional[Correction] = Correction(self.geometry)
        self.file = ""
        self.problem = ""
        self._load("", keep_serving=False)
        self.create_service(CorrectSetpoints, "correct_setpoints", self.on_correct,
                            callback_group=self.reentrant_group)
        self.create_service(LoadCalibration, "correction/load", self.on_load)
        # A file other than the active one is served only for the run that loaded it (a candidate under
        # validation): when no calibration manager is left in the graph, the active one is served again.
        self.manager = self.create_client(Calibrate, "calibrate")
        self.create_timer(MANAGER_CHECK_PERIOD_S, self._check_candidate)

    def _check_candidate(self) -> None:
        if self.correction is None or self.manager.service_is_ready():
            return
        try:
            active = self.store.active_path()
        except CalibrationFileError:  # an unusable pointer: nothing better to serve (logged at load)
            return
        if self.file and (active is None or Path(self.file).resolve() != active.resolve()):
            self.get_logger().warning(f"no calibration manager any more: {self.file} was a candidate; "
                                      "serving the active calibration again")
            self._load("", keep_serving=True)

    def _load(self, file: str, *, keep_serving: bool) -> tuple[bool, str]:
        """Load ``file`` of the store (empty: the active calibration); (loaded, message).

        With ``keep_serving``, a refused file leaves the calibration that was serving in use; at
        start-up (nothing serving yet) corrections are refused with the reason until a good load.
        """
        try:
            path = self.store.confined(file) if file else self.store.active_path()
            if path is None:
                correction = Correction(self.geometry)
            else:
                correction = correction_from_record(self.store.load(path), self.geometry)
        except (CalibrationFileError, ValueError, OSError, RecursionError, MemoryError) as error:
            problem = f"{'calibration file ' + file if file else 'active calibration'} refused: {error}"
            self.get_logger().error(problem)
            if keep_serving and self.correction is not None:
                return False, f"{problem}; still serving {self.file or 'the nominal model'}"
            self.correction, self.file, self.problem = None, file, problem
            return False, problem
        self.correction, self.file, self.problem = correction, "" if path is None else str(path), ""
        if path is None:
            self.get_logger().info("no calibration in the store: nominal model")
            return True, "no calibration in the store: nominal model in use"
        self.get_logger().info(f"calibration loaded from {path}")
        return True, f"calibration loaded from {path}"

    def on_load(self, request, response):
        """Hot reload; a refused file leaves the serving calibration in use."""
        response.success, response.message = self._load(request.file, keep_serving=True)
        response.file = self.file
        return response

    @answers_errors(ValueError)
    async def on_correct(self, request, response):
        """Correct the targets; ``success=false`` and a message naming the problem on bad input."""
        correction = self.correction
        if correction is None:
            response.success = False
            response.message = f"corrections refused: {self.problem}"
            return response
        count = len(request.x)
        if count > self.max_targets:
            response.success = False
            response.message = (f"{count} targets refused: at most {self.max_targets} per request "
                                "(parameter max_targets); split the request")
            return response
        x, y, z = as_coordinate_arrays(request.x, request.y, request.z if len(request.z) else None)
        parts = []
        for start in range(0, max(count, 1), self.chunk_targets):
            if start:
                await self.yield_to_executor()
            end = start + self.chunk_targets
            parts.append(correction.correct(x[start:end], y[start:end], z[start:end]))
        result = parts[0] if len(parts) == 1 else CorrectedSetpoints(
            *(np.concatenate([getattr(part, field.name) for part in parts]) for field in fields(CorrectedSetpoints)))
        conversions.setpoints_to_response(result, response)
        unreachable = int((~result.within_limits).sum())
        if unreachable:
            first = int((~result.within_limits).argmax())
            response.success = False
            response.message = (f"{unreachable} target(s) beyond the mirror limits or the focus range "
                                 f"(first at index {first}); see within_limits")
        else:
            response.success = True
            response.message = "corrected" if self.file else "no calibration loaded: nominal model"
        return response


def main(args=None) -> None:
    """Console script ``gls-correction``."""
    run_node(CorrectionNode, args)
