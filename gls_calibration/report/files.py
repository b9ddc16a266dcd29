"""Human-readable calibration report: Markdown tables, PNG plots, a per-fiducial CSV and a JSON summary.

``write_report(out_dir, data)`` writes into ``out_dir``:

- ``report.md``: run summary, the Table 1 layout of the paper (rows: field and source, columns:
  max/RMS of u_x, u_y, |delta| before and after), the published reference figures, the plots;
- ``deviations_arrows.png``: deviation vectors before and after on the same axes and arrow scale;
- ``cumulative_histogram.png``: cumulative distribution of |delta| (measured, and true when given);
- ``correction_field.png``: the fitted correction (only when ``correction_field`` is given);
- ``fiducials.csv``: one row per fiducial and stage;
- ``summary.json``: the summary dict. JSON has no NaN: NaN and infinities are written as ``null``.

Plots use matplotlib's Agg canvas directly (no pyplot, no display, no global backend switch).
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
import csv
from dataclasses import dataclass, field
from datetime import datetime, timezone
import io
import json
import math
from pathlib import Path
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure, SubplotParams
import numpy as np

import gls_calibration
from gls_calibration.common.files import atomic_write_bytes, atomic_write_text, nan_to_none, to_plain
from gls_calibration.common.validation import as_points

# Published results of the in-situ calibration (|delta| over the full 190 x 190 mm field).
PUBLISHED_REFERENCE_MM = {"before_rms": 0.854, "before_max": 2.08, "after_rms": 0.071, "after_max": 0.25}
METRIC_COLUMNS = (
    ("max_ux_mm", "max u_x"), ("rms_ux_mm", "RMS u_x"), ("max_uy_mm", "max u_y"),
    ("rms_uy_mm", "RMS u_y"), ("max_abs_mm", r"max \|d\|"), ("rms_abs_mm", r"RMS \|d\|"),
)
CORRECTION_GRID_PER_SIDE = 25
_DPI = 100
PNG_COMPRESS_LEVEL = 1

SUMMARY_FILE = "summary.json"
"""The run summary's file name in a report folder (``write_summary_json``)."""

CorrectionGrid = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class ReportData:
    """Everything the report shows; deviations in mm, target minus measured (delta = Q - P).

    ``deviations_after``/``targets_after`` are the validation grid (both or neither);
    ``true_before``/``true_after`` are deviations against the simulation's ground truth, row for row
    with the measured ones. ``correction_field`` is either a callable mapping (K, 2) points (mm)
    to (K, 2) correction offsets (mm), evaluated on a grid over the targets, or a precomputed
    ``(X, Y, dX, dY)`` tuple of equally shaped arrays (2-D mesh or scattered 1-D).
    Metrics dicts are those of ``registration.deviation_metrics``.
    """

    targets_xy: np.ndarray
    deviations_before: np.ndarray
    metrics_before: Mapping[str, Mapping[str, float]]
    summary: Mapping[str, Any] = field(default_factory=dict)
    targets_after: np.ndarray | None = None
    deviations_after: np.ndarray | None = None
    metrics_after: Mapping[str, Mapping[str, float]] | None = None
    true_before: np.ndarray | None = None
    true_after: np.ndarray | None = None
    true_metrics_before: Mapping[str, Mapping[str, float]] | None = None
    true_metrics_after: Mapping[str, Mapping[str, float]] | None = None
    correction_field: Callable[[np.ndarray], np.ndarray] | CorrectionGrid | None = None
    extra_lines: tuple[str, ...] = ()
    extra_files: tuple[str, ...] = ()    # further '- `name`: what it is' lines of the Files section
    certificate_lines: tuple[str, ...] = ()   # the "Certificate" section (report.certificate); none when empty
    title: str = "Galvo laser scanner calibration report"
    full_field_label: str = "190x190 (full)"

    def __post_init__(self) -> None:
        """Validate the fields and store them normalised (ValueError on the first bad one)."""
        def set_points(name: str, rows: int | None) -> None:
            value = getattr(self, name)
            if value is None:
                return
            points = as_points(value, name, 2)
            if rows is not None and points.shape[0] != rows:
                raise ValueError(f"{name} must have {rows} rows like its targets, got {points.shape[0]}")
            object.__setattr__(self, name, points)

        set_points("targets_xy", None)
        count = self.targets_xy.shape[0]
        set_points("deviations_before", count)
        set_points("true_before", count)
        if (self.targets_after is None) != (self.deviations_after is None):
            raise ValueError("targets_after and deviations_after must be given together")
        set_points("targets_after", None)
        after_count = None if self.targets_after is None else self.targets_after.shape[0]
        set_points("deviations_after", after_count)
        if self.true_after is not None and self.targets_after is None:
            raise ValueError("true_after needs targets_after and deviations_after")
        set_points("true_after", after_count)
        object.__setattr__(self, "extra_lines", tuple(self.extra_lines))


def write_report(out_dir: str | Path, data: ReportData) -> Path:
    """Write the report files into ``out_dir`` (created if needed) and return the path of report.md."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    figures = [("Deviations before and after", _plot_deviation_arrows(out_dir / "deviations_arrows.png", data)),
               ("Cumulative distribution of |delta|",
                _plot_cumulative_histogram(out_dir / "cumulative_histogram.png", data))]
    if data.correction_field is not None:
        figures.append(("Fitted correction", _plot_correction_field(out_dir / "correction_field.png", data)))
    _write_fiducials_csv(out_dir / "fiducials.csv", data)
    write_summary_json(out_dir, data.summary)
    report_path = out_dir / "report.md"
    atomic_write_text(report_path, _markdown(data, [(title, path.name) for title, path in figures]))
    return report_path


def write_summary_json(out_dir: str | Path, summary: Mapping[str, Any]) -> Path:
    """Write ``out_dir/summary.json`` atomically (a reader sees the old or the whole new summary).

    Parameters
    ----------
    out_dir : str or pathlib.Path
        The report folder (it must exist).
    summary : Mapping
        The summary's values; NaN and infinities are written as null.

    Returns
    -------
    pathlib.Path
        The path of ``summary.json``.

    Raises
    ------
    OSError
        If it cannot be written; an existing ``summary.json`` is then left as it was.
    """
    path = Path(out_dir) / SUMMARY_FILE
    atomic_write_text(path, summary_json(summary) + "\n")
    return path


# ----------------------------------------------------------------------------------------- text


def json_safe(value: Any) -> Any:
    """Convert numpy types to Python ones and NaN/infinity to None, recursively.

    Parameters
    ----------
    value : object
        Numbers, arrays, mappings, sequences and dataclasses, nested.

    Returns
    -------
    object
        The same structure in plain Python types, ready for ``json.dumps``.

    Examples
    --------
    >>> json_safe({"rms_mm": np.float64(0.5), "sigma": np.array([1.0, np.nan])})
    {'rms_mm': 0.5, 'sigma': [1.0, None]}
    """
    return nan_to_none(to_plain(value))


def summary_json(summary: Mapping[str, Any]) -> str:
    """Return the summary as strict JSON (NaN written as null)."""
    return json.dumps(json_safe(summary), indent=2, allow_nan=False)


def format_value(value: Any) -> str:
    """Short text for a summary value: n/a for missing/NaN, 4 significant digits for floats."""
    if value is None:
        return "n/a"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        value = float(value)
        if not math.isfinite(value):
            return "n/a"
        return f"{value:.1f}" if abs(value) >= 1000.0 else f"{value:.4g}"
    return str(value)


def format_mm(value: Any) -> str:
    """Return a length in the Table 1 style (three decimals, mm); n/a for missing or NaN."""
    if value is None:
        return "n/a"
    value = float(value)
    return "n/a" if not math.isfinite(value) else f"{value:.3f}"


def _field_keys(*metrics: Mapping | None) -> list[str]:
    keys: list[str] = []
    for entry in metrics:
        for key in entry or {}:
            if key not in keys:
                keys.append(key)
    return keys


def _metric_cells(metrics: Mapping | None, field_key: str) -> list[str]:
    values = (metrics or {}).get(field_key)
    if values is None:
        return ["n/a"] * (1 + len(METRIC_COLUMNS))
    count = values.get("count")
    return [format_value(count)] + [format_mm(values.get(key)) for key, _ in METRIC_COLUMNS]


def table1_markdown(data: ReportData) -> list[str]:
    """Markdown lines of the Table 1 layout: one row per field and source (measured, then true)."""
    sources = [("measured", data.metrics_before, data.metrics_after)]
    if data.true_metrics_before is not None or data.true_metrics_after is not None:
        sources.append(("true", data.true_metrics_before, data.true_metrics_after))
    header = ["Field", "Source"]
    for stage in ("before", "after"):
        header += [f"{stage} n"] + [f"{stage} {label}" for _, label in METRIC_COLUMNS]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * 2 + "---:|" * (len(header) - 2)]
    for field_key in _field_keys(data.metrics_before, data.metrics_after,
                                 data.true_metrics_before, data.true_metrics_after):
        label = data.full_field_label if field_key == "full" else field_key
        for source, before, after in sources:
            cells = [label, source] + _metric_cells(before, field_key) + _metric_cells(after, field_key)
            lines.append("| " + " | ".join(cells) + " |")
    return lines


def _full_metric(metrics: Mapping | None, key: str) -> Any:
    return ((metrics or {}).get("full") or {}).get(key)


def reference_markdown(data: ReportData) -> list[str]:
    """Markdown lines comparing |delta| over the full field with the published figures."""
    # Pipes inside table cells are escaped (\|) so Markdown keeps the columns.
    rows = [(r"before RMS \|d\|", "before_rms", data.metrics_before, data.true_metrics_before, "rms_abs_mm"),
            (r"before max \|d\|", "before_max", data.metrics_before, data.true_metrics_before, "max_abs_mm"),
            (r"after RMS \|d\|", "after_rms", data.metrics_after, data.true_metrics_after, "rms_abs_mm"),
            (r"after max \|d\|", "after_max", data.metrics_after, data.true_metrics_after, "max_abs_mm")]
    lines = ["| Quantity (full field, mm) | published | this run, measured | this run, true |",
             "|---|---:|---:|---:|"]
    for label, reference_key, measured, true, metric_key in rows:
        lines.append(f"| {label} | {format_mm(PUBLISHED_REFERENCE_MM[reference_key])} | "
                     f"{format_mm(_full_metric(measured, metric_key))} | {format_mm(_full_metric(true, metric_key))} |")
    return lines


def _markdown(data: ReportData, figures: list[tuple[str, str]]) -> str:
    now = datetime.now(timezone.utc).isoformat(timespec="seconds")
    lines = [f"# {data.title}", "",
             f"Generated {now} by gls_calibration {gls_calibration.__version__}. Lengths in mm; "
             "deviations are target minus measured position (delta = Q - P, after the best rigid "
             "alignment).", "",
             "## Run summary", "", "| Item | Value |", "|---|---:|"]
    lines += [f"| {key} | {format_value(value)} |" for key, value in data.summary.items()]
    lines += ["", "## Deviations (Table 1 layout)", "",
              "u_x, u_y: deviation components; |d|: deviation length; n: fiducials in the field.", ""]
    lines += table1_markdown(data)
    lines += ["", "## Published reference", "",
              "Figures reported for the published set-up (19 x 19 grid over 190 x 190 mm):", ""]
    lines += reference_markdown(data)
    if data.certificate_lines:
        lines += ["", "## Certificate", ""] + list(data.certificate_lines)
    lines += ["", "## Figures", ""]
    for title, name in figures:
        lines += [f"### {title}", "", f"![{title}]({name})", ""]
    if data.correction_field is None:
        lines += ["No correction field was given.", ""]
    lines += ["## Files", "",
              "- `fiducials.csv`: one row per fiducial and stage (before/after).",
              "- `summary.json`: the run summary (NaN written as null)."] + list(data.extra_files) + [""]
    if data.extra_lines:
        lines += ["## Notes", ""] + list(data.extra_lines) + [""]
    return "\n".join(lines)


def _write_fiducials_csv(path: Path, data: ReportData) -> None:
    """One row per fiducial and stage; true columns only when some ground truth is given."""
    with_truth = data.true_before is not None or data.true_after is not None
    header = ["stage", "index", "target_x_mm", "target_y_mm", "dx_mm", "dy_mm", "abs_mm"]
    if with_truth:
        header += ["true_dx_mm", "true_dy_mm", "true_abs_mm"]
    stages = [("before", data.targets_xy, data.deviations_before, data.true_before)]
    if data.targets_after is not None:
        stages.append(("after", data.targets_after, data.deviations_after, data.true_after))
    handle = io.StringIO(newline="")
    writer = csv.writer(handle)
    writer.writerow(header)
    for stage, targets, deviations, truth in stages:
        for index, (target, deviation) in enumerate(zip(targets, deviations)):
            row = [stage, index, float(target[0]), float(target[1]), float(deviation[0]),
                   float(deviation[1]), float(np.hypot(*deviation))]
            if with_truth:
                row += ([float(truth[index, 0]), float(truth[index, 1]), float(np.hypot(*truth[index]))]
                        if truth is not None else ["", "", ""])
            writer.writerow(row)
    atomic_write_text(path, handle.getvalue())


# ---------------------------------------------------------------------------------------- plots


def report_figure(width_in: float, height_in: float, *, left_in: float, right_in: float, bottom_in: float,
                  top_in: float = 0.3, wspace: float = 0.2) -> Figure:
    """Return a Figure of the report with fixed margins (inches from each edge) for its labels.

    Fixed margins instead of ``Figure.tight_layout``: a figure of the report always carries the same
    labels, and tight_layout measured them by laying out every axis's ticks once more before the
    rendering did it again (0.4-0.5 s of the manager's CPU for the main job's four plots). The margins
    hold the widest tick labels the report's fields give (about -100 mm on the axes, five characters
    on a colour bar) with room to spare.
    """
    return Figure(figsize=(width_in, height_in), subplotpars=SubplotParams(
        left=left_in / width_in, right=1.0 - right_in / width_in, bottom=bottom_in / height_in,
        top=1.0 - top_in / height_in, wspace=wspace))


def save_figure(figure: Figure, path: Path) -> Path:
    """Render ``figure`` to the PNG ``path`` at the report's resolution; the path.

    A figure with a layout engine (``Figure.tight_layout`` leaves one) is drawn once more by savefig:
    the report's figures have fixed margins instead (:func:`report_figure`).
    """
    FigureCanvasAgg(figure)  # attaches the Agg canvas: rendering never touches a display backend
    image = io.BytesIO()
    # zlib level 1 instead of PIL's 6: the same pixels in ~10 % more bytes, at well under half the
    # encoding CPU (0.13 -> 0.05 s for the main job's four plots)
    figure.savefig(image, format="png", dpi=_DPI, pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL})
    # not cleared after: Figure.clear clears every axes again (new ticks and spines) for a figure
    # that is dropped anyway
    atomic_write_bytes(path, image.getvalue())
    return path


def _nice_step(value: float) -> float:
    """Return the largest 1/2/5 x 10^k not above ``value`` (for arrow scale keys)."""
    if not math.isfinite(value) or value <= 0.0:
        return 1.0
    exponent = math.floor(math.log10(value))
    for mantissa in (5.0, 2.0, 1.0):
        if mantissa * 10.0 ** exponent <= value:
            return mantissa * 10.0 ** exponent
    return 10.0 ** exponent


def _typical_spacing(points: np.ndarray) -> float:
    """Median nearest-neighbour distance; sets how long the longest arrow may be drawn."""
    if points.shape[0] < 2:
        return 1.0
    from scipy.spatial import cKDTree
    distances, _ = cKDTree(points).query(points, k=2)
    spacing = float(np.median(distances[:, 1]))
    return spacing if spacing > 0.0 else 1.0


def _arrow_scale(targets: np.ndarray, deviations_list: list[np.ndarray]) -> tuple[float, float]:
    """Return a round magnification (the longest arrow spans 0.75-1.5 grid spacings) and key length (mm)."""
    longest = max(float(np.max(np.hypot(dev[:, 0], dev[:, 1]))) for dev in deviations_list)
    if longest <= 0.0:
        return 1.0, 1.0
    return _nice_step(1.5 * _typical_spacing(targets) / longest), _nice_step(longest / 2.0)


def _plot_deviation_arrows(path: Path, data: ReportData) -> Path:
    # Before and after share one layout and one arrow scale, so the improvement is seen as it is;
    # a third panel shows the after field at its own scale, so its pattern stays readable.
    shared = [("before", data.targets_xy, data.deviations_before)]
    if data.targets_after is not None:
        shared.append(("after", data.targets_after, data.deviations_after))
    magnification, key_length = _arrow_scale(data.targets_xy, [dev for _, _, dev in shared])
    panels = [(stage, targets, deviations, magnification, key_length) for stage, targets, deviations in shared]
    if data.targets_after is not None:
        own, own_key = _arrow_scale(data.targets_after, [data.deviations_after])
        panels.append(("after, own scale", data.targets_after, data.deviations_after, own, own_key))
    all_targets = np.vstack([panel[1] for panel in panels])
    lower, upper = all_targets.min(axis=0), all_targets.max(axis=0)
    margin = 0.08 * max(float(np.max(upper - lower)), 1.0)
    # the bottom margin also holds the arrow keys under the axes
    figure = report_figure(5.0 * len(panels), 5.4, left_in=0.9, right_in=0.2, bottom_in=0.3, wspace=0.05)
    axes_list = figure.subplots(1, len(panels), sharex=True, sharey=True, squeeze=False)[0]
    for axes, (stage, targets, deviations, scale, key) in zip(axes_list, panels):
        axes.plot(targets[:, 0], targets[:, 1], ".", color="0.6", markersize=2)
        arrows = axes.quiver(targets[:, 0], targets[:, 1], deviations[:, 0], deviations[:, 1],
                             angles="xy", scale_units="xy", scale=1.0 / scale, color="C3", width=0.004)
        axes.quiverkey(arrows, 0.80, -0.16, key, f"{key:g} mm", labelpos="E", coordinates="axes")
        rms = float(np.sqrt(np.mean(np.sum(deviations ** 2, axis=1))))
        axes.set_title(f"{stage}: RMS |d| {rms:.3f} mm, arrows x{scale:g}", loc="left", fontsize=10)
        axes.set_xlim(lower[0] - margin, upper[0] + margin)
        axes.set_ylim(lower[1] - margin, upper[1] + margin)
        axes.set_aspect("equal")
        axes.set_xlabel("x (mm)")
    axes_list[0].set_ylabel("y (mm)")
    return save_figure(figure, path)


def _plot_cumulative_histogram(path: Path, data: ReportData) -> Path:
    series = [("before, measured", data.deviations_before, "C3", "-"),
              ("after, measured", data.deviations_after, "C2", "-"),
              ("before, true", data.true_before, "C3", "--"),
              ("after, true", data.true_after, "C2", "--")]
    figure = report_figure(6.0, 4.0, left_in=0.75, right_in=0.2, bottom_in=0.6, top_in=0.2)
    axes = figure.subplots()
    for label, deviations, colour, style in series:
        if deviations is None:
            continue
        lengths = np.sort(np.hypot(deviations[:, 0], deviations[:, 1]))
        fraction = np.arange(1, lengths.size + 1) / lengths.size
        axes.step(np.concatenate([[0.0], lengths]), np.concatenate([[0.0], fraction]), where="post",
                  color=colour, linestyle=style, label=label)
    axes.set_xlabel("|d| (mm)")
    axes.set_ylabel("fraction of fiducials")
    axes.set_ylim(0.0, 1.02)
    axes.set_xlim(left=0.0)
    axes.grid(True, alpha=0.3)
    axes.legend(loc="lower right", fontsize=8)
    return save_figure(figure, path)


def _correction_grid(data: ReportData) -> CorrectionGrid:
    """Return the correction as (X, Y, dX, dY): evaluated on a grid over the targets, or as given."""
    field_value = data.correction_field
    if callable(field_value):
        targets = data.targets_xy if data.targets_after is None else np.vstack([data.targets_xy, data.targets_after])
        lower, upper = targets.min(axis=0), targets.max(axis=0)
        grid_x, grid_y = np.meshgrid(np.linspace(lower[0], upper[0], CORRECTION_GRID_PER_SIDE),
                                     np.linspace(lower[1], upper[1], CORRECTION_GRID_PER_SIDE))
        offsets = np.asarray(field_value(np.column_stack([grid_x.ravel(), grid_y.ravel()])), dtype=float)
        if offsets.shape != (grid_x.size, 2):
            raise ValueError(f"correction_field must return an array of shape ({grid_x.size}, 2), "
                             f"got {offsets.shape}")
        return grid_x, grid_y, offsets[:, 0].reshape(grid_x.shape), offsets[:, 1].reshape(grid_x.shape)
    if len(field_value) != 4:
        raise ValueError("correction_field must be a callable or a tuple (X, Y, dX, dY)")
    arrays = [np.asarray(item, dtype=float) for item in field_value]
    if any(item.shape != arrays[0].shape for item in arrays):
        raise ValueError("correction_field arrays X, Y, dX, dY must have the same shape, got "
                         + ", ".join(str(item.shape) for item in arrays))
    return tuple(arrays)


def _plot_correction_field(path: Path, data: ReportData) -> Path:
    grid_x, grid_y, offset_x, offset_y = _correction_grid(data)
    magnitude = np.hypot(offset_x, offset_y)
    figure = report_figure(6.0, 5.0, left_in=0.85, right_in=0.45, bottom_in=0.6)
    axes = figure.subplots()
    if grid_x.ndim == 2 and min(grid_x.shape) >= 2:
        image = axes.pcolormesh(grid_x, grid_y, magnitude, shading="nearest", cmap="viridis")
        # At most ~20 arrows per side keep the quiver readable.
        step = max(1, max(grid_x.shape) // 20)
        sample = (slice(None, None, step), slice(None, None, step))
    else:
        image = axes.scatter(grid_x.ravel(), grid_y.ravel(), c=magnitude.ravel(), cmap="viridis", s=12)
        sample = (slice(None),)
    axes.quiver(grid_x[sample], grid_y[sample], offset_x[sample], offset_y[sample], color="white",
                angles="xy", pivot="middle")
    figure.colorbar(image, ax=axes, label="|correction| (mm)")
    axes.set_aspect("equal")
    axes.set_xlabel("x (mm)")
    axes.set_ylabel("y (mm)")
    axes.set_title("fitted correction (arrows: direction, colour: magnitude)", fontsize=10)
    return save_figure(figure, path)
