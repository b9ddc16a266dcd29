"""A node's parameter as one record (name, default, description, range, kind).

The node declares it from the record and the offline tools check a parameter file's value against
the same record (no rclpy here).

Ranges are ROS's: inclusive, and a side left open is bounded by what ``GlsNode.declare`` puts in the
descriptor (``INTEGER_LIMITS``, ``FLOAT_LIMITS``). Types are ROS's too: a parameter file's ``5`` is an
integer and ``5.0`` a double, and a node refuses one for the other.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Optional

from gls_calibration.common.validation import as_integer_at_least

INTEGER_LIMITS = (-(2 ** 31), 2 ** 31 - 1)   # the range an integer parameter gets when a side is open
FLOAT_LIMITS = (-1e308, 1e308)               # ...and a double one
KINDS = ("integer", "number", "numbers", "flag")


@dataclass(frozen=True)
class ParameterSpec:
    """One parameter of a node.

    ``kind``: ``integer``, ``number`` (a double), ``flag`` (a bool) or ``numbers`` (a list of finite
    doubles, positive or, with ``minimum=0.0``, not negative; ROS ranges do not apply to lists, the
    node checks them at start).
    """

    name: str
    default: Any
    description: str
    minimum: Optional[float] = None
    maximum: Optional[float] = None
    kind: str = "number"
    allow_empty: bool = False          # numbers: [] is a valid value

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        if self.kind not in KINDS:
            raise ValueError(f"parameter {self.name}: kind must be one of {', '.join(KINDS)}, got {self.kind!r}")

    @property
    def bounds(self) -> Optional[tuple[float, float]]:
        """Return the inclusive range of an integer or number parameter with a range (None otherwise)."""
        if self.kind not in ("integer", "number") or (self.minimum is None and self.maximum is None):
            return None
        low, high = INTEGER_LIMITS if self.kind == "integer" else FLOAT_LIMITS
        return (low if self.minimum is None else self.minimum, high if self.maximum is None else self.maximum)

    @property
    def positive(self) -> bool:
        """numbers: every one must be > 0 (>= 0 when ``minimum`` is 0.0)."""
        return self.minimum != 0.0

    def check(self, value: Any, what: str) -> Any:
        """Return ``value`` of a parameter file when the node would take it; ValueError otherwise.

        ``value`` is as YAML reads it; the ValueError names ``what`` and the parameter.
        """
        key = f"{what} {self.name!r}"
        if self.kind == "flag":
            if not isinstance(value, bool):
                raise ValueError(f"{key} must be true or false, got {value!r}")
            return value
        if self.kind == "numbers":
            return self._check_numbers(value, key)
        if self.kind == "integer":
            low, high = self.bounds or INTEGER_LIMITS
            number = as_integer_at_least(value, key, int(low))
            high = int(high)
        else:
            if isinstance(value, int) and not isinstance(value, bool):
                raise ValueError(f"{key} must be a floating-point number (ROS reads {value!r} as an integer: "
                                 f"write {value!r}.0), got {value!r}")
            if not isinstance(value, float) or not math.isfinite(value):
                raise ValueError(f"{key} must be a finite number, got {value!r}")
            low, high = self.bounds or FLOAT_LIMITS
            number = value
            if number < low:
                raise ValueError(f"{key} must be >= {low:g}, got {number:g}")
        if number > high:
            shown = (f"{high}", f"{number}") if self.kind == "integer" else (f"{high:g}", f"{number:g}")
            raise ValueError(f"{key} must be at most {shown[0]}, got {shown[1]}")
        return number

    def _check_numbers(self, value: Any, key: str) -> tuple[float, ...]:
        if not isinstance(value, list) or (not value and not self.allow_empty):
            raise ValueError(f"{key} must be a {'' if self.allow_empty else 'non-empty '}list of numbers, "
                             f"got {value!r}")
        if any(isinstance(item, int) and not isinstance(item, bool) for item in value):
            raise ValueError(f"{key} must be a list of floating-point numbers (ROS reads a list holding an "
                             f"integer as integers: write 5.0 for 5), got {value!r}")
        if not all(isinstance(item, float) and math.isfinite(item) for item in value) \
                or any(item <= 0.0 if self.positive else item < 0.0 for item in value):
            raise ValueError(f"{key} must hold finite {'positive' if self.positive else 'non-negative'} numbers, "
                             f"got {value!r}")
        return tuple(value)
