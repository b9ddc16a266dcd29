"""Tests of the human report: files written, valid PNGs, strict JSON, Table 1 numbers, CSV rows."""
from __future__ import annotations

import csv
import json
import math
import os

from matplotlib.image import imread
import numpy as np
import pytest

from gls_calibration.report.files import (ReportData, format_mm, summary_json, table1_markdown, write_report,
                                          write_summary_json)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def grid(per_side: int = 19, size_mm: float = 180.0) -> np.ndarray:
    axis = np.linspace(-size_mm / 2.0, size_mm / 2.0, per_side)
    x, y = np.meshgrid(axis, axis)
    return np.column_stack([x.ravel(), y.ravel()])


def metrics(scale: float, count: int) -> dict:
    """Known Table 1 metrics: every number distinct so a misplaced column shows."""
    def field(offset: float, n: int) -> dict:
        return {"count": n, "max_ux_mm": scale * (1.0 + offset), "rms_ux_mm": scale * (0.2 + offset),
                "max_uy_mm": scale * (1.1 + offset), "rms_uy_mm": scale * (0.3 + offset),
                "max_abs_mm": scale * (1.5 + offset), "rms_abs_mm": scale * (0.4 + offset)}
    return {"full": field(0.0, count), "150x150": field(0.01, 225), "50x50": field(0.02, 25)}


def make_data(seed: int = 0, with_truth: bool = True, with_after: bool = True, correction="callable") -> ReportData:
    rng = np.random.default_rng(seed)
    targets = grid()
    before = rng.normal(0.0, 0.6, targets.shape)
    after_targets = grid(per_side=10)
    after = rng.normal(0.0, 0.05, after_targets.shape)
    if correction == "callable":
        correction_field = lambda points: -0.005 * points  # noqa: E731
    elif correction == "grid":
        x, y = np.meshgrid(np.linspace(-90, 90, 7), np.linspace(-90, 90, 5))
        correction_field = (x, y, 0.01 * y, -0.01 * x)
    else:
        correction_field = None
    return ReportData(
        targets_xy=targets, deviations_before=before, metrics_before=metrics(1.0, 361),
        targets_after=after_targets if with_after else None, deviations_after=after if with_after else None,
        metrics_after=metrics(0.1, 100) if with_after else None,
        true_before=before + 0.01 if with_truth else None,
        true_after=after + 0.01 if with_truth and with_after else None,
        true_metrics_before=metrics(1.01, 361) if with_truth else None,
        true_metrics_after=metrics(0.11, 100) if with_truth and with_after else None,
        correction_field=correction_field,
        summary={"pre_rms_mm": 0.854, "post_rms_mm": math.nan, "neurons": np.int64(42), "duration_s": 12.5},
        extra_lines=("Simulated run, seed 0.",),
    )


def check_png(path) -> None:
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE
    image = imread(path)
    assert image.ndim == 3 and image.shape[0] >= 200 and image.shape[1] >= 200
    # Not a blank canvas: the plot draws something other than the background.
    assert np.ptp(image[..., :3]) > 0.5


def test_report_writes_every_file(tmp_path):
    report = write_report(tmp_path / "out", make_data())
    assert report == tmp_path / "out" / "report.md"
    names = sorted(path.name for path in report.parent.iterdir())
    assert names == ["correction_field.png", "cumulative_histogram.png", "deviations_arrows.png",
                     "fiducials.csv", "report.md", "summary.json"]
    for name in ("correction_field.png", "cumulative_histogram.png", "deviations_arrows.png"):
        check_png(report.parent / name)
    text = report.read_text()
    for name in ("deviations_arrows.png", "cumulative_histogram.png", "correction_field.png"):
        assert f"]({name})" in text
    assert "Simulated run, seed 0." in text


def test_a_report_that_fails_midway_leaves_the_previous_files_whole(tmp_path, monkeypatch):
    # every file goes through a temporary file and a rename: make the renames fail and the files of
    # the report before must be byte for byte what they were, with no temporary file left behind
    out = tmp_path / "out"
    write_report(out, make_data(seed=0))
    before = {path.name: path.read_bytes() for path in out.iterdir()}

    def refuse(source, target):
        raise OSError("disk full")
    monkeypatch.setattr(os, "replace", refuse)
    with pytest.raises(OSError, match="disk full"):
        write_report(out, make_data(seed=1))
    with pytest.raises(OSError, match="disk full"):
        write_summary_json(out, {"pre_rms_mm": 1.0})
    assert {path.name: path.read_bytes() for path in out.iterdir()} == before


def test_arrow_panels_share_one_layout(tmp_path):
    with_after = write_report(tmp_path / "a", make_data())
    before_only = write_report(tmp_path / "b", make_data(with_after=False))
    wide = imread(with_after.parent / "deviations_arrows.png")
    single = imread(before_only.parent / "deviations_arrows.png")
    assert wide.shape[0] == single.shape[0]
    # before, after (same scale) and after at its own scale, side by side, same panel size
    assert wide.shape[1] == 3 * single.shape[1]


def test_summary_json_is_strict_with_null_for_nan(tmp_path):
    report = write_report(tmp_path, make_data())
    text = (tmp_path / "summary.json").read_text()
    assert "NaN" not in text
    summary = json.loads(text)
    assert summary == {"pre_rms_mm": 0.854, "post_rms_mm": None, "neurons": 42, "duration_s": 12.5}
    assert "| post_rms_mm | n/a |" in report.read_text()
    assert json.loads(summary_json({"a": [np.float32(np.inf), 1]})) == {"a": [None, 1]}


def test_table1_rows_hold_the_metrics(tmp_path):
    text = write_report(tmp_path, make_data()).read_text()
    expected_rows = [
        "| 190x190 (full) | measured | 361 | 1.000 | 0.200 | 1.100 | 0.300 | 1.500 | 0.400 "
        "| 100 | 0.100 | 0.020 | 0.110 | 0.030 | 0.150 | 0.040 |",
        "| 190x190 (full) | true | 361 | 1.010 | 0.202 | 1.111 | 0.303 | 1.515 | 0.404 "
        "| 100 | 0.110 | 0.022 | 0.121 | 0.033 | 0.165 | 0.044 |",
        "| 150x150 | measured | 225 | 1.010 | 0.210 | 1.110 | 0.310 | 1.510 | 0.410 "
        "| 225 | 0.101 | 0.021 | 0.111 | 0.031 | 0.151 | 0.041 |",
        "| 50x50 | measured | 25 | 1.020 | 0.220 | 1.120 | 0.320 | 1.520 | 0.420 "
        "| 25 | 0.102 | 0.022 | 0.112 | 0.032 | 0.152 | 0.042 |",
    ]
    lines = text.splitlines()
    for row in expected_rows:
        assert row in lines
    table = [line for line in lines if line.startswith("| 190x190") or line.startswith("| 150x150")
             or line.startswith("| 50x50")]
    assert [line.split(" | ")[0:2] for line in table] == [
        ["| 190x190 (full)", "measured"], ["| 190x190 (full)", "true"], ["| 150x150", "measured"],
        ["| 150x150", "true"], ["| 50x50", "measured"], ["| 50x50", "true"]]
    # Every table row has as many cells as the header (escaped pipes do not split cells).
    header = next(line for line in lines if line.startswith("| Field |"))
    cells = lambda line: len(line.replace("\\|", "").split("|"))  # noqa: E731
    assert all(cells(line) == cells(header) == 16 + 2 for line in table)  # 16 cells, outer pipes


def test_published_reference_next_to_run(tmp_path):
    text = write_report(tmp_path, make_data()).read_text()
    assert "| before RMS \\|d\\| | 0.854 | 0.400 | 0.404 |" in text
    assert "| before max \\|d\\| | 2.080 | 1.500 | 1.515 |" in text
    assert "| after RMS \\|d\\| | 0.071 | 0.040 | 0.044 |" in text
    assert "| after max \\|d\\| | 0.250 | 0.150 | 0.165 |" in text


def test_report_without_after_and_truth(tmp_path):
    data = make_data(with_truth=False, with_after=False, correction=None)
    report = write_report(tmp_path, data)
    text = report.read_text()
    assert "| 190x190 (full) | measured | 361 | 1.000 | 0.200 | 1.100 | 0.300 | 1.500 | 0.400 | n/a |" in text
    assert "| true |" not in text
    assert not (tmp_path / "correction_field.png").exists()
    assert "No correction field was given." in text
    with (tmp_path / "fiducials.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 361
    assert "true_dx_mm" not in rows[0]


def test_fiducials_csv_rows_and_values(tmp_path):
    data = make_data()
    write_report(tmp_path, data)
    with (tmp_path / "fiducials.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 361 + 100
    assert [row["stage"] for row in rows].count("after") == 100
    first = rows[0]
    assert float(first["target_x_mm"]) == data.targets_xy[0, 0]
    assert float(first["dx_mm"]) == data.deviations_before[0, 0]  # full precision
    assert float(first["abs_mm"]) == pytest.approx(np.hypot(*data.deviations_before[0]), rel=1e-15)
    assert float(rows[361]["true_dy_mm"]) == data.true_after[0, 1]


def test_precomputed_correction_grid(tmp_path):
    write_report(tmp_path, make_data(correction="grid"))
    check_png(tmp_path / "correction_field.png")
    scattered = (np.array([0.0, 10.0, 0.0]), np.array([0.0, 0.0, 10.0]), np.ones(3), np.zeros(3))
    data = ReportData(targets_xy=grid(3), deviations_before=np.zeros((9, 2)), metrics_before={},
                      correction_field=scattered)
    write_report(tmp_path / "scattered", data)
    check_png(tmp_path / "scattered" / "correction_field.png")


def test_bad_correction_field(tmp_path):
    data = ReportData(targets_xy=grid(3), deviations_before=np.zeros((9, 2)), metrics_before={},
                      correction_field=lambda points: points[:, 0])
    with pytest.raises(ValueError, match=r"^correction_field must return an array of shape \(625, 2\), got \(625,\)$"):
        write_report(tmp_path, data)
    data = ReportData(targets_xy=grid(3), deviations_before=np.zeros((9, 2)), metrics_before={},
                      correction_field=(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(2)))
    with pytest.raises(ValueError, match=r"X, Y, dX, dY must have the same shape, got \(3,\), \(3,\), \(3,\), \(2,\)$"):
        write_report(tmp_path, data)


@pytest.mark.parametrize("changes, message", [
    ({"deviations_before": np.zeros((5, 2))}, r"^deviations_before must have 9 rows like its targets, got 5$"),
    ({"targets_xy": np.zeros((9, 3))}, r"^targets_xy must have shape \(N, 2\), got \(9, 3\)$"),
    ({"deviations_before": np.full((9, 2), np.nan)}, r"^deviations_before contains 18 NaN or infinite value\(s\)$"),
    ({"targets_after": np.zeros((4, 2))}, r"^targets_after and deviations_after must be given together$"),
    ({"true_after": np.zeros((4, 2))}, r"^true_after needs targets_after and deviations_after$"),
    ({"targets_after": np.zeros((4, 2)), "deviations_after": np.zeros((3, 2))},
     r"^deviations_after must have 4 rows like its targets, got 3$"),
])
def test_report_data_validation(changes, message):
    arguments = {"targets_xy": grid(3), "deviations_before": np.zeros((9, 2)), "metrics_before": {}} | changes
    with pytest.raises(ValueError, match=message):
        ReportData(**arguments)


def test_formatting_helpers():
    assert format_mm(0.0714999) == "0.071"
    assert format_mm(None) == "n/a"
    assert format_mm(float("nan")) == "n/a"
    data = make_data(with_truth=False)
    assert table1_markdown(data)[0].startswith("| Field | Source | before n | before max u_x |")
