"""Fiducial measurement on plates from two independent renderers (issue 31 item 2).

Each condition of ``test/plate_renderers.py`` (point pitch 0.07 / 0.1 / 0.15 mm, correlated speckle
of contrast 0.3, marks darkening the steel to 85 %, a 3 deg tilt) is rendered as a 19x19 plate by the
project's renderer (``test/rendering.py``) and by an independent one (``test/rendering_independent.py``:
flat-topped lines, speckle from random phasors, darkness varying along the path, jittered scan
lines), handed over as an unorganized cloud in mm and measured as ``gls-measure`` does without
``--pixel`` (``measure_fiducials`` defaults, polarity found by the measurement). Printed per renderer
and condition: fiducials found (accepted and within 1 mm of a true centre) of 361, candidates
rejected, per-axis RMS and worst error of the accepted centres against the TRUE centres (um), how
many accepted centres are beyond 30 um, the raster pixel used and the measurement's wall time.
Targets (issue 31): 361/361, <= 10 um RMS per axis, none accepted beyond 30 um.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_vision_renderers.py [--per-side 19]
     [--seed 0] [--renderers project independent] [--only CONDITION ...]
"""
from __future__ import annotations

import argparse
from pathlib import Path
import sys
import time

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
from plate_renderers import CONDITIONS, RENDERERS, render  # noqa: E402

from gls_calibration.fiducials.measure import measure_fiducials  # noqa: E402
from gls_calibration.scan.plate_pose import estimate_plate_pose  # noqa: E402

MATCH_MM = 1.0
LIMIT_MM = 0.030


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--per-side", type=int, default=19)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--renderers", nargs="*", default=list(RENDERERS), choices=RENDERERS)
    parser.add_argument("--only", nargs="*", default=list(CONDITIONS), choices=CONDITIONS)
    args = parser.parse_args()
    count = args.per_side**2
    print(f"{'renderer':12s} {'condition':12s} {'found':>9s} {'rej':>4s} {'rms x':>6s} {'rms y':>6s} "
          f"{'worst':>6s} {'>30um':>5s} {'pixel mm':>9s} {'time s':>6s}   (errors in um, TRUE centres)")
    for renderer in args.renderers:
        for condition in args.only:
            cloud, truth = render(renderer, condition, args.per_side, seed=args.seed)
            pose = estimate_plate_pose(cloud[:, :3])
            start = time.perf_counter()
            measurement = measure_fiducials(cloud[:, :3], cloud[:, 3], pose, expected_count=count,
                                            marks_darker=None, allow_empty=True)
            seconds = time.perf_counter() - start
            centres = np.asarray(measurement.centres).reshape(-1, 3)
            if len(centres):
                distance, index = cKDTree(truth).query(centres)
                match = distance < MATCH_MM
                error_um = (centres[match, :2] - truth[index[match], :2]) * 1000
                found = len(np.unique(index[match]))
                rms = np.sqrt(np.mean(error_um**2, axis=0)) if len(error_um) else (np.nan, np.nan)
                worst = float(np.abs(error_um).max()) if len(error_um) else np.nan
                beyond = int(np.count_nonzero(~match) + np.count_nonzero(np.abs(error_um).max(axis=1)
                                                                         > LIMIT_MM * 1000))
            else:
                found, rms, worst, beyond = 0, (np.nan, np.nan), np.nan, 0
            print(f"{renderer:12s} {condition:12s} {found:4d}/{count:<4d} {measurement.rejected:4d} "
                  f"{rms[0]:6.2f} {rms[1]:6.2f} {worst:6.1f} {beyond:5d} "
                  f"{max(measurement.pixel_pitch_mm):9.4f} {seconds:6.2f}", flush=True)


if __name__ == "__main__":
    main()
