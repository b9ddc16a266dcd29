"""The steel plate of the simulated cell: its pose, its reflectivity and the marks burnt into it.

Plate coordinates ``(u, v)`` (mm) lie in the plate plane about the plate origin (the field centre);
the pose is the same physical thing as the ``plate_tilt`` and ``working_distance`` effects of the
truth head (:func:`gls_calibration.geometry.optics.plate_frame`), so marks land exactly on this plane.

Marks are kept as vector polylines and rendered on demand: each darkens the steel with a Gaussian
line profile across the path, ``reflectivity * (1 - depth * exp(-dist^2 / (2 sigma^2)))`` with
``sigma = line_width_fwhm_mm / 2.3548`` (the line width is the full width at half maximum of the
darkening). A negative depth brightens instead. Distances come from a KD-tree over the polylines
resampled at ``sigma / 4``, queried only for sample points in cells near a mark.

The measurement chain (:class:`~gls_calibration.simulation.measurement.MeasurementChain`) makes
marks as a laser makes them -- each resampled point of a path gets its own width and darkness (smooth
relative variations), the burnt line wanders off the beam path, each mark starts and ends with a dark
blob, and the spot size blurs the line (wider, less deep) -- and gives each plate (drawn anew on
:meth:`Plate.load_clean`) the robot-held head's marking-pose error (``marking_pose_error``: height in
mm, tilts about x and y in rad, used by the truth head), a thermal scale between marking and
scanning (marks burnt on the warm plate shrink with it) and a warp (``warp``: height above the plane
along its normal). A mark's random draws depend on the plate's seed and the mark's order only, so a
plate rebuilt from the same landed paths (the simulated scanner's copy) looks the same.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from scipy.ndimage import binary_dilation, gaussian_filter, map_coordinates
from scipy.spatial import cKDTree

from gls_calibration.common.validation import as_finite_array, as_points, as_positive_number
from gls_calibration.geometry.optics import plate_frame
from gls_calibration.simulation.measurement import MeasurementChain, smooth_process

_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


@dataclass(frozen=True)
class PlateSettings:
    """Steel plate: size, pose in the gls frame, surface look and mark appearance (mm, rad)."""

    size_mm: float = 250.0
    tilt_x_rad: float = 0.0
    tilt_y_rad: float = 0.0
    delta_d_mm: float = 0.0
    base_reflectivity: float = 0.6
    texture_std: float = 0.02
    texture_cell_mm: float = 0.5
    texture_correlation_mm: float = 1.5
    line_width_fwhm_mm: float = 0.1
    mark_depth: float = 0.7

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        for name in ("size_mm", "texture_cell_mm", "texture_correlation_mm", "line_width_fwhm_mm"):
            as_positive_number(getattr(self, name), f"plate {name}")
        for name in ("tilt_x_rad", "tilt_y_rad", "delta_d_mm", "texture_std"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"plate {name} must be finite, got {getattr(self, name)!r}")
        if not 0.0 < self.base_reflectivity <= 1.0:
            raise ValueError(f"plate base_reflectivity must be in (0, 1], got {self.base_reflectivity!r}")
        if not (math.isfinite(self.mark_depth) and self.mark_depth <= 1.0):
            raise ValueError(f"plate mark_depth must be at most 1 (negative brightens), got {self.mark_depth!r}")
        if self.texture_std < 0.0:
            raise ValueError(f"plate texture_std must be non-negative, got {self.texture_std!r}")

    @property
    def pose_effects(self) -> dict[str, tuple[float, ...]]:
        """Return the head effects that put the work plane on this plate."""
        return {"plate_tilt": (self.tilt_x_rad, self.tilt_y_rad), "working_distance": (self.delta_d_mm,)}


class Plate:
    """A steel plate with a textured reflectivity and vector marks (stateful: marks accumulate)."""

    def __init__(self, settings: PlateSettings | None = None, seed: int | np.random.Generator = 0,
                 chain: MeasurementChain | None = None, beam_distance_mm: float = 490.0) -> None:
        self.settings = settings if settings is not None else PlateSettings()
        self.chain = chain if chain is not None else MeasurementChain()
        # distance of the beam's exit point from the plate: a warped surface meets the beam early
        self.beam_distance_mm = as_positive_number(beam_distance_mm, "beam_distance_mm")
        self.rotation, self.origin = plate_frame(
            self.settings.tilt_x_rad, self.settings.tilt_y_rad, self.settings.delta_d_mm)
        self.normal = self.rotation[:, 2].copy()
        self.load_clean(seed, plate_id=0)

    # ------------------------------------------------------------------ state
    def load_clean(self, seed: int | np.random.Generator | None = None, plate_id: int | None = None) -> int:
        """Put a fresh plate in the fixture: new id, new texture, no marks. Returns the plate id.

        ``plate_id`` (None: one more than the plate's before) numbers the plates loaded into this
        fixture, 0 for the one it was built with: a copy of another fixture's plate is given that
        plate's id (and seed). The id belongs to the fixture, not the process, so that it, like the
        draws, does not depend on how many plates were made before.
        """
        rng = np.random.default_rng(seed)
        self.plate_id = self.plate_id + 1 if plate_id is None else int(plate_id)
        self._texture = self._make_texture(rng)
        self._marks: list[np.ndarray] = []
        self._index = None
        # per-plate draws of the measurement chain, from a stream of their own
        c = self.chain
        self._mark_seed = int(rng.integers(2 ** 62))
        draws = np.random.default_rng(self._mark_seed).standard_normal(6)
        self.marking_pose_error = (c.marking_height_mm * draws[0], c.marking_tilt_rad * draws[1],
                                   c.marking_tilt_rad * draws[2])
        self.thermal_scale = 1e-6 * c.thermal_scale_ppm * draws[3]
        bowl_saddle = draws[4:6]
        self._warp = None
        if c.plate_warp_mm > 0.0:
            corners = self._warp_shape(
                np.array([[1.0, 1.0], [1.0, -1.0], [1.0, 0.0], [0.0, 1.0]]) * 0.5 * self.settings.size_mm, bowl_saddle)
            peak = max(np.abs(corners).max(), 1e-12)
            self._warp = bowl_saddle * c.plate_warp_mm / peak
        return self.plate_id

    def _warp_shape(self, uv: np.ndarray, coefficients: np.ndarray) -> np.ndarray:
        """Bowl and saddle heights (mm per unit coefficient) at plate coordinates (..., 2)."""
        half = 0.5 * self.settings.size_mm
        u, v = uv[..., 0] / half, uv[..., 1] / half
        return coefficients[0] * 0.5 * (u * u + v * v) + coefficients[1] * 0.5 * (u * u - v * v)

    def warp(self, uv) -> np.ndarray | None:
        """Height (mm) of the surface above the plate plane along its normal at (..., 2), None when flat."""
        if self._warp is None:
            return None
        return self._warp_shape(np.asarray(uv, dtype=float), self._warp)

    def _make_texture(self, rng: np.random.Generator) -> np.ndarray:
        s = self.settings
        cells = int(math.ceil(s.size_mm / s.texture_cell_mm)) + 1
        noise = gaussian_filter(rng.standard_normal((cells, cells)),
                                s.texture_correlation_mm / s.texture_cell_mm, mode="wrap")
        std = noise.std()
        scale = s.texture_std / std if std > 0 else 0.0
        return (s.base_reflectivity + scale * noise).astype(np.float32)

    @property
    def marks(self) -> tuple[np.ndarray, ...]:
        """Return the marked polylines in plate coordinates, (M, 2) each, in marking order."""
        return tuple(self._marks)

    # ------------------------------------------------------------ frames
    def to_plate(self, points) -> np.ndarray:
        """Map gls points (..., 3) to plate coordinates (..., 2), projected on the plate plane."""
        offsets = np.asarray(points, dtype=float) - self.origin
        return np.stack([offsets @ self.rotation[:, 0], offsets @ self.rotation[:, 1]], axis=-1)

    def from_plate(self, uv) -> np.ndarray:
        """Plate coordinates (..., 2) -> gls points (..., 3) on the plate plane."""
        uv = np.asarray(uv, dtype=float)
        return self.origin + uv[..., 0:1] * self.rotation[:, 0] + uv[..., 1:2] * self.rotation[:, 1]

    # ------------------------------------------------------------ marking
    def add_mark(self, points_gls) -> None:
        """Burn a landed polyline (M, 3) in gls coordinates (M >= 1) into the plate."""
        points = as_points(points_gls, "points_gls", 3)
        uv = self.to_plate(points)
        height = self.warp(uv)
        if height is not None:
            # the beam meets the raised surface before the plane: closer to the field centre
            uv = uv * (1.0 - height / self.beam_distance_mm)[:, None]
        # burnt on the warm plate, measured on the cooled one
        self._marks.append(uv * (1.0 + self.thermal_scale))
        self._index = None

    def add_mark_plate(self, uv) -> None:
        """Burn a polyline given directly in plate coordinates (M, 2)."""
        self._marks.append(as_points(uv, "uv", 2).copy())
        self._index = None

    def _mark_index(self):
        """Resampled mark points with their width and darkness, their KD-trees and a coarse occupancy grid."""
        if self._index is None:
            s, c = self.settings, self.chain
            sigma = s.line_width_fwhm_mm / _FWHM_PER_SIGMA
            spacing = sigma / 4.0
            samples, widths, darkness, blobs = [], [], [], []
            for number, polyline in enumerate(self._marks):
                points = _resample(polyline, spacing)
                rng = np.random.default_rng([self._mark_seed, number])
                along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(points, axis=0).T))])
                if c.mark_wander_mm and len(points) > 1:
                    tangent = np.gradient(points, axis=0)
                    tangent /= np.maximum(np.hypot(tangent[:, 0], tangent[:, 1]), 1e-12)[:, None]
                    offset = smooth_process(rng, along, c.mark_wander_mm, c.mark_wander_correlation_mm)
                    points = points + offset[:, None] * np.column_stack([-tangent[:, 1], tangent[:, 0]])
                width = 1.0 + smooth_process(rng, along, c.mark_width_variation, c.mark_variation_correlation_mm)
                dark = 1.0 + smooth_process(rng, along, c.mark_darkness_variation, c.mark_variation_correlation_mm)
                samples.append(points)
                widths.append(np.maximum(width, 0.2) * sigma)
                darkness.append(np.maximum(dark, 0.0))
                blobs += [points[0], points[-1]]
            samples = np.concatenate(samples)
            widths = np.concatenate(widths)
            darkness = np.concatenate(darkness)
            # the spot's blur widens the line and lowers its peak by the same factor
            blurred = np.sqrt(widths ** 2 + c.spot_blur_mm ** 2)
            darkness = darkness * widths / blurred
            blob_sigma = math.hypot(c.mark_blob_mm, sigma) if c.mark_blob_mm else 0.0
            cutoff = 4.0 * max(float(blurred.max()), blob_sigma)
            cell = max(cutoff, 0.25)
            half = 0.5 * s.size_mm
            cells = int(math.ceil(s.size_mm / cell)) + 1
            occupied = np.zeros((cells, cells), dtype=bool)
            idx = np.floor((samples + half) / cell).astype(int)
            keep = np.all((idx >= 0) & (idx < cells), axis=1)
            occupied[idx[keep, 0], idx[keep, 1]] = True
            occupied = binary_dilation(occupied, iterations=1)
            blob_tree = cKDTree(np.array(blobs)) if blob_sigma else None
            self._index = (cKDTree(samples), occupied, cell, cutoff, blurred, darkness, blob_tree, blob_sigma)
        return self._index

    # ------------------------------------------------------------ rendering
    def contains(self, uv) -> np.ndarray:
        """Return True where plate coordinates (..., 2) lie on the plate."""
        uv = np.asarray(uv)
        half = 0.5 * self.settings.size_mm
        return (np.abs(uv[..., 0]) <= half) & (np.abs(uv[..., 1]) <= half)

    def mark_darkening(self, uv) -> np.ndarray:
        """Mark profile at plate coordinates (..., 2): 1 on a path's centre line (of a nominal mark), 0 far away."""
        uv = np.asarray(uv, dtype=float)
        shape = uv.shape[:-1]
        flat = uv.reshape(-1, 2)
        result = np.zeros(flat.shape[0], dtype=np.float32)
        if not self._marks:
            return result.reshape(shape)
        tree, occupied, cell, cutoff, sigma, darkness, blob_tree, blob_sigma = self._mark_index()
        half = 0.5 * self.settings.size_mm
        with np.errstate(invalid="ignore"):
            idx = np.floor((flat + half) / cell)
        inside = np.all((idx >= 0) & (idx < occupied.shape[0]), axis=1)
        candidates = np.flatnonzero(inside)
        candidates = candidates[occupied[idx[candidates, 0].astype(int), idx[candidates, 1].astype(int)]]
        if candidates.size:
            distance, nearest = tree.query(flat[candidates], distance_upper_bound=cutoff, workers=-1)
            near = np.isfinite(distance)
            which = nearest[near]
            result[candidates[near]] = darkness[which] * np.exp(-0.5 * (distance[near] / sigma[which]) ** 2)
            if blob_tree is not None:
                # a mark starts and ends with a dark blob (the laser dwells while switching)
                distance, _ = blob_tree.query(flat[candidates], distance_upper_bound=cutoff, workers=-1)
                near = np.isfinite(distance)
                blob = np.exp(-0.5 * (distance[near] / blob_sigma) ** 2)
                result[candidates[near]] = np.maximum(result[candidates[near]], blob)
        return result.reshape(shape)

    def reflectivity(self, uv) -> np.ndarray:
        """Reflectivity (..., ) at plate coordinates (..., 2), NaN off the plate; float32."""
        uv = np.asarray(uv, dtype=float)
        s = self.settings
        grid = (uv + 0.5 * s.size_mm) / s.texture_cell_mm
        shape = uv.shape[:-1]
        base = map_coordinates(self._texture, [grid[..., 0].ravel(), grid[..., 1].ravel()],
                               order=1, mode="nearest", output=np.float32).reshape(shape)
        if self._marks:
            base *= np.maximum(1.0 - np.float32(s.mark_depth) * self.mark_darkening(uv), 0.0)
        base[~self.contains(uv)] = np.nan
        return base

    def render(self, pixel_mm: float = 0.02, extent_mm: float | None = None,
               centre_uv=(0.0, 0.0)) -> np.ndarray:
        """Reflectivity image (rows along v, columns along u) around ``centre_uv``; for inspection."""
        if not pixel_mm > 0.0:
            raise ValueError(f"pixel_mm must be positive, got {pixel_mm!r}")
        extent = self.settings.size_mm if extent_mm is None else float(extent_mm)
        centre = as_finite_array(centre_uv, "centre_uv", ndim=1)
        axis = (np.arange(int(round(extent / pixel_mm)) + 1) - round(extent / pixel_mm) / 2) * pixel_mm
        u, v = np.meshgrid(centre[0] + axis, centre[1] + axis)
        return self.reflectivity(np.stack([u, v], axis=-1))


def _resample(polyline: np.ndarray, spacing: float) -> np.ndarray:
    """Points along a polyline no more than ``spacing`` apart (vertices kept)."""
    if polyline.shape[0] == 1:
        return polyline
    segments = np.diff(polyline, axis=0)
    lengths = np.hypot(segments[:, 0], segments[:, 1])
    counts = np.maximum(np.ceil(lengths / spacing).astype(int), 1)
    starts = np.repeat(polyline[:-1], counts, axis=0)
    steps = np.repeat(segments / counts[:, None], counts, axis=0)
    fraction = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    return np.concatenate([starts + steps * fraction[:, None], polyline[-1:]])
