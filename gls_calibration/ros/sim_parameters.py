"""Parameters of the simulation nodes: the sim configuration file and the true defects.

The true defects are parameters of their own so that a run can override one
(``-p effects.galvo_gain_x:=[0.02]``).
"""
from __future__ import annotations

import dataclasses

from gls_calibration.common.config_files import config_path
from gls_calibration.geometry.effect_table import EFFECT_TABLE
from gls_calibration.geometry.optics import HeadEffects
from gls_calibration.ros.base import GlsNode
from gls_calibration.simulation.world import SimConfig, load_sim_config


def declare_sim_config(node: GlsNode) -> SimConfig:
    """Load ``sim_config`` with the ``effects.*`` and ``seed`` parameters applied.

    Load ``sim_config`` (default: the package's config/sim.yaml) with the ``effects.*`` and ``seed``
    parameters applied; ValueError names a bad file or defect.
    """
    path = node.declare("sim_config", "", "sim configuration file (empty: the package's config/sim.yaml)")
    preset = node.declare("measurement_preset", "", "measurement chain preset: ideal, careful, paper_like or "
                          "custom (empty: the file's measurement.preset)")
    config = load_sim_config(path or config_path("sim.yaml"), preset or None)
    values = {}
    for name, spec in EFFECT_TABLE.items():
        units = ", ".join(f"{p.name} [{p.unit}]" for p in spec.parameters)
        values[name] = tuple(node.declare(f"effects.{name}", [float(v) for v in config.effects.get(name)],
                                          f"true {name} of the simulated head: {units}"))
    seed = node.declare("seed", config.seed, "seed of the simulated cell's random draws", minimum=0)
    return dataclasses.replace(config, effects=HeadEffects(values), seed=seed)
