"""The discrepancy workflow's report: residual-field and gap plots, Markdown, JSON, written atomically."""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
import shutil
import tempfile

import numpy as np

from gls_calibration.discrepancy.measurements_file import Measurements
from gls_calibration.discrepancy.results import DiscrepancyResult


# --------------------------------------------------------------------------------------------------
# outputs

def _plot_residual_fields(result: DiscrepancyResult, path: Path) -> None:
    """Residual arrows before and after (same scale), and the map of what is left unexplained."""
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    points = result.commanded_xy
    before, after = result.residual_before_xy, result.residual_after_xy
    span = float(np.max(np.ptp(points, axis=0))) or 1.0
    longest = float(np.max(np.hypot(*before.T))) or 1e-9
    scale = longest / (0.08 * span)        # data mm per plot mm: longest arrow ~8 % of the field, both panels
    key = float(f"{longest:.1g}")
    figure, axes = plt.subplots(1, 3, figsize=(18, 5.8), sharex=True, sharey=True)
    for axis, residual, title in ((axes[0], before, f"before: RMS {result.rms_before_mm:.4f} mm"),
                                  (axes[1], after, f"after {', '.join(result.named_effects) or 'nothing'}: "
                                                   f"RMS {result.rms_after_mm:.4f} mm")):
        arrows = axis.quiver(points[:, 0], points[:, 1], residual[:, 0], residual[:, 1], angles="xy",
                             scale_units="xy", scale=scale, width=0.003, color="tab:red")
        axis.quiverkey(arrows, 0.82, 1.02, key, f"{key:g} mm", labelpos="E")
        axis.set_title(title, fontsize=10, loc="left")
    # the map of the verdict: |residual| after the named effects, outliers marked
    shown = axes[2].scatter(points[:, 0], points[:, 1], c=np.hypot(*after.T), s=30, cmap="viridis", vmin=0.0)
    figure.colorbar(shown, ax=axes[2], label="|residual| after (mm)")
    if result.outliers:
        axes[2].scatter([o.position_mm[0] for o in result.outliers], [o.position_mm[1] for o in result.outliers],
                        marker="x", s=80, color="tab:red", label="outliers (excluded)")
        axes[2].legend(loc="upper right", fontsize=8)
    axes[2].set_title(f"{result.verdict.verdict}: {result.verdict.unexplained_rms_mm:.4f} mm "
                      + ("of structure below the floor" if result.verdict.below_floor else "above the floor"),
                      fontsize=10, loc="left")
    for axis in axes:
        axis.set_xlabel("x (mm, gls)")
        axis.set_aspect("equal")
    axes[0].set_ylabel("y (mm, gls)")
    figure.suptitle(f"residual after rigid alignment (same arrow scale); {result.floor.source} noise floor "
                    f"{result.noise_floor_mm:.4f} mm")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def _plot_gap(result: DiscrepancyResult, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    labels = ["model"] + [f"+ {step.name}" for step in result.steps]
    gaps = result.gap_per_step_mm
    figure, axis = plt.subplots(figsize=(max(5.0, 1.4 * len(labels) + 2), 4))
    axis.bar(range(len(gaps)), gaps, color="tab:blue")
    axis.axhline(result.noise_floor_mm, color="tab:red", linestyle="--",
                 label=f"noise floor {result.noise_floor_mm:.4f} mm")
    axis.set_xticks(range(len(gaps)), labels, rotation=20, ha="right")
    axis.set_ylabel("residual RMS (mm)")
    axis.set_title("gap between model and measurement per step")
    axis.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def _format_parameters(step) -> str:
    return "; ".join(f"{name} = {value:.4g} ± {step.uncertainty[name]:.2g} {step.units[name]}"
                     for name, value in step.parameters.items())


def _data_row(data: Measurements, index: int):
    return data.data_rows[index] if data.data_rows else index


def _format_values(values, units) -> str:
    return "; ".join(f"{name} = {value:.4g} {units.get(name, '')}".rstrip() for name, value in values.items())


def _report_markdown(result: DiscrepancyResult, measured: Path, model: Path | None, data: Measurements) -> str:
    from gls_calibration.discrepancy import verdict_lines
    from gls_calibration.discrepancy.separability import SEPARABLE_AT
    from gls_calibration.discrepancy.verdict import naming_phrase

    criterion = result.criterion.upper()
    floor = result.floor
    lines = [
        "# Discrepancy report",
        "",
        f"- measurements: `{measured}` ({len(data.commanded_xy)} points"
        + (f", {floor.repeats} repeats averaged" if floor.repeats > 1 else "")
        + (", a calibration run's fiducials.csv, stage 'before'" if data.source_format == "fiducials" else "")
        + (f", {len(data.dropped_lines)} row(s) with NaN dropped" if data.dropped_lines else "")
        + (", with marking time" if result.t is not None else ", no marking time") + ")",
        f"- model: `{model}`" if model is not None else "- model: published defaults",
        f"- known effects: {', '.join(f'{k} = {list(v)}' for k, v in result.known_effects.values.items()) or 'none'}",
        f"- user effects: {', '.join(effect.name for effect in result.user_effects) or 'none'}",
        "",
        "## Verdict",
        "",
    ] + verdict_lines(result) + [
        "",
        "![residual before, after, and where the unexplained part is](residual_field.png)",
        "",
        "## Gap",
        "",
        "| | value |",
        "|---|---|",
        f"| residual RMS before | {result.rms_before_mm:.4f} mm |",
        f"| residual RMS after | {result.rms_after_mm:.4f} mm |",
        f"| noise floor ({floor.source}) | {floor.noise_floor_mm:.4f} mm ({floor.sigma_axis_mm:.4f} mm per axis) |",
        f"| residual roughness (cross-check) | {floor.residual_estimate_mm:.4f} mm |",
        f"| structure test before (F-test p) | {result.structure_before.p_value:.3g} "
        f"({'smooth structure' if result.structure_before.is_structure else 'no smooth structure'}) |",
        f"| structure test after (F-test p) | {result.structure_after.p_value:.3g} "
        f"({'smooth structure' if result.structure_after.is_structure else 'no smooth structure'}) |",
        f"| named effects | {naming_phrase(result) if result.named_effects or result.named_groups else 'none'} |",
        f"| outliers excluded | {len(result.outliers)} |",
        "",
        f"Stopped because {result.stop_reason}.",
        "",
        "![gap per step](gap_per_step.png)",
        "",
    ]
    if result.outliers:
        lines += ["## Outliers (excluded from every fit)", "",
                  "| data row | size (mm) | x (mm) | y (mm) |", "|---|---|---|---|"]
        lines += [f"| {_data_row(data, o.index)} | {o.size_mm:.4f} | {o.position_mm[0]:.2f} | {o.position_mm[1]:.2f} |"
                  for o in result.outliers]
        lines.append("")
    lines += ["## Steps", ""]
    if result.steps:
        lines += [f"| step | effect | parameters (± 1 sigma) | indistinguishable from | {criterion} gain "
                  "| RMS before → after (mm) | dropped |",
                  "|---|---|---|---|---|---|---|"]
        for number, step in enumerate(result.steps, start=1):
            lines.append(f"| {number} | {step.name} | {_format_parameters(step)} | "
                         f"{', '.join(step.indistinguishable_from) or '-'} | {step.improvement:.1f} | "
                         f"{step.rms_before_mm:.4f} → {step.rms_after_mm:.4f} | {', '.join(step.removed) or '-'} |")
        lines += ["", "Final joint fit (± 1 sigma; correlation with the rigid rotation / translation x / y). "
                  f"z is the size of what survives the rigid alignment and the other fitted effects over its "
                  f"standard error; an effect is named alone at z >= {SEPARABLE_AT:g} when no other candidate "
                  "brings it below that. Each effect's definition (the convention its values refer to) follows "
                  "its values.", ""]
        separability = {record.name: record for record in result.separability}
        for name in result.fitted_effects:
            values = result.model_effects.get(name) if name in result.model_effects.values else result.user_values[name]
            spec = _effect_spec(result, name)
            record = separability.get(name)
            status = ("named" if name in result.named_effects else
                      f"named as a group with {', '.join(record.group[1:])}" if record is not None
                      and record.separable_from_rigid else "not named: not separable from the rigid motion")
            lines.append(f"- **{name}** ({status}" + (f"; z = {record.z:.1f}" if record is not None else "") + ")")
            for i, (parameter, unit) in enumerate(zip(spec.parameter_names, spec.units)):
                label = f"{name}.{parameter}"
                corr = result.rigid_correlation.get(label, {})
                lines.append(f"  - {label} = {values[i]:.4g} ± {result.model_uncertainty[name][i]:.2g} {unit} "
                             f"(correlation {corr.get('rotation', math.nan):+.2f}"
                             f" / {corr.get('translation_x', math.nan):+.2f}"
                             f" / {corr.get('translation_y', math.nan):+.2f})")
            lines.append(f"  - definition: {spec.doc}")
        for number, step in enumerate(result.steps, start=1):
            lines += ["", f"### Candidates at step {number}", "",
                      f"| candidate | {criterion} gain | RMS after (mm) | field difference to best (mm) |",
                      "|---|---|---|---|"]
            lines += [f"| {c.name} | {c.improvement:.1f} | {c.rms_after_mm:.4f} | {c.field_difference_mm:.4f} |"
                      for c in step.candidates]
    else:
        lines.append("No missing effect named.")
    if result.implausible:
        lines += ["", "## Not named: physically implausible fits", ""]
        lines += [f"- step {i.step}: {i.name} ({_format_values(i.parameters, {})}): {i.why}"
                  for i in result.implausible]
    lines += ["", "## Where the residual lives", ""]
    for label, location in (("before", result.location_before), ("after", result.location_after)):
        lines.append(f"- {label}: RMS x {location.rms_x_mm:.4f} mm, y {location.rms_y_mm:.4f} mm; centre "
                     f"{location.rms_centre_mm:.4f} mm, edge {location.rms_edge_mm:.4f} mm"
                     + (f"; {'; '.join(location.findings)}" if location.findings else ""))
    lines += ["", "## Notes", ""] + [f"- {note}" for note in result.notes] + [""]
    return "\n".join(lines)


def _effect_spec(result: DiscrepancyResult, name: str):
    """Return the table entry (library or user effect) that defines ``name``'s parameters."""
    from gls_calibration.geometry.effect_table import EFFECT_TABLE

    for effect in result.user_effects:
        if effect.name == name:
            return effect.spec
    return EFFECT_TABLE[name]


def write_discrepancy_report(result: DiscrepancyResult, out: Path, measured: Path, model: Path | None,
                             data: Measurements) -> None:
    """Render the discrepancy report in a temporary directory beside ``out``, then move it in atomically.

    The folder gets ``discrepancy.json``, ``residual_field.png``, ``gap_per_step.png`` and
    ``report.md``; an existing folder has each of these files replaced atomically.

    Parameters
    ----------
    result : DiscrepancyResult
        The workflow's result.
    out : pathlib.Path
        The report folder (created with its parents).
    measured : pathlib.Path
        The measurement file, named in the report.
    model : pathlib.Path or None
        The head configuration used, named in the report.
    data : Measurements
        The validated input (its rows name the outliers; its dropped lines are listed).

    Raises
    ------
    OSError
        If the folder cannot be created or written (the temporary directory is removed).
    """
    from gls_calibration.common.files import nan_to_none, to_plain

    out = out.resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        document = result.to_dict()
        for entry, outlier in zip(document["outliers"], result.outliers):
            entry["index"] = _data_row(data, outlier.index)      # the CSV's 0-based data row
        document["input"] = {"measured": str(measured), "model": None if model is None else str(model),
                             "format": data.source_format, "dropped_lines": list(data.dropped_lines)}
        text = json.dumps(nan_to_none(to_plain(document)), indent=2) + "\n"
        (staging / "discrepancy.json").write_text(text, encoding="utf-8")
        _plot_residual_fields(result, staging / "residual_field.png")
        _plot_gap(result, staging / "gap_per_step.png")
        (staging / "report.md").write_text(_report_markdown(result, measured, model, data), encoding="utf-8")
        for item in staging.iterdir():
            with item.open("rb") as handle:
                os.fsync(handle.fileno())
        if not out.exists():
            os.replace(staging, out)      # the whole directory appears at once
            return
        for item in staging.iterdir():   # existing directory: each file replaced atomically
            os.replace(item, out / item.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
