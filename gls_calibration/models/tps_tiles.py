"""Fast kernel sums of a thin-plate spline for large batches: exact near field, Chebyshev far field.

The spline's kernel part ``s(p) = sum_i w_i phi(|p - c_i|)`` with ``phi(r) = r^2 ln r`` costs one
logarithm per centre and point (361 per target for the default 19x19 calibration). The box around
the centres is cut into ``tiles x tiles`` tiles. For a point in tile t, the centres in t and its
eight neighbours are summed exactly; the sum over all other centres is smooth over t (they lie at
least one tile away) and enters through a tensor Chebyshev interpolant of degree ``degree`` fitted
on t when the evaluator is built. The evaluator checks itself against the exact sum at points
between the interpolation nodes of every tile and refuses to exist (``build`` returns None) when it
is off by more than ``TOLERANCE_MM``; the stored model, its formula and the format document are
unchanged. A point's value does not depend on the other points of the batch.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Optional

import cv2
import numpy as np

TOLERANCE_MM = 1e-10          # most the tiles may differ from the exact sum (format evaluator: 1e-9)
TILES = 12
DEGREE = 12
_MARGIN = 0.05                # the box: the centres' box grown by this share of its size on each side
_CHECKS_PER_TILE = 25
PAGE = 64                    # slots of one page: points of one tile computed together
_PAGES_AT_ONCE = 256          # pages per batched product: fewer, larger calls hold the GIL less (work arrays ~3 MB)
_TINY = np.finfo(float).tiny


def exact_kernel_sum(points: np.ndarray, centres: np.ndarray, half_weights: np.ndarray) -> np.ndarray:
    """Return ``sum_i 2 half_weights_i phi(|p - c_i|)`` (M, K) from plain differences.

    Points (M, 2), centres (N, 2), half_weights (N, K) (``0.5 w``: ``phi = 0.5 r^2 ln r^2``).
    """
    return _kernel_sum_by_rows(points[:, 0], points[:, 1], centres, half_weights).T


def _kernel_sum_by_rows(x: np.ndarray, y: np.ndarray, centres: np.ndarray, half_weights: np.ndarray) -> np.ndarray:
    """:func:`exact_kernel_sum` as (K, M) for coordinates x, y (M,): one row per output, contiguous."""
    squared = np.subtract.outer(centres[:, 0], x)
    squared *= squared
    dy = np.subtract.outer(centres[:, 1], y)
    dy *= dy
    squared += dy
    np.maximum(squared, _TINY, out=squared)       # r = 0: tiny * ln(tiny) is 0 to 1e-305
    cv2.log(squared, dy)
    dy *= squared
    return half_weights.T @ dy


def _chebyshev_rows(u: np.ndarray, degree: int, axis: int = 0) -> np.ndarray:
    """``T_k(u)`` for k = 0..degree along a new axis ``axis`` of u's shape, u in [-1, 1]."""
    rows = np.empty((degree + 1,) + u.shape)
    rows[0] = 1.0
    if degree:
        rows[1] = u
    twice = 2.0 * u
    for k in range(2, degree + 1):
        np.multiply(twice, rows[k - 1], out=rows[k])
        rows[k] -= rows[k - 2]
    return np.moveaxis(rows, 0, axis) if axis else rows


@dataclass(frozen=True)
class TiledKernelSum:
    """The kernel sum of one spline over its centres' box; points outside it are not handled here.

    ``origin`` (2,) and ``tile_size`` (2,) in mm place the tiles (tile ``ix * tiles + iy``). Per tile:
    ``near_expansion`` (tiles^2, S, 4) its exact centres c, as ``[c_x, c_y, |c|^2, 1]`` in mm from the
    tile's centre, and ``near_weights`` (tiles^2, K, S) their half weights, padded to S with weightless
    centres; ``coefficients`` (tiles^2, K * (degree + 1),
    degree + 1) its far field's Chebyshev coefficients: row ``o * (degree + 1) + l`` (output o, degree
    l in v), column k (degree in u).
    """

    origin: np.ndarray
    tile_size: np.ndarray
    tiles: int
    degree: int
    near_expansion: np.ndarray
    near_weights: np.ndarray
    coefficients: np.ndarray

    def inside(self, points: np.ndarray) -> np.ndarray:
        """Return flags (M,): the points this evaluator handles (within its box)."""
        high = self.origin + self.tiles * self.tile_size
        return ((points >= self.origin) & (points <= high)).all(axis=1)

    def covers(self, points: np.ndarray) -> bool:
        """Whether every point of ``points`` (M >= 1, 2) is inside (two reductions, no flags)."""
        high = self.origin + self.tiles * self.tile_size
        x, y = points[:, 0], points[:, 1]           # column by column: 30x numpy's min(axis=0) on (M, 2)
        return bool(x.min() >= self.origin[0] and y.min() >= self.origin[1] and x.max() <= high[0]
                    and y.max() <= high[1])

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Kernel sums (M, K) at ``points`` (M, 2) in mm, all inside the box (see :meth:`inside`)."""
        # The points are laid out in pages of PAGE slots, each page holding points of one tile, so
        # that all tiles are computed by a few batched products (a loop over tiles would make
        # thousands of small numpy calls: worker threads then queue for the GIL, 2x slower than one).
        rows = np.ascontiguousarray(points.T)
        relative = rows - self.origin[:, None]
        relative /= self.tile_size[:, None]
        index = np.floor(relative)
        np.clip(index, 0, self.tiles - 1, out=index)         # the box's far edges belong to the last tiles
        relative -= index
        relative *= 2.0
        relative -= 1.0                                      # position in the tile, [-1, 1]
        tile = (index[0] * self.tiles + index[1]).astype(np.int16)
        counts = np.bincount(tile, minlength=self.tiles ** 2)
        pages = -(-counts // PAGE)
        page_tile = np.repeat(np.arange(counts.size), pages)
        # Slot of each point: its tile's first page, plus its rank among the tile's points.
        order = np.argsort(tile, kind="stable")              # 16-bit keys: a radix sort
        sorted_slots = np.arange(points.shape[0]) + np.repeat(PAGE * (np.cumsum(pages) - pages)
                                                              - (np.cumsum(counts) - counts), counts)
        slot = np.empty_like(sorted_slots)
        slot[order] = sorted_slots
        laid_out = np.zeros((2, page_tile.size * PAGE))      # u, v; empty slots compute harmless zeros
        laid_out[:, slot] = relative
        laid_out = laid_out.reshape(2, page_tile.size, PAGE)
        outputs = self.near_weights.shape[1]
        result = np.empty((page_tile.size, outputs, PAGE))
        for first in range(0, page_tile.size, _PAGES_AT_ONCE):
            group = slice(first, first + _PAGES_AT_ONCE)
            tiles, u, v = page_tile[group], laid_out[0, group], laid_out[1, group]
            result[group] = self._near(tiles, u, v) + self._far(tiles, u, v)
        return np.take(result.transpose(1, 0, 2).reshape(outputs, -1), slot, axis=1).T

    def _near(self, tiles: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Exact sums (G, K, PAGE) over the near centres of pages of tiles ``tiles`` (G,) at local u, v (G, PAGE)."""
        # r^2 = |c|^2 + |p|^2 - 2 c.p in mm from the tile's centre (|c| < 27 mm: round-off ~1e-12 mm^2),
        # one batched product; |.| and tiny keep it positive (a point on a centre: phi ~ 1e-11).
        half_x, half_y = 0.5 * self.tile_size
        expanded = np.empty((tiles.size, 4, u.shape[-1]))
        np.multiply(u, -2.0 * half_x, out=expanded[:, 0])
        np.multiply(v, -2.0 * half_y, out=expanded[:, 1])
        expanded[:, 2] = 1.0
        np.multiply(expanded[:, 0], expanded[:, 0], out=expanded[:, 3])
        expanded[:, 3] += np.square(expanded[:, 1])
        expanded[:, 3] *= 0.25
        squared = np.matmul(np.take(self.near_expansion, tiles, axis=0), expanded)
        np.abs(squared, out=squared)
        squared += _TINY
        flat = squared.reshape(-1, squared.shape[-1])
        kernel = np.empty_like(squared)
        cv2.log(flat, kernel.reshape(flat.shape))
        kernel *= squared
        return np.matmul(np.take(self.near_weights, tiles, axis=0), kernel)

    def _far(self, tiles: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Chebyshev far fields (G, K, PAGE) of pages of tiles ``tiles`` (G,) at local u, v (G, PAGE)."""
        # sum over l of T_l(v) (sum over k of a_okl T_k(u)): 3x faster than one product with T_k(u) T_l(v).
        degree = self.degree
        far = np.matmul(np.take(self.coefficients, tiles, axis=0), _chebyshev_rows(u, degree, axis=1))
        far = far.reshape(tiles.size, -1, degree + 1, u.shape[-1])
        far *= _chebyshev_rows(v, degree, axis=1)[:, None]
        return far.sum(axis=2)


def build(centres: np.ndarray, half_weights: np.ndarray, tiles: int = TILES,
          degree: int = DEGREE) -> Optional[TiledKernelSum]:
    """Build the tiled evaluator of ``sum_i 2 half_weights_i phi(|p - c_i|)``, or None.

    The tiled evaluator of ``sum_i 2 half_weights_i phi(|p - c_i|)``, or None where it would not be
    within ``TOLERANCE_MM`` of the exact sum (checked) or the centres span no area.

    centres (N, 2) mm, half_weights (N, K). Costs about (tiles * (degree + 1))^2 * N logarithms.
    """
    low, high = centres.min(axis=0), centres.max(axis=0)
    span = high - low
    if centres.shape[0] < 4 or not (span > 0.0).all():
        return None
    origin = low - _MARGIN * span
    tile_size = span * (1.0 + 2.0 * _MARGIN) / tiles
    centre_tile = np.clip(np.floor((centres - origin) / tile_size).astype(np.intp), 0, tiles - 1)
    nodes = np.cos(math.pi * (np.arange(degree + 1) + 0.5) / (degree + 1))    # Chebyshev points, first kind
    # Coefficients from values at the nodes: a = A F A^T with A[k, j] = (2 - [k = 0]) T_k(u_j) / (degree + 1).
    transform = _chebyshev_rows(nodes, degree) * (2.0 / (degree + 1))
    transform[0] *= 0.5
    grid_u, grid_v = np.meshgrid(nodes, nodes, indexing="ij")
    outputs = half_weights.shape[1]
    near_sets, coefficients = [], np.empty((tiles * tiles, outputs * (degree + 1), degree + 1))
    for ix in range(tiles):
        for iy in range(tiles):
            near = np.flatnonzero((np.abs(centre_tile[:, 0] - ix) <= 1) & (np.abs(centre_tile[:, 1] - iy) <= 1))
            far_weights = half_weights.copy()
            far_weights[near] = 0.0
            at = origin + tile_size * (np.array([ix, iy]) + 0.5 * (1.0 + np.column_stack([grid_u.ravel(),
                                                                                          grid_v.ravel()])))
            values = exact_kernel_sum(at, centres, far_weights).reshape(degree + 1, degree + 1, outputs)
            tile_coefficients = np.einsum("ka,abo,lb->olk", transform, values, transform)
            coefficients[ix * tiles + iy] = tile_coefficients.reshape(outputs * (degree + 1), degree + 1)
            near_sets.append(near)
    # Near sets padded to one size with weightless centres at the tile's centre.
    size = max(near.size for near in near_sets)
    near_expansion = np.zeros((tiles * tiles, size, 4))
    near_expansion[:, :, 3] = 1.0
    near_weights = np.zeros((tiles * tiles, outputs, size))
    for t, near in enumerate(near_sets):
        local = centres[near] - (origin + tile_size * (np.array(divmod(t, tiles)) + 0.5))
        near_expansion[t, :near.size, :2] = local
        near_expansion[t, :near.size, 2] = np.sum(local ** 2, axis=1)
        near_weights[t, :, :near.size] = half_weights[near].T
    evaluator = TiledKernelSum(origin, tile_size, tiles, degree, near_expansion, near_weights, coefficients)
    # Self-check between the nodes of every tile (a fixed pattern: the same verdict on every load).
    offsets = np.random.default_rng(0).uniform(0.0, 1.0, size=(_CHECKS_PER_TILE, 2))
    corners = origin + tile_size * np.stack(np.meshgrid(np.arange(tiles), np.arange(tiles), indexing="ij"),
                                            axis=-1).reshape(-1, 1, 2)
    probes = (corners + offsets * tile_size).reshape(-1, 2)
    probes = probes[evaluator.inside(probes)]
    error = np.max(np.abs(evaluator(probes) - exact_kernel_sum(probes, centres, half_weights)), initial=0.0)
    return evaluator if error <= TOLERANCE_MM else None
