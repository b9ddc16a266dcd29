"""gls-measure: offline measurement of a plate scan file (npz organized / unorganized, pcd, ply)."""
import csv
import json
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gls_calibration.cli.measure import CSV_HEADER, main
from rendering import BASE_SCAN, grid_truth, plate_to_scanner, render_plate_scan

PER_SIDE = 3
SIZE_MM = 2 * 190.0 / 18


@pytest.fixture(scope="module")
def scan():
    truth_uv = grid_truth(PER_SIDE, seed=5)
    xyz, intensity = render_plate_scan(truth_uv, size_mm=(30.0, 30.0), speckle=0.1, speckle_corr_px=1.5,
                                       dropout_fraction=0.01, supersampling=3, **BASE_SCAN)
    return xyz, intensity, plate_to_scanner(truth_uv, BASE_SCAN["tilt_rad"], BASE_SCAN["offset_mm"])


def _save_npz(path, xyz, values, **override):
    arrays = dict(x=xyz[..., 0], y=xyz[..., 1], z=xyz[..., 2], intensity=values)
    arrays.update(override)
    np.savez(path, **{name: value for name, value in arrays.items() if value is not None})
    return path


def _run(cloud, out, *extra):
    return main(["--cloud", str(cloud), "--grid", str(PER_SIDE), "--size", str(SIZE_MM), "--out", str(out),
                 *extra])


def _rows(out):
    with (out / "centres.csv").open(newline="") as stream:
        return list(csv.DictReader(stream))


@pytest.mark.parametrize("organized", [True, False])
def test_npz_cloud_gives_centres_picture_and_summary(tmp_path, scan, organized):
    xyz, intensity, truth = scan
    if not organized:
        xyz, intensity = xyz.reshape(-1, 3), intensity.reshape(-1)
    cloud = _save_npz(tmp_path / "scan.npz", xyz, intensity)
    out = tmp_path / "result" / "deep"
    assert _run(cloud, out) == 0
    assert (out / "centres.csv").read_text().splitlines()[0] == CSV_HEADER
    rows = _rows(out)
    ok = np.array([[float(row[k]) for k in ("x", "y", "z")] for row in rows if row["status"] == "ok"])
    assert len(ok) == PER_SIDE**2
    distance, index = cKDTree(truth).query(ok)
    assert len(set(index)) == PER_SIDE**2 and distance.max() < 0.03
    assert all(0 < float(row["sigma_x_um"]) < 10 and 0.75 <= float(row["coverage"]) <= 1 for row in rows
               if row["status"] == "ok")
    assert all(row["status"] == "ok" or row["status"].startswith("rejected:") for row in rows)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["accepted"] == PER_SIDE**2 and summary["missing"] == 0
    assert 0 < summary["sigma_x_um"]["median"] <= summary["sigma_x_um"]["max"]
    assert summary["time_s"] > 0
    assert (out / "detections.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(out.glob(".*.tmp"))


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
def test_open3d_cloud_files(tmp_path, scan, suffix):
    import open3d as o3d

    xyz, intensity, truth = scan
    keep = np.isfinite(intensity.reshape(-1))
    cloud = o3d.t.geometry.PointCloud()
    cloud.point["positions"] = o3d.core.Tensor(xyz.reshape(-1, 3)[keep].astype(np.float32))
    cloud.point["intensity"] = o3d.core.Tensor(intensity.reshape(-1, 1)[keep].astype(np.float32))
    path = tmp_path / f"scan{suffix}"
    assert o3d.t.io.write_point_cloud(str(path), cloud)
    assert _run(path, tmp_path / "out") == 0
    assert sum(row["status"] == "ok" for row in _rows(tmp_path / "out")) == PER_SIDE**2


def test_no_fiducial_writes_the_header_and_exits_0(tmp_path):
    xyz, intensity = render_plate_scan(np.empty((0, 2)), size_mm=(30.0, 30.0), noise=2.0)
    assert _run(_save_npz(tmp_path / "bare.npz", xyz, intensity), tmp_path / "out") == 0
    assert (tmp_path / "out" / "centres.csv").read_text() == CSV_HEADER + "\n"
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["accepted"] == 0


def _two_fiducials():
    """A scan as large as the grid's with only two of its fiducials marked: too few to use."""
    return render_plate_scan(grid_truth(PER_SIDE, seed=5)[:2], size_mm=(30.0, 30.0), supersampling=3, **BASE_SCAN)


def _bad_clouds(tmp_path, xyz, intensity):
    unreadable = tmp_path / "broken.npz"
    unreadable.write_bytes(b"not a zip file")
    flat = np.stack(list(np.meshgrid(np.arange(50.0), np.arange(50.0))) + [np.zeros((50, 50))], axis=-1)
    scattered = np.random.default_rng(1).uniform(-50, 50, (2000, 3))
    return {
        "missing array": (_save_npz(tmp_path / "a.npz", xyz, intensity, intensity=None), "missing array(s) intensity"),
        "shapes": (_save_npz(tmp_path / "b.npz", xyz, intensity, z=xyz[:-1, :, 2]), "must have one shape"),
        "unreadable": (unreadable, "unreadable npz file"),
        "missing file": (tmp_path / "nothing.npz", "no such file"),
        "type": (tmp_path / "scan.txt", "unsupported file type"),
        "no plane": (_save_npz(tmp_path / "c.npz", scattered, np.ones(2000)), ""),
        "few found": (_save_npz(tmp_path / "d.npz", *_two_fiducials()), "at least 4"),
        "small cloud": (_save_npz(tmp_path / "f.npz", xyz[:100, :100], intensity[:100, :100]),
                        "cannot hold the 3x3 grid"),
        "flat": (_save_npz(tmp_path / "e.npz", flat, np.full((50, 50), np.nan)), ""),
    }


@pytest.mark.parametrize("case", ["missing array", "shapes", "unreadable", "missing file", "type", "no plane",
                                  "few found", "small cloud", "flat"])
def test_bad_input_exits_2_and_writes_nothing(tmp_path, scan, capsys, case):
    xyz, intensity, _ = scan
    (tmp_path / "scan.txt").write_text("1 2 3\n")
    cloud, message = _bad_clouds(tmp_path, xyz, intensity)[case]
    out = tmp_path / "out"
    assert _run(cloud, out) == 2
    error = capsys.readouterr().err
    assert error.startswith("gls-measure: ") and message in error
    assert not out.exists()


def test_bad_arguments_exit_2(tmp_path, scan):
    xyz, intensity, _ = scan
    cloud = _save_npz(tmp_path / "scan.npz", xyz, intensity)
    for extra in (["--rings", "2.5,x"], ["--pixel", "0"], ["--rings", "2.5,2.5"]):
        with pytest.raises(SystemExit) as stop:
            _run(cloud, tmp_path / "out", *extra)
        assert stop.value.code == 2
    assert not (tmp_path / "out").exists()


def test_console_script_is_installed(tmp_path):
    tool = Path(sys.executable).parent / "gls-measure"
    assert tool.is_file()
    result = subprocess.run([tool, "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "--cloud" in result.stdout and "--rings" in result.stdout


def _summary(out):
    return json.loads((out / "summary.json").read_text())


@pytest.mark.parametrize("units", [None, "m"])
def test_cloud_in_metres_is_measured_as_the_one_in_mm(tmp_path, scan, units):
    # The same unorganized cloud in mm and in metres (as most ROS and PCL exports give): the same
    # centres, in mm, whether the unit is given or found from the plate's extent against --size.
    xyz, intensity, truth = scan
    xyz, intensity = xyz.reshape(-1, 3), intensity.reshape(-1)
    assert _run(_save_npz(tmp_path / "mm.npz", xyz, intensity), tmp_path / "mm") == 0
    extra = () if units is None else ("--units", units)
    assert _run(_save_npz(tmp_path / "m.npz", xyz / 1000.0, intensity), tmp_path / "m", *extra) == 0
    in_mm, in_m = _rows(tmp_path / "mm"), _rows(tmp_path / "m")
    assert [row["status"] for row in in_m] == [row["status"] for row in in_mm]
    centres_mm = np.array([[float(row[k]) for k in ("x", "y", "z")] for row in in_mm])
    centres_m = np.array([[float(row[k]) for k in ("x", "y", "z")] for row in in_m])
    np.testing.assert_allclose(centres_m, centres_mm, atol=1e-5)
    ok = centres_m[[row["status"] == "ok" for row in in_m]]
    assert len(ok) == PER_SIDE**2 and cKDTree(truth).query(ok)[0].max() < 0.03
    assert _summary(tmp_path / "mm")["cloud_units"] == "mm" and _summary(tmp_path / "m")["cloud_units"] == "m"


def test_units_option_overrides_the_geometry(tmp_path, scan, capsys):
    # A cloud in metres declared as mm (0.03 mm wide) is refused, naming both sizes, though the
    # geometry alone would have read it as metres.
    xyz, intensity, _ = scan
    cloud = _save_npz(tmp_path / "m.npz", xyz / 1000.0, intensity)
    assert _run(cloud, tmp_path / "out", "--units", "mm") == 2
    assert capsys.readouterr().err == (
        "gls-measure: cloud extent 0.02991 x 0.02991 mm (read as mm) cannot hold the 3x3 grid: it needs "
        "26.51 x 26.51 mm (--size 21.1111 mm plus rings of 2.7 mm); check --size and --units\n")
    assert not (tmp_path / "out").exists()


def test_cloud_too_small_for_the_grid_is_refused_naming_both_sizes(tmp_path, scan, capsys):
    xyz, intensity, _ = scan
    cloud = _save_npz(tmp_path / "small.npz", xyz[:100, :100], intensity[:100, :100])
    assert _run(cloud, tmp_path / "out") == 2
    assert capsys.readouterr().err == (
        "gls-measure: cloud extent 9.901 x 9.904 mm (read as mm) cannot hold the 3x3 grid: it needs "
        "26.51 x 26.51 mm (--size 21.1111 mm plus rings of 2.7 mm); check --size and --units\n")
    assert not (tmp_path / "out").exists()


def test_pixel_comes_from_the_point_spacing_unless_given(tmp_path, scan):
    # Points 0.15 mm apart: one pixel per point, not a 0.1 mm raster with holes between them.
    xyz, intensity = render_plate_scan(grid_truth(PER_SIDE, seed=5), size_mm=(30.0, 30.0), pixel_mm=0.15,
                                       supersampling=3, **BASE_SCAN)
    coarse = _save_npz(tmp_path / "coarse.npz", xyz.reshape(-1, 3), intensity.reshape(-1))
    assert _run(coarse, tmp_path / "auto") == 0
    summary = _summary(tmp_path / "auto")
    assert summary["pixel_from"] == "point spacing" and summary["accepted"] == PER_SIDE**2
    assert summary["pixel_pitch_mm"] == pytest.approx([0.15, 0.15], rel=0.01)
    assert _run(coarse, tmp_path / "given", "--pixel", "0.1") == 0
    given = _summary(tmp_path / "given")
    assert given["pixel_from"] == "--pixel" and given["pixel_pitch_mm"] == pytest.approx([0.1, 0.1], rel=0.01)
