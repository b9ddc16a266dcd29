"""The full 19x19 calibration loop with validation on the simulated cell, over several seeds.

Runs ``gls-sim-cell`` (every node in one process, real DDS inside it) per seed and iteration count
and prints the TRUE errors on the validation grid, the wall time and the peak memory of each run,
then the medians and worst cases. Each seed draws its own noise, robot path errors and textures.

Run: .venv/bin/python benchmarks/bench_sim_cell.py [--seeds 1 2 3 4 5] [--iterations 1 2] [--grid 19]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
import resource
import statistics
import subprocess
import sys
import tempfile
import time

from gls_calibration.config_files import config_path

FIGURES = ("pre_rms_mm", "pre_max_mm", "true_post_rms_mm", "true_post_max_mm", "true_post_rms_150_mm")


def run(seed: int, iterations: int, grid: int, out: Path, extra: list[str]) -> dict:
    """One gls-sim-cell run; its summary.json plus wall time and the child's peak RSS."""
    script = Path(sys.executable).with_name("gls-sim-cell")
    began = time.perf_counter()
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    result = subprocess.run([str(script), "--out", str(out), "--seed", str(seed), "--grid", str(grid),
                             "--iterations", str(iterations), *extra], capture_output=True, text=True)
    wall = time.perf_counter() - began
    if result.returncode != 0:
        raise RuntimeError(f"gls-sim-cell failed (seed {seed}):\n{result.stderr[-2000:]}")
    summary = json.loads((out / "summary.json").read_text())
    summary["wall_s"] = wall
    summary["peak_rss_mb"] = max(before, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) / 1024.0
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--iterations", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--grid", type=int, default=19)
    parser.add_argument("--no-path-error", action="store_true",
                        help="a cell whose robot path repeats exactly (scanner.path_repeatability_mm 0)")
    parser.add_argument("extra", nargs="*", help="more gls-sim-cell arguments after --")
    args = parser.parse_args()
    if args.no_path_error:
        # The per-sweep path error shifts the measured plate height, hence the commanded z and the
        # field's scale (dr/r = dz/d): the floor of what a calibration can reach in this cell.
        text = config_path("sim.yaml").read_text()
        variant = Path(tempfile.mkdtemp(prefix="gls-bench-")) / "sim_no_path_error.yaml"
        variant.write_text(text.replace("path_repeatability_mm: 0.05", "path_repeatability_mm: 0.0"))
        args.extra += ["--sim-config", str(variant)]
    header = f"{'iter':>4} {'seed':>4} " + " ".join(f"{name:>20}" for name in FIGURES) + f" {'wall s':>7} {'RSS MB':>7}"
    print(f"gls-sim-cell, {args.grid}x{args.grid} grid with validation (18x18 between the training fiducials), mm")
    print(header)
    for iterations in args.iterations:
        rows = []
        for seed in args.seeds:
            with tempfile.TemporaryDirectory() as out:
                summary = run(seed, iterations, args.grid, Path(out), args.extra)
            rows.append(summary)
            print(f"{iterations:>4} {seed:>4} " + " ".join(f"{summary[name]:>20.4f}" for name in FIGURES)
                  + f" {summary['wall_s']:>7.1f} {summary['peak_rss_mb']:>7.0f}", flush=True)
        for label, pick in (("median", statistics.median), ("worst", max)):
            print(f"{iterations:>4} {label:>6}" + " ".join(f"{pick(row[name] for row in rows):>20.4f}" for name in FIGURES)
                  + f" {pick(row['wall_s'] for row in rows):>7.1f} {pick(row['peak_rss_mb'] for row in rows):>7.0f}")


if __name__ == "__main__":
    main()
