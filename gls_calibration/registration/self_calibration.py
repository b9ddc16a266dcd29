"""Grid-plate self-calibration: views of one marked plate moved against the chain's error field.

A plate carries marks on a grid of pitch ``p`` (mark ``k`` at grid node ``g_k``, integer). The chain
measures a mark with an error that depends on where the mark lies relative to the chain: a field
``F`` over the grid nodes, one field per *pass type* (a line's travel direction and sensor
orientation: each has its own repeating robot error and sensor axis). Moving the plate by ``-s``
grid pitches in its fixture (Ye et al. 1997, "An exact algorithm for self-calibration of
two-dimensional precision metrology stages"; Raugh) samples the same field at other marks:

    m_vk = t_k + F_p(v)(g_k - s_v) + c_v + theta_v J (p g_k - centroid) + noise

- ``m_vk``: centre of mark ``k`` measured in view ``v`` (any frame that differs from the plate's
  by a small rotation, |theta| well below 1e-2 rad, and a translation);
- ``t_k``: the marks' true positions (the unknowns wanted), ``F_p`` the field of pass type ``p`` at
  every node it is sampled at, ``c_v`` and ``theta_v`` each view's rigid motion (a plate moved in
  its fixture, a sweep's repeatability offset), ``J`` the 90 deg rotation.

Weighted least squares over every seen mark of every view (``sigma_mm`` per view and axis: a line's
cross-track noise can be far larger than its along-track noise), solved as sparse normal equations
(scipy.sparse). What no translation of the plate can tell apart, the *unobservable* terms:

1. a rigid motion of the marks against the views' rigid motions (3);
2. per pass type, a constant and a rotation of its field against its views' rigid motions (3 each);
3. a linear map of the marks against the same linear map, with the other sign, in every field: for
   a translation ``d``, ``A (x + d) - A x`` is a constant that each view's fit absorbs. Its
   antisymmetric part is a rotation (item 1); its symmetric part (scale in x, scale in y, shear: 3)
   is what a reference must supply -- a certified plate, or a rotated view.

The gauge (fixed explicitly): the normal equations, scaled to a unit diagonal, carry a ridge of
``RIDGE``, so every unobservable combination comes out with zero norm; then the marks are
moved along the null space (items 1 and 3) so that their affine part (translation, rotation,
scales, shear; 6 terms) equals that of the views' mean measured centres, the fields taking the
opposite symmetric linear part. ``linear_correction`` (a symmetric 2x2 matrix, mm per mm) is then
the chain's symmetric linear error in that mean, measured on a reference; the marks lose it:
``t_k -= L (p g_k - centroid)``. Without it the marks keep the chain's linear error.

``field_model="separable"`` replaces the free value per node by a term per node column plus one per
node row (per pass type and axis): a robot line's error depends on the travel coordinate, the
sensor's on the coordinate along its laser line. The unobservable terms stay those above.

Measured on the simulated cell (``benchmarks/bench_self_calibration.py``, docs/method-and-results.md,
"Grid-plate self-calibration"): with the plate moved in its fixture it separates the chain's
repeating field to 0.006 mm, but the per-sweep random path error of ``paper_like`` is amplified to
0.09-0.2 mm; it is not wired into the calibration.

A view's rotation acts in the model on the nominal node positions: a view rotated by ``theta``
leaves ``theta`` times a mark's offset from its node unexplained (1e-4 mm at 2e-4 rad and 0.5 mm).
The model samples the field at grid nodes: a mark that lies ``e`` off its node sees
``F(g - s) + grad F . e``; with a field of 0.05 mm over 20 mm and marks 1 mm off their nodes that
is ~0.002 mm.

Example
-------
>>> rng = np.random.default_rng(1)
>>> nodes = np.array([(i, j) for j in range(6) for i in range(6)])
>>> truth = 10.0 * nodes + 0.02 * rng.standard_normal(nodes.shape)
>>> def field(n):   # the chain's error at grid node n (the same for every view)
...     return 0.01 * np.column_stack([np.sin(n[:, 1]), np.cos(0.7 * n[:, 0])])
>>> views = [GridView(truth + field(nodes - s), np.ones(len(nodes), bool), s, "0+")
...          for s in ((0, 0), (1, 0), (0, 1))]
>>> result = self_calibrate(nodes, views, 10.0)
>>> error = non_affine_part(result.marks_mm - truth, nodes, 10.0)
>>> bool(np.sqrt(np.mean(error ** 2)) < 1e-9)
True
>>> result.unobservable[-1]
'symmetric linear part of the marks (scale x, scale y, shear): from a reference'
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Optional, Sequence
import warnings

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import MatrixRankWarning, spsolve

#: Ridge of the normal equations scaled to a unit diagonal: it sets every unobservable combination
#: to zero (scaled) norm and is far below the smallest observable eigenvalue of the designs measured
#: here (noise-free data fit to 1e-9 mm: test/test_self_calibration.py).
RIDGE = 1e-10
#: Gauss-Newton passes: each removes the views' fitted rotations from the measurements exactly.
PASSES = 3
#: Fewest marks a view must see, fewest field nodes it must share with the other views of its pass type.
MIN_MARKS = 3
MIN_SHARED_NODES = 3
FIELD_MODELS = ("nodes", "separable")
UNOBSERVABLE = ("rigid motion of the marks (translation x, y, rotation)",
                "per pass type: constant and rotation of its field (absorbed by its views' rigid motions)",
                "symmetric linear part of the marks (scale x, scale y, shear): from a reference")


@dataclass(frozen=True)
class GridView:
    """One view of the marked plate: the measured centres, which were seen, the shift, the pass type.

    Parameters
    ----------
    centres_mm : numpy.ndarray, shape (N, 2)
        Measured centre of every mark (any value where not seen), mm.
    seen : numpy.ndarray, shape (N,), bool
        Which marks the view found.
    shift : tuple of int
        The plate's shift against the chain in grid pitches (x, y): the field is sampled at
        ``node - shift``.
    pass_type : str
        The pass type (e.g. a sweep plan label ``0+``): views of one type share one field.
    sigma_mm : tuple of float, default (0.001, 0.001)
        Standard deviation of a centre's noise per axis, mm (the weights).
    """

    centres_mm: np.ndarray
    seen: np.ndarray
    shift: tuple
    pass_type: str
    sigma_mm: tuple = (0.001, 0.001)


@dataclass(frozen=True)
class PassField:
    """The field of one pass type at the nodes it was sampled at, in the result's gauge.

    Parameters
    ----------
    pass_type : str
        The pass type.
    nodes : numpy.ndarray, shape (M, 2), int
        Grid nodes (x, y).
    error_mm : numpy.ndarray, shape (M, 2)
        The field at the nodes, mm (up to its unobservable constant and rotation).
    """

    pass_type: str
    nodes: np.ndarray
    error_mm: np.ndarray


@dataclass(frozen=True)
class SelfCalibration:
    """Result of :func:`self_calibrate`.

    Parameters
    ----------
    marks_mm : numpy.ndarray, shape (N, 2)
        The marks' positions in the gauge of the module docstring, mm.
    mark_sigma_mm : numpy.ndarray or None, shape (N, 2)
        Standard deviation per mark and axis propagated from the views' ``sigma_mm`` (white noise),
        of the marks' part beyond their affine part (what the gauge leaves); None unless asked for.
    fields : tuple of PassField
        One per pass type, in order of first appearance.
    view_translation_mm : numpy.ndarray, shape (V, 2)
        Each view's fitted translation, mm.
    view_rotation_rad : numpy.ndarray, shape (V,)
        Each view's fitted rotation, rad.
    residual_rms_mm : tuple of float
        RMS residual per axis over every seen mark of every view, mm.
    unobservable : tuple of str
        What the views cannot tell apart (the gauge fixes it; the last item needs a reference).
    """

    marks_mm: np.ndarray
    mark_sigma_mm: Optional[np.ndarray]
    fields: tuple
    view_translation_mm: np.ndarray
    view_rotation_rad: np.ndarray
    residual_rms_mm: tuple
    unobservable: tuple


def affine_basis(nodes: np.ndarray, pitch_mm: float) -> np.ndarray:
    """Return the (2N, 6) basis of affine displacements of the marks, rows interleaved x, y.

    Columns: translation x, translation y, rotation, scale x, scale y, shear (symmetric), about the
    nodes' centroid.

    Parameters
    ----------
    nodes : numpy.ndarray, shape (N, 2)
        Grid nodes.
    pitch_mm : float
        Grid pitch, mm.

    Returns
    -------
    numpy.ndarray, shape (2N, 6)
        The basis.
    """
    position = pitch_mm * (np.asarray(nodes, dtype=float) - np.asarray(nodes, dtype=float).mean(axis=0))
    x, y = position[:, 0], position[:, 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    columns = [(one, zero), (zero, one), (-y, x), (x, zero), (zero, y), (y, x)]
    return np.column_stack([np.column_stack(pair).ravel() for pair in columns])


def non_affine_part(displacement_mm, nodes, pitch_mm: float) -> np.ndarray:
    """Return ``displacement_mm`` (N, 2) less its least-squares affine part (see :func:`affine_basis`).

    Parameters
    ----------
    displacement_mm : array_like, shape (N, 2)
        Displacements of the marks, mm.
    nodes : array_like, shape (N, 2)
        Their grid nodes.
    pitch_mm : float
        Grid pitch, mm.

    Returns
    -------
    numpy.ndarray, shape (N, 2)
        What no affine map explains.
    """
    values = np.asarray(displacement_mm, dtype=float).ravel()
    basis = affine_basis(nodes, pitch_mm)
    coefficients = np.linalg.lstsq(basis, values, rcond=None)[0]
    return (values - basis @ coefficients).reshape(-1, 2)


def _check_inputs(nodes, views: Sequence[GridView], pitch_mm, linear_correction) -> tuple:
    nodes_array = np.asarray(nodes)
    if (nodes_array.ndim != 2 or nodes_array.shape[1] != 2 or nodes_array.shape[0] == 0
            or not np.issubdtype(nodes_array.dtype, np.integer)):
        raise ValueError(f"nodes must be an (N, 2) array of integer grid indices, got shape "
                         f"{nodes_array.shape} of {nodes_array.dtype}")
    keys = [tuple(int(v) for v in row) for row in nodes_array]
    if len(set(keys)) != len(keys):
        seen_keys: set = set()
        duplicate = next(key for key in keys if key in seen_keys or seen_keys.add(key))
        raise ValueError(f"nodes must be distinct; node {duplicate} appears twice")
    if isinstance(pitch_mm, bool) or not isinstance(pitch_mm, (int, float)) or not (
            math.isfinite(pitch_mm) and pitch_mm > 0.0):
        raise ValueError(f"pitch_mm must be a positive finite number, got {pitch_mm!r}")
    views = list(views)
    if len(views) < 2:
        raise ValueError(f"self-calibration needs at least 2 views, got {len(views)}")
    count = len(keys)
    checked = []
    for number, view in enumerate(views):
        if not isinstance(view, GridView):
            raise ValueError(f"view {number}: must be a GridView, got {type(view).__name__}")
        centres = np.asarray(view.centres_mm, dtype=float)
        if centres.shape != (count, 2):
            raise ValueError(f"view {number}: centres_mm must have shape (N, 2) = ({count}, 2), got {centres.shape}")
        seen = np.asarray(view.seen)
        if seen.shape != (count,) or seen.dtype != bool:
            raise ValueError(f"view {number}: seen must be a boolean array of shape ({count},)")
        if not np.all(np.isfinite(centres[seen])):
            raise ValueError(f"view {number}: centres_mm holds non-finite values for seen marks")
        shift = tuple(view.shift) if isinstance(view.shift, (tuple, list, np.ndarray)) else ()
        if len(shift) != 2 or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in shift):
            raise ValueError(f"view {number}: shift must be two integers (grid pitches), got {view.shift!r}")
        sigma = np.asarray(view.sigma_mm, dtype=float) if isinstance(view.sigma_mm, (tuple, list, np.ndarray)) \
            else np.array([np.nan])
        if sigma.shape != (2,) or not np.all(np.isfinite(sigma) & (sigma > 0.0)):
            raise ValueError(f"view {number}: sigma_mm must be two positive finite numbers, got {view.sigma_mm!r}")
        if not isinstance(view.pass_type, str) or not view.pass_type:
            raise ValueError(f"view {number}: pass_type must be a non-empty string, got {view.pass_type!r}")
        if np.count_nonzero(seen) < MIN_MARKS:
            raise ValueError(f"view {number}: sees {np.count_nonzero(seen)} marks; at least {MIN_MARKS} are needed")
        checked.append((centres, seen, (int(shift[0]), int(shift[1])), view.pass_type, sigma))
    views_per_mark = np.sum([item[1] for item in checked], axis=0)
    lonely = np.flatnonzero(views_per_mark < 2)
    if lonely.size:
        k = int(lonely[0])
        raise ValueError(f"mark {k} (node {keys[k]}) is seen in {int(views_per_mark[k])} view(s); "
                         "at least 2 are needed")
    passes = list(dict.fromkeys(item[3] for item in checked))
    differences = []
    for name in passes:
        members = [number for number, item in enumerate(checked) if item[3] == name]
        shifts = {checked[number][2] for number in members}
        if len(shifts) < 2:
            raise ValueError(f"pass type {name!r} has views at 1 shift; each pass type needs views at 2 or more "
                             "shifts (one shift measures its field and the marks only together)")
        first = next(iter(sorted(shifts)))
        differences += [np.subtract(shift, first) for shift in shifts]
        for number in members:
            own = {(keys[k][0] - checked[number][2][0], keys[k][1] - checked[number][2][1])
                   for k in np.flatnonzero(checked[number][1])}
            others = set()
            for other in members:
                if other != number:
                    others |= {(keys[k][0] - checked[other][2][0], keys[k][1] - checked[other][2][1])
                               for k in np.flatnonzero(checked[other][1])}
            shared = len(own & others)
            if shared < MIN_SHARED_NODES:
                raise ValueError(f"view {number} (pass {name!r}, shift {checked[number][2]}) shares {shared} field "
                                 f"node(s) with the other views of its pass type; at least {MIN_SHARED_NODES} are "
                                 "needed (shifts that leave no overlap separate nothing)")
    if np.linalg.matrix_rank(np.array(differences, dtype=float)) < 2:
        raise ValueError("the shifts within the pass types span one direction only; the marks are then "
                         "unobservable along the other: give shifts in x and in y")
    if linear_correction is not None:
        matrix = np.asarray(linear_correction, dtype=float)
        symmetric = matrix.shape == (2, 2) and np.all(np.isfinite(matrix)) and np.allclose(matrix, matrix.T,
                                                                                           atol=1e-15)
        if not symmetric:
            raise ValueError("linear_correction must be a finite symmetric 2x2 matrix (mm per mm)")
    return nodes_array.astype(int), checked, passes


def self_calibrate(nodes, views: Sequence[GridView], pitch_mm: float, *, linear_correction=None,
                   field_model: str = "nodes", covariance: bool = False) -> SelfCalibration:
    """Separate the marks of a grid plate from the chain's error fields by views at several shifts.

    The model, the unobservable terms and the gauge are those of the module docstring.

    Parameters
    ----------
    nodes : array_like of int, shape (N, 2)
        Each mark's grid node (x, y index), distinct.
    views : sequence of GridView
        At least 2; every pass type at 2 or more shifts, the shifts within the pass types spanning x
        and y, every mark seen by 2 or more views.
    pitch_mm : float
        The grid pitch, mm.
    linear_correction : array_like, shape (2, 2), optional
        The chain's symmetric linear error (mm per mm) in the views' mean, from a reference; the
        marks lose it. None: the marks keep the views' mean linear part.
    field_model : {"nodes", "separable"}, default "nodes"
        ``nodes``: a free value per node and pass type (the exact algorithm). ``separable``: per
        pass type and axis a term per node column plus a term per node row -- a line scanner on a
        robot line errs by a function of the travel coordinate (the robot) plus one of the
        coordinate along the laser line (the sensor); far fewer unknowns, so less noise.
    covariance : bool, default False
        Also propagate the views' ``sigma_mm`` to ``mark_sigma_mm`` (a dense inverse).

    Returns
    -------
    SelfCalibration
        The marks, the fields, the views' rigid motions, the residual and the unobservable terms.

    Raises
    ------
    ValueError
        For bad shapes, non-finite centres, shifts that leave no overlap or span one direction, a
        mark seen by fewer than 2 views, or a system the views leave singular.
    """
    nodes, checked, passes = _check_inputs(nodes, views, pitch_mm, linear_correction)
    if field_model not in FIELD_MODELS:
        raise ValueError(f"field_model must be one of {', '.join(FIELD_MODELS)}, got {field_model!r}")
    count = len(nodes)
    centroid = nodes.mean(axis=0)
    position = pitch_mm * (nodes - centroid)
    # unknown layout: marks (2N), fields (2 per parameter per pass), views (3 each: cx, cy, theta)
    node_parameters, parameter_count = {}, {}
    for name in passes:
        sampled = sorted({(int(nodes[k, 0]) - item[2][0], int(nodes[k, 1]) - item[2][1])
                          for item in checked if item[3] == name for k in np.flatnonzero(item[1])})
        if field_model == "nodes":
            node_parameters[name] = {node: (number,) for number, node in enumerate(sampled)}
            parameter_count[name] = len(sampled)
        else:    # separable: a term per node column plus a term per node row
            columns = sorted({node[0] for node in sampled})
            rows_of = sorted({node[1] for node in sampled})
            node_parameters[name] = {node: (columns.index(node[0]), len(columns) + rows_of.index(node[1]))
                                     for node in sampled}
            parameter_count[name] = len(columns) + len(rows_of)
    field_start, offset = {}, 2 * count
    for name in passes:
        field_start[name] = offset
        offset += 2 * parameter_count[name]
    view_start = offset
    unknowns = view_start + 3 * len(checked)

    entry_rows, entry_cols, entry_values, weights, observed_index = [], [], [], [], []
    for number, (centres, seen, shift, name, sigma) in enumerate(checked):
        for k in np.flatnonzero(seen):
            parameters = node_parameters[name][(int(nodes[k, 0]) - shift[0], int(nodes[k, 1]) - shift[1])]
            for axis in (0, 1):
                row = len(weights)
                columns = ([2 * k + axis] + [field_start[name] + 2 * item + axis for item in parameters]
                           + [view_start + 3 * number + axis, view_start + 3 * number + 2])
                values = [1.0] * (len(columns) - 1) + [-position[k, 1] if axis == 0 else position[k, 0]]
                entry_rows += [row] * len(columns)
                entry_cols += columns
                entry_values += values
                weights.append(1.0 / sigma[axis])
                observed_index.append((number, k, axis))
    design = sparse.csr_matrix((entry_values, (entry_rows, entry_cols)), shape=(len(weights), unknowns))
    weight = np.array(weights)
    weighted = sparse.diags(weight) @ design
    normal = (weighted.T @ weighted).tocsc()
    # Jacobi scaling (unit diagonal), then the ridge: every unknown weighs alike in the gauge's norm
    scale = 1.0 / np.sqrt(normal.diagonal())
    scaling = sparse.diags(scale)
    regularised = (scaling @ normal @ scaling + RIDGE * sparse.identity(unknowns)).tocsc()
    observed = np.array(observed_index)
    measured = np.array([checked[v][0][k, axis] for v, k, axis in observed])

    rotation = np.zeros(len(checked))     # removed from the data so far
    solution = np.zeros(unknowns)
    for _ in range(PASSES):
        applied = rotation.copy()
        # remove the views' rotations found so far exactly; the linear model fits what is left
        corrected = measured.copy()
        for number, (centres, seen, _shift, _name, _sigma) in enumerate(checked):
            if rotation[number] == 0.0:
                continue
            cos, sin = math.cos(rotation[number]), math.sin(rotation[number])
            pick = observed[:, 0] == number
            xy = centres.copy()
            xy = np.column_stack([cos * xy[:, 0] + sin * xy[:, 1], -sin * xy[:, 0] + cos * xy[:, 1]])
            corrected[pick] = xy[observed[pick, 1], observed[pick, 2]]
        with warnings.catch_warnings():
            warnings.simplefilter("error", MatrixRankWarning)
            try:
                solution = scale * spsolve(regularised, scale * (weighted.T @ (weight * corrected)))
            except MatrixRankWarning:
                raise ValueError("the views leave the system singular") from None
        if not np.all(np.isfinite(solution)):
            raise ValueError("the views leave the system singular")
        step = solution[view_start + 2::3].copy()
        # a rotation common to a pass type's views is unobservable (its field's rotation): only the
        # rotations within a pass type are removed from the data
        for name in passes:
            members = [number for number, item in enumerate(checked) if item[3] == name]
            step[members] -= step[members].mean()
        rotation = rotation + step
        if np.max(np.abs(step)) < 1e-12:
            break
    residual = (design @ solution - corrected).reshape(-1)
    residual_rms = tuple(float(np.sqrt(np.mean(residual[observed[:, 2] == axis] ** 2))) for axis in (0, 1))

    marks = solution[:2 * count].reshape(count, 2)
    # gauge: the marks' affine part equals that of the views' mean measured centres
    mean_measured = np.zeros((count, 2))
    for centres, seen, _shift, _name, _sigma in checked:
        mean_measured[seen] += centres[seen]
    mean_measured /= np.sum([item[1] for item in checked], axis=0)[:, None]
    basis = affine_basis(nodes, pitch_mm)
    coefficients = np.linalg.lstsq(basis, (mean_measured - marks).ravel(), rcond=None)[0]
    if linear_correction is not None:
        matrix = np.asarray(linear_correction, dtype=float)
        coefficients[3:] -= (matrix[0, 0], matrix[1, 1], matrix[0, 1])
    marks = marks + (basis @ coefficients).reshape(count, 2)
    symmetric = np.array([[coefficients[3], coefficients[5]], [coefficients[5], coefficients[4]]])
    fields = []
    for name in passes:
        field_nodes = np.array(list(node_parameters[name]), dtype=int)
        start = field_start[name]
        values = solution[start:start + 2 * parameter_count[name]].reshape(-1, 2)
        error = np.array([values[list(node_parameters[name][tuple(node)])].sum(axis=0) for node in field_nodes])
        error = error - (pitch_mm * (field_nodes - centroid)) @ symmetric.T
        fields.append(PassField(name, field_nodes, error))
    views_part = solution[view_start:].reshape(-1, 3)

    sigma_marks = None
    if covariance:
        inverse = scale[:, None] * np.linalg.inv(regularised.toarray()) * scale[None, :]
        covariance_all = inverse @ normal.toarray() @ inverse
        block = covariance_all[:2 * count, :2 * count]
        projector = np.eye(2 * count) - basis @ np.linalg.pinv(basis)
        sigma_marks = np.sqrt(np.clip(np.diag(projector @ block @ projector.T), 0.0, None)).reshape(count, 2)
    return SelfCalibration(marks_mm=marks, mark_sigma_mm=sigma_marks, fields=tuple(fields),
                           view_translation_mm=views_part[:, :2].copy(), view_rotation_rad=applied + views_part[:, 2],
                           residual_rms_mm=residual_rms, unobservable=UNOBSERVABLE)
