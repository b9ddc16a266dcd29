"""/diagnostics (diagnostic_msgs) from a node: one status, published at 1 Hz.

The standard aggregator and rqt_robot_monitor read ``/diagnostics`` (absolute: one topic for the
whole system, whatever the node's namespace).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import Callable, Mapping

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from gls_calibration.calibration.record import record_identity
from gls_calibration.ros.base import GlsNode

PERIOD_S = 1.0
LEVELS = {"ok": DiagnosticStatus.OK, "warn": DiagnosticStatus.WARN, "error": DiagnosticStatus.ERROR}


@dataclass
class Health:
    """What a node reports: level ("ok", "warn", "error"), one line, and named values."""

    level: str
    message: str
    values: dict[str, object] = field(default_factory=dict)


def publish_diagnostics(node: GlsNode, health: Callable[[], Health]) -> None:
    """Publish ``health()`` on /diagnostics every second, named after the node."""
    publisher = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
    name = f"{node.get_namespace().strip('/')}/{node.get_name()}".strip("/")

    def tick() -> None:
        state = health()
        status = DiagnosticStatus(level=LEVELS[state.level], name=name, message=state.message,
                                  hardware_id="gls",
                                  values=[KeyValue(key=key, value=str(value)) for key, value in state.values.items()])
        array = DiagnosticArray(status=[status])
        array.header.stamp = node.get_clock().now().to_msg()
        publisher.publish(array)
    node.create_timer(PERIOD_S, tick)


NOMINAL_SUMMARY = {"active_calibration_id": "nominal", "model_type": "none (nominal model)"}


def record_summary(record: Mapping) -> dict[str, object]:
    """Return the diagnostic values of the active calibration's record.

    Diagnostic values of the active calibration's record: id, creation time, model types and
    the RMS measured last; :func:`with_age` turns the creation time into an age.
    """
    content_hash, created = record_identity(record)
    values: dict[str, object] = {
        "active_calibration_id": content_hash, "created_s": created.timestamp(),
        "model_type": "+".join(str(model.get("type")) for model in record["models"]) or "none"}
    iterations = record.get("metrics", {}).get("iterations") or []
    rms = iterations[-1].get("full", {}).get("rms_abs_mm") if iterations else None
    if rms is not None:
        values["measured_rms_mm"] = f"{rms:.4f}"
    return values


def with_age(summary: Mapping[str, object]) -> dict[str, object]:
    """``summary`` with its creation time replaced by the age now (s)."""
    values = dict(summary)
    created = values.pop("created_s", None)
    if created is not None:
        values["active_calibration_age_s"] = f"{time.time() - float(created):.0f}"
    return values
