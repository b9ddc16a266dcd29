"""Every stored deviation model type by its ``type`` key: rebuilding a model from its plain form, YAML files.

The registry sits above the modules that define the types (``rbf``, ``physical_model``), so none of
them needs to know the others: a new type is one entry in ``MODEL_TYPES``.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
import os
from types import MappingProxyType
from typing import Any

import yaml

from gls_calibration.common.files import atomic_write_text
from gls_calibration.common.validation import require_mapping
from gls_calibration.models.physical_model import PhysicalDeviationModel, SumModel
from gls_calibration.models.rbf import DeviationModel, OLSRBFNetwork, ThinPlateSplineModel


def model_from_dict(data: Mapping[str, Any]) -> DeviationModel:
    """Rebuild any deviation model from its ``to_dict()`` form, dispatching on ``type``.

    Parameters
    ----------
    data : mapping
        A model's ``to_dict()`` form; ``type`` is one of ``MODEL_TYPES`` (``ols_rbf``,
        ``thin_plate_spline``, ``physical``, ``sum``).

    Returns
    -------
    DeviationModel
        The model, evaluating as the one that was stored (never refitted).

    Raises
    ------
    ValueError
        If ``data`` is not a mapping, its type is unknown, or the type's ``from_dict`` rejects it.

    Examples
    --------
    >>> from gls_calibration.models.thin_plate_spline import ThinPlateSplineModel
    >>> points = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 100.0], [100.0, 100.0]])
    >>> model = ThinPlateSplineModel(points, 0.001 * points)
    >>> rebuilt = model_from_dict(model.to_dict())
    >>> type(rebuilt).__name__, bool(np.allclose(rebuilt(points), model(points)))
    ('ThinPlateSplineModel', True)
    """
    require_mapping(data, "model description")
    kind = data.get("type")
    if kind not in MODEL_TYPES:
        raise ValueError(f"unknown model type {kind!r}; known types: {', '.join(sorted(MODEL_TYPES))}")
    return MODEL_TYPES[kind](data)


# type key -> builder of a model from its description; a sum's parts go back through the registry.
MODEL_TYPES: Mapping[str, Callable[[Mapping[str, Any]], DeviationModel]] = MappingProxyType({
    "ols_rbf": OLSRBFNetwork.from_dict,
    "thin_plate_spline": ThinPlateSplineModel.from_dict,
    "physical": PhysicalDeviationModel.from_dict,
    "sum": lambda data: SumModel.from_dict(data, model_from_dict),
})


def save_model_yaml(path: str | os.PathLike, model: DeviationModel) -> None:
    """Write ``model.to_dict()`` as YAML, atomically (a reader sees the old or the whole new file)."""
    atomic_write_text(path, yaml.safe_dump(model.to_dict(), sort_keys=False))


def load_model_yaml(path: str | os.PathLike) -> DeviationModel:
    """Read a model written by :func:`save_model_yaml`."""
    with open(path, encoding="utf-8") as stream:
        return model_from_dict(yaml.safe_load(stream))
