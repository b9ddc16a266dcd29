"""Head configuration file: nominal geometry and effects already known, in one YAML file.

The file is a ROS 2 parameter file (``config/head.yaml``)::

    /**:
      ros__parameters:
        head:
          working_distance_mm: 490.0
          mirror_distance_mm: 15.0
          mirror_limit_deg: 10.5
          focus_range_mm: 25.0
          effects:                 # optional, name -> parameters (effect_table.EFFECT_TABLE order and units)
            galvo_gain_x: [0.0012]

Nodes see the same values as the parameters ``head.working_distance_mm`` and so on (ROS flattens the
nested dict into dotted names). This loader also takes the dotted spelling, and a plain YAML mapping
without the ``/**: ros__parameters:`` wrapper. Missing geometry keys take the published defaults.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping


from gls_calibration.common.config_files import config_path, read_config_file
from gls_calibration.common.validation import as_config_number
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.geometry.optics import HeadEffects

_NOMINAL = HeadGeometry()
#: Geometry keys of the ``head`` block and their defaults (HeadGeometry's: the published set-up).
HEAD_DEFAULTS: dict[str, float] = {
    "working_distance_mm": _NOMINAL.working_distance_mm,
    "mirror_distance_mm": _NOMINAL.mirror_distance_mm,
    "mirror_limit_deg": math.degrees(_NOMINAL.mirror_limit_rad),
    "focus_range_mm": _NOMINAL.focus_range_mm,
}


def default_head_config_path() -> Path:
    """Return the package's ``config/head.yaml``.

    Returns
    -------
    pathlib.Path
        The path of the head configuration installed with the package.
    """
    return config_path("head.yaml")


def _undot(mapping: Mapping[str, Any]) -> dict[str, Any]:
    """Turn dotted keys (``head.working_distance_mm``) into nested dicts, as ROS does."""
    nested: dict[str, Any] = {}
    for key, value in mapping.items():
        parts = str(key).split(".")
        target = nested
        for part in parts[:-1]:
            target = target.setdefault(part, {})
            if not isinstance(target, dict):
                raise ValueError(f"head configuration key {key!r} clashes with a value")
        if isinstance(value, Mapping):
            value = _undot(value)
            if isinstance(target.get(parts[-1]), dict):
                target[parts[-1]].update(value)
                continue
        target[parts[-1]] = value
    return nested


def parameters_block(document: Any) -> dict[str, Any]:
    """Return the parameter mapping of a ROS parameter file or of a plain mapping.

    Parameters
    ----------
    document : mapping or None
        A parsed YAML document: a ROS parameter file (the ``/**`` entry's ``ros__parameters`` is
        preferred, else the first node's) or a plain mapping; dotted keys are nested.

    Returns
    -------
    dict
        The parameters, nested by their dotted names; empty for None.

    Raises
    ------
    ValueError
        If ``document`` or its ``ros__parameters`` is not a mapping.
    """
    if document is None:
        return {}
    if not isinstance(document, Mapping):
        raise ValueError(f"head configuration must be a mapping, got {type(document).__name__}")
    wrapped = {key: value for key, value in document.items()
               if isinstance(value, Mapping) and "ros__parameters" in value}
    if wrapped:
        # prefer the wildcard entry that every node reads
        entry = wrapped.get("/**", next(iter(wrapped.values())))
        document = entry["ros__parameters"] or {}
        if not isinstance(document, Mapping):
            raise ValueError("ros__parameters must be a mapping")
    return _undot(document)


def head_config_from_dict(document: Any) -> tuple[HeadGeometry, HeadEffects]:
    """Build the geometry and the known effects from a parsed head configuration (see the module docstring).

    Parameters
    ----------
    document : mapping or None
        A parsed ROS parameter file or plain mapping; the keys are read from its ``head`` block when
        there is one (``working_distance_mm``, ``mirror_distance_mm``, ``mirror_limit_deg``,
        ``focus_range_mm``, ``effects``); absent keys take the defaults.

    Returns
    -------
    geometry : HeadGeometry
        The nominal head (mm, rad).
    effects : HeadEffects
        The effects already known for this head.

    Raises
    ------
    ValueError
        If the document or its ``head`` block is not a mapping, a key is unknown, a value is not a
        finite number, the geometry is not valid or an effect is bad.
    """
    parameters = parameters_block(document)
    head = parameters.get("head", parameters)
    if not isinstance(head, Mapping):
        raise ValueError(f"'head' must be a mapping, got {type(head).__name__}")
    known = set(HEAD_DEFAULTS) | {"effects"}
    unknown = sorted(set(head) - known)
    if unknown:
        raise ValueError(f"unknown head parameter(s) {', '.join(map(repr, unknown))}; "
                         f"known: {', '.join(sorted(known))}")
    values = {key: as_config_number(head.get(key, default), key, "head parameter")
              for key, default in HEAD_DEFAULTS.items()}
    geometry = HeadGeometry(
        working_distance_mm=values["working_distance_mm"],
        mirror_distance_mm=values["mirror_distance_mm"],
        mirror_limit_rad=math.radians(values["mirror_limit_deg"]),
        focus_range_mm=values["focus_range_mm"],
    )
    return geometry, effects_from_mapping(head.get("effects"), "head effects")


def effects_from_mapping(effects: Any, what: str) -> HeadEffects:
    """Read named effects from a YAML mapping ``name: [parameters...]``.

    Parameters
    ----------
    effects : mapping or None
        Effect name -> list of parameters (a lone number stands for one parameter); None or empty
        means no effect.
    what : str
        What the mapping is, for the error message.

    Returns
    -------
    HeadEffects
        The effects, validated.

    Raises
    ------
    ValueError
        If ``effects`` is not a mapping, a value is not a finite number, an effect name is unknown or
        an effect has the wrong number of parameters.
    """
    effects = effects or {}
    if not isinstance(effects, Mapping):
        raise ValueError(f"{what} must be a mapping of effect name to parameters, got {effects!r}")
    cleaned = {}
    for name, parameters_of_effect in effects.items():
        listed = parameters_of_effect if isinstance(parameters_of_effect, (list, tuple)) else [parameters_of_effect]
        cleaned[str(name)] = tuple(as_config_number(value, f"effects.{name}", "head parameter") for value in listed)
    return HeadEffects(cleaned)


def load_head_config(path: str | Path) -> tuple[HeadGeometry, HeadEffects]:
    """Read a head configuration YAML file.

    Parameters
    ----------
    path : str or pathlib.Path
        The YAML file (e.g. ``config/head.yaml``).

    Returns
    -------
    geometry : HeadGeometry
        The nominal head (mm, rad).
    effects : HeadEffects
        The effects already known for this head.

    Raises
    ------
    ValueError
        With the file name, for an unreadable file or YAML, unknown keys, bad values or unknown effect names.
    """
    return read_config_file(path, "head configuration", head_config_from_dict)
