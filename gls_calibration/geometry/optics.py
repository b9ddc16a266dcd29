"""Physical model of the galvo head: an exact vector ray trace with named physical effects.

The beam arrives along +y at the Y mirror pivot ``(-e, 0, d)``, is turned by the Y mirror (first)
towards +x, meets the X mirror (last) at its pivot ``(0, 0, d)`` and leaves along -z towards the
work plane ``z = 0`` (``gls`` frame, z towards the head). Reflections use ``r = v - 2 (v.n) n``
with mirror planes through their pivots (or displaced along their normal), so with every effect
zero :meth:`PhysicalHead.land` reproduces :func:`gls_calibration.geometry.kinematics.forward`.

Mirror conventions (zero mechanical angle, normals point to the reflecting side):

- Y mirror: normal ``(1, -1, 0)/sqrt(2)``, rotation axis +z, so a positive angle turns the beam
  towards +y.
- X mirror: normal ``(-1, 0, -1)/sqrt(2)``, rotation axis -y, so a positive angle turns the beam
  towards +x.

The model serves twice: as the truth head of the simulation and as the extended model that the
discrepancy workflow fits to measured deviations. Both refer to effects by the names of
:data:`gls_calibration.geometry.effect_table.EFFECT_TABLE` (parameters, units, typical size, plausible range).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
from types import MappingProxyType
from typing import Iterable, Mapping, Sequence

import numpy as np

from gls_calibration.common.validation import as_finite_array
from gls_calibration.geometry.effect_table import EFFECTS
from gls_calibration.geometry.kinematics import HeadGeometry

_SQRT_HALF = np.sqrt(0.5)
_Y_NORMAL = np.array([_SQRT_HALF, -_SQRT_HALF, 0.0])
_Y_AXIS = np.array([0.0, 0.0, 1.0])
_X_NORMAL = np.array([-_SQRT_HALF, 0.0, -_SQRT_HALF])


def effect_names() -> tuple[str, ...]:
    """All known effect names, in the order of :data:`EFFECTS`."""
    return tuple(EFFECTS)


def _check_effect_name(name: str) -> None:
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; known effects: {', '.join(EFFECTS)}")


def parameter_count(names: Iterable[str]) -> int:
    """Return the number of parameters of the listed effects (their flat vector length)."""
    names = list(names)
    for name in names:
        _check_effect_name(name)
    return sum(len(EFFECTS[name]) for name in names)


def parameter_labels(names: Iterable[str]) -> tuple[str, ...]:
    """``effect.parameter`` labels of the flat vector of the listed effects."""
    labels = []
    for name in names:
        _check_effect_name(name)
        labels.extend(f"{name}.{parameter}" for parameter in EFFECTS[name])
    return tuple(labels)


def _rotation_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rotation_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def plate_frame(tilt_x_rad: float = 0.0, tilt_y_rad: float = 0.0,
                delta_d_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Return the plate's rotation and origin for the plate_tilt and working_distance effects.

    The plate is turned first about gls x, then about gls y; its origin (the field centre) sits
    ``delta_d_mm`` below the nominal work plane. The rotation's third column is the plate normal.

    Parameters
    ----------
    tilt_x_rad, tilt_y_rad : float, default 0.0
        Tilt of the plate about gls x and then gls y, rad.
    delta_d_mm : float, default 0.0
        How far the plate's origin lies below the nominal work plane, mm.

    Returns
    -------
    rotation : numpy.ndarray, shape (3, 3)
        Plate -> gls rotation.
    origin : numpy.ndarray, shape (3,)
        The plate's origin in the gls frame, mm.

    Examples
    --------
    >>> rotation, origin = plate_frame(0.0, 0.0, 2.0)
    >>> rotation[:, 2], origin
    (array([0., 0., 1.]), array([ 0.,  0., -2.]))
    """
    rotation = _rotation_y(tilt_y_rad) @ _rotation_x(tilt_x_rad)
    return rotation, np.array([0.0, 0.0, -float(delta_d_mm)])


@dataclass(frozen=True)
class HeadEffects:
    """Values of named physical effects; absent effects are zero.

    ``values`` is stored read-only with float tuples.

    Parameters
    ----------
    values : mapping of str to tuple of float, optional
        Effect name of :data:`EFFECTS` -> its parameters (a tuple, or a bare number for
        one-parameter effects), in the units of the effect table.

    Raises
    ------
    ValueError
        If ``values`` is not a mapping, a name is unknown, a parameter is not finite or an effect has
        the wrong number of parameters.
    """

    values: Mapping[str, tuple[float, ...]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Validate the fields and store them normalised (ValueError on the first bad one)."""
        if not isinstance(self.values, Mapping):
            raise ValueError(f"effects must be a mapping of effect name to parameters, "
                             f"got {type(self.values).__name__}")
        clean: dict[str, tuple[float, ...]] = {}
        for name, parameters in self.values.items():
            expected = EFFECTS.get(name)
            if (expected is not None and type(parameters) is tuple and len(parameters) == len(expected)
                    and all(type(value) is float and math.isfinite(value) for value in parameters)):
                # already what the checks below make of it (the fits build effects from such tuples
                # at every residual evaluation: the array round trip was a seventh of their cost)
                clean[name] = parameters
                continue
            _check_effect_name(name)        # an unknown name (expected None) stops here
            flat = np.atleast_1d(as_finite_array(parameters, f"effect {name!r}"))
            if flat.ndim != 1 or flat.size != len(expected):
                raise ValueError(
                    f"effect {name!r} takes {len(expected)} parameter(s) ({', '.join(expected)}), got {flat.size}")
            clean[name] = tuple(float(value) for value in flat)
        object.__setattr__(self, "values", MappingProxyType(clean))

    def __hash__(self) -> int:
        """Hash the non-zero effects, as equality compares them."""
        return hash(tuple(sorted(self.nonzero().items())))

    def __eq__(self, other: object) -> bool:
        """Compare the non-zero effects: a zero effect equals an absent one."""
        if not isinstance(other, HeadEffects):
            return NotImplemented
        return self.nonzero() == other.nonzero()

    def nonzero(self) -> dict[str, tuple[float, ...]]:
        """Return the effects with at least one non-zero parameter."""
        return {name: values for name, values in self.values.items() if any(values)}

    def get(self, name: str) -> tuple[float, ...]:
        """Parameters of ``name`` (zeros when absent)."""
        _check_effect_name(name)
        return self.values.get(name, (0.0,) * len(EFFECTS[name]))

    @classmethod
    def from_vector(cls, names: Sequence[str], vector) -> "HeadEffects":
        """Effects from a flat parameter vector laid out as ``names`` (each in EFFECTS order)."""
        names = list(names)
        if len(set(names)) != len(names):
            raise ValueError(f"effect names must be unique, got {names}")
        expected = parameter_count(names)
        vector = np.atleast_1d(as_finite_array(vector, "vector"))
        if vector.ndim != 1 or vector.size != expected:
            raise ValueError(f"vector must hold {expected} value(s) for effects {names}, got {vector.size}")
        values, start = {}, 0
        for name in names:
            count = len(EFFECTS[name])
            values[name] = tuple(float(v) for v in vector[start:start + count])
            start += count
        return cls(values)

    def to_vector(self, names: Sequence[str]) -> np.ndarray:
        """Flat parameter vector of ``names`` (absent effects give zeros)."""
        parameter_count(names)
        parts = [self.get(name) for name in names]
        return np.array([value for part in parts for value in part], dtype=float)

    def replace(self, **changes) -> "HeadEffects":
        """Copy with some effects set (``replace(galvo_gain_x=0.01)``)."""
        values = dict(self.values)
        values.update(changes)
        return HeadEffects(values)

    def without(self, *names: str) -> "HeadEffects":
        """Copy with the listed effects removed (set to zero)."""
        for name in names:
            _check_effect_name(name)
        return HeadEffects({k: v for k, v in self.values.items() if k not in names})


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of (3, N) arrays (or a (3, 1) column): component layout keeps it fast."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _rotate(vector: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues rotation of one vector (3,) about a unit axis (3,) by per-point angles (N,) -> (3, N)."""
    cos = np.cos(angle)
    sin = np.sin(angle)
    # np.cross's products and differences, written out: np.cross spends most of its time on its axes
    cross = np.array([axis[1] * vector[2] - axis[2] * vector[1], axis[2] * vector[0] - axis[0] * vector[2],
                      axis[0] * vector[1] - axis[1] * vector[0]])[:, None]
    along = (axis * np.dot(axis, vector))[:, None]
    return vector[:, None] * cos + cross * sin + along * (1.0 - cos)


def _reflect(directions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    return directions - 2.0 * _dot(directions, normals) * normals


def _hit_plane(origins: np.ndarray, directions: np.ndarray, plane_points: np.ndarray,
               normals: np.ndarray) -> np.ndarray:
    """Intersection (3, N) of lines with planes; arguments are (3, N) or (3, 1) columns."""
    gap = _dot(plane_points - origins, normals)
    return origins + directions * (gap / _dot(directions, normals))


class PhysicalHead:
    """Galvo head with named physical effects; traces where the spot lands on the plate.

    The plate is the plane through ``plate_origin`` (``(0, 0, -delta_d)``) with normal
    ``plate_rotation @ (0, 0, 1)``; :meth:`to_plate` / :meth:`from_plate` convert between the gls
    frame and plate coordinates ``(u, v)`` about that origin.

    Parameters
    ----------
    geometry : HeadGeometry, optional
        The nominal head; the default :class:`HeadGeometry` when None.
    effects : HeadEffects or mapping, optional
        The head's effects (a mapping is turned into :class:`HeadEffects`); none when None.

    Raises
    ------
    ValueError
        If ``effects`` is a mapping that :class:`HeadEffects` rejects.
    """

    def __init__(self, geometry: HeadGeometry | None = None,
                 effects: HeadEffects | Mapping[str, object] | None = None) -> None:
        self.geometry = geometry if geometry is not None else HeadGeometry()
        if effects is None:
            effects = HeadEffects()
        elif not isinstance(effects, HeadEffects):
            effects = HeadEffects(effects)
        self.effects = effects
        self.plate_rotation, self.plate_origin = plate_frame(
            *effects.get("plate_tilt"), effects.get("working_distance")[0])
        self.plate_normal = self.plate_rotation[:, 2].copy()

    def __repr__(self) -> str:
        """Show the geometry and the non-zero effects."""
        return f"PhysicalHead({self.geometry!r}, {self.effects.nonzero()!r})"

    def mechanical_angles(self, alpha_x, alpha_y, t=None) -> tuple[np.ndarray, np.ndarray]:
        """Return the true mechanical angles (rad) for commanded ones: gain, offset and thermal drift applied."""
        return self._mechanical_angles(*self.checked_angles(alpha_x, alpha_y, t))

    def _mechanical_angles(self, alpha_x, alpha_y, t) -> tuple[np.ndarray, np.ndarray]:
        """Return :meth:`mechanical_angles` of inputs :meth:`checked_angles` returned."""
        gain_rate, offset_rate = self.effects.get("thermal_drift")
        gain_x = 1.0 + self.effects.get("galvo_gain_x")[0] + gain_rate * t
        gain_y = 1.0 + self.effects.get("galvo_gain_y")[0] + gain_rate * t
        offset_x = self.effects.get("galvo_offset_x")[0] + offset_rate * t
        offset_y = self.effects.get("galvo_offset_y")[0] + offset_rate * t
        return alpha_x * gain_x + offset_x, alpha_y * gain_y + offset_y

    @staticmethod
    def checked_angles(alpha_x, alpha_y, t=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the angles and times as :meth:`land` takes them, checked; ValueError naming a problem.

        What :meth:`land_checked` takes: a caller that lands the same angles many times (the fits of
        the discrepancy workflow) checks them once.

        Parameters
        ----------
        alpha_x, alpha_y : array_like
            Commanded mechanical angles, rad, 1-D of one length.
        t : float or array_like, optional
            Marking time, s: a scalar, one per point, or None (zero).

        Returns
        -------
        alpha_x, alpha_y, t : numpy.ndarray
            Finite float arrays of one shape.

        Raises
        ------
        ValueError
            If a value is not finite or the shapes differ.
        """
        alpha_x = np.atleast_1d(as_finite_array(alpha_x, "alpha_x"))
        alpha_y = np.atleast_1d(as_finite_array(alpha_y, "alpha_y"))
        if alpha_x.ndim != 1 or alpha_y.shape != alpha_x.shape:
            raise ValueError(
                f"alpha_x and alpha_y must be 1-D arrays of the same length, got {alpha_x.shape} and {alpha_y.shape}")
        if t is None:
            t = np.zeros_like(alpha_x)
        else:
            t = np.atleast_1d(as_finite_array(t, "t"))
            if t.size == 1:
                t = np.full_like(alpha_x, t.reshape(-1)[0])
            elif t.shape != alpha_x.shape:
                raise ValueError(f"t must be a scalar or have the length of alpha_x ({alpha_x.size}), got {t.size}")
        return alpha_x, alpha_y, t

    def _trace(self, alpha_x, alpha_y, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Y mirror hit, X mirror hit and plate hit (each (3, N), gls frame) before lens distortion."""
        return self._trace_checked(*self.checked_angles(alpha_x, alpha_y, t))

    def _trace_checked(self, alpha_x, alpha_y, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return :meth:`_trace` of inputs :meth:`checked_angles` returned."""
        ax, ay = self._mechanical_angles(alpha_x, alpha_y, t)
        e = self.geometry.mirror_distance_mm + self.effects.get("mirror_distance")[0]
        d = self.geometry.working_distance_mm
        offset_x_mm, offset_y_mm = self.effects.get("mirror_offset")
        tilt_a, tilt_b = self.effects.get("beam_tilt")
        skew = self.effects.get("axis_skew")[0]

        y_pivot = np.array([[-e], [0.0], [d]])
        x_pivot = np.array([[0.0], [0.0], [d]])
        incoming = np.array([[np.tan(tilt_a)], [1.0], [np.tan(tilt_b)]])
        incoming /= np.linalg.norm(incoming)

        # Y mirror: turns about +z; its surface may sit offset along the normal
        y_normals = _rotate(_Y_NORMAL, _Y_AXIS, ay)
        y_hits = _hit_plane(y_pivot, incoming, y_pivot + offset_y_mm * y_normals, y_normals)
        directions = _reflect(incoming, y_normals)

        # X mirror: turns about -y, tilted by the skew about gls x
        x_axis = np.array([0.0, -np.cos(skew), -np.sin(skew)])
        x_normals = _rotate(_X_NORMAL, x_axis, ax)
        x_hits = _hit_plane(y_hits, directions, x_pivot + offset_x_mm * x_normals, x_normals)
        directions = _reflect(directions, x_normals)

        plate_hits = _hit_plane(x_hits, directions, self.plate_origin[:, None], self.plate_normal[:, None])
        return np.broadcast_to(y_hits, x_hits.shape), x_hits, plate_hits

    def land(self, alpha_x, alpha_y, t=None) -> np.ndarray:
        """Where the spot lands on the plate (N, 3), gls frame, mm, for commanded mechanical angles (rad).

        ``t`` is the marking time in s (scalar or one per point), used by ``thermal_drift`` only.
        """
        return self.land_checked(*self.checked_angles(alpha_x, alpha_y, t))

    def land_checked(self, alpha_x: np.ndarray, alpha_y: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Return :meth:`land` of angles and times :meth:`checked_angles` returned (not checked again).

        Parameters
        ----------
        alpha_x, alpha_y, t : numpy.ndarray
            As :meth:`checked_angles` returns them.

        Returns
        -------
        numpy.ndarray, shape (N, 3)
            Where the spot lands, gls frame, mm.
        """
        _, _, hits = self._trace_checked(alpha_x, alpha_y, t)
        k1 = self.effects.get("radial_distortion")[0]
        if k1 != 0.0:
            # scale the in-plane offset from the field centre (the plate origin)
            radial = hits - self.plate_origin[:, None]
            radial *= 1.0 + k1 * _dot(radial, radial)
            hits = self.plate_origin[:, None] + radial
        return np.ascontiguousarray(hits.T)

    def path_length(self, alpha_x, alpha_y, t=None) -> np.ndarray:
        """Beam path (mm) from the Y mirror reflection via the X mirror to the plate (before distortion).

        With every effect zero, ``path_length - (e + d - z)`` equals the focus shift of
        :func:`gls_calibration.geometry.kinematics.inverse`.
        """
        y_hits, x_hits, plate_hits = self._trace(alpha_x, alpha_y, t)
        return np.sqrt(_dot(x_hits - y_hits, x_hits - y_hits)) + np.sqrt(_dot(plate_hits - x_hits, plate_hits - x_hits))

    def focus_path_length(self, alpha_x, alpha_y, t=None) -> np.ndarray:
        """Path length beyond the nominal one at zero angles, ``path_length - (e + d)`` (mm)."""
        return self.path_length(alpha_x, alpha_y, t) - (
            self.geometry.mirror_distance_mm + self.geometry.working_distance_mm)

    def to_plate(self, points) -> np.ndarray:
        """Map gls points (N, 3) to in-plane coordinates (N, 2) about the plate origin (mm)."""
        offsets = np.asarray(points, dtype=float) - self.plate_origin
        return np.stack([offsets @ self.plate_rotation[:, 0], offsets @ self.plate_rotation[:, 1]], axis=-1)

    def from_plate(self, uv) -> np.ndarray:
        """Plate coordinates (N, 2) -> gls points (N, 3) on the plate plane (mm)."""
        uv = np.asarray(uv, dtype=float)
        return (self.plate_origin + uv[..., 0:1] * self.plate_rotation[:, 0]
                + uv[..., 1:2] * self.plate_rotation[:, 1])
