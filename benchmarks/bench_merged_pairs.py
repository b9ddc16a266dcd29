"""Two fiducials marked s apart (a doubled mark): how often the merged detection is turned down (issue 11).

A 5x5 plate at the 19x19 grid's pitch, rendered by ``test/rendering.py`` (independent of the package's
simulator, ``BASE_SCAN``: 1 % intensity noise, 1.3 deg tilt), whose middle fiducial is marked twice,
s apart in a random direction; the other 24 are single. Per separation, over random placements:
how the pair's detection ends (rejected as ``merged``, rejected for another reason, or accepted and
how far off against the TRUE centres, in units of its stated uncertainty) and how many of the 24
single fiducials were turned down (false rejections). ``measure_fiducials`` defaults.

Run: .venv/bin/python benchmarks/bench_merged_pairs.py [--placements 10] [--speckle 0.3]
"""
from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path
import sys

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
from rendering import BASE_SCAN, GRID_PITCH_MM, plate_to_scanner, render_plate_scan  # noqa: E402

from gls_calibration.fiducials import measure_fiducials  # noqa: E402
from gls_calibration.plate_pose import estimate_plate_pose  # noqa: E402

SEPARATIONS_MM = (0.0, 0.11, 0.16, 0.21, 0.32)


def one_plate(separation_mm: float, rng: np.random.Generator, speckle: float, seed: int) -> tuple[str, Counter]:
    """Outcome of the pair's detection and the reasons of the single fiducials turned down."""
    axis = (np.arange(5) - 2) * GRID_PITCH_MM
    singles = np.array([(u, v) for v in axis for u in axis if (u, v) != (0.0, 0.0)])
    singles = singles + rng.uniform(-0.05, 0.05, singles.shape)
    first = rng.uniform(-0.05, 0.05, 2)
    angle = rng.uniform(0.0, np.pi)
    marks = [first, first + separation_mm * np.array([np.cos(angle), np.sin(angle)])] if separation_mm else [first]
    truth_uv = np.vstack([singles, *marks])
    scan = dict(BASE_SCAN, seed=seed, speckle=speckle, speckle_corr_px=1.5 if speckle else 0.0)
    xyz, intensity = render_plate_scan(truth_uv, size_mm=(60.0, 60.0), **scan)
    truth = plate_to_scanner(truth_uv, BASE_SCAN["tilt_rad"], BASE_SCAN["offset_mm"])
    measurement = measure_fiducials(xyz, intensity, estimate_plate_pose(xyz), allow_empty=True)
    _, index = cKDTree(truth).query(measurement.centres) if len(measurement.centres) else (None, np.empty(0, int))
    _, rejected_index = (cKDTree(truth).query(measurement.rejected_centres)
                         if len(measurement.rejected_centres) else (None, np.empty(0, int)))
    lost = set(range(len(singles))) - set(index.tolist())
    single_reasons = Counter(next((r for r, k in zip(measurement.rejected_reasons, rejected_index) if k == single),
                                  "not detected") for single in lost)
    on_pair = index >= len(singles)
    if on_pair.any():
        error = np.abs(measurement.centres[on_pair, :2] - truth[index[on_pair], :2])
        ratio = float(np.max(error / measurement.sigma_xy_mm[on_pair]))
        outcome = f"accepted, {1000 * error.max():.0f} um = {ratio:.1f} sigma off"
        if separation_mm and ratio > 3:
            outcome = "ACCEPTED beyond 3 sigma"
        elif not separation_mm:
            outcome = "single: accepted"
    else:
        reasons = sorted({r for r, k in zip(measurement.rejected_reasons, rejected_index) if k >= len(singles)})
        outcome = "rejected: " + ("merged" if "merged" in reasons else "/".join(reasons) or "not detected")
    return outcome, single_reasons


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--placements", type=int, default=10)
    parser.add_argument("--speckle", type=float, default=0.0, help="speckle contrast (1.5 px correlation)")
    parser.add_argument("--seed", type=int, default=5)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    print(f"speckle {args.speckle}, {args.placements} placements per separation, 24 single fiducials each")
    for separation in SEPARATIONS_MM:
        outcomes, false_rejections = Counter(), Counter()
        for placement in range(args.placements):
            outcome, lost = one_plate(separation, rng, args.speckle, seed=placement)
            outcomes["accepted within 3 sigma" if outcome.startswith("accepted") else outcome] += 1
            false_rejections.update(lost)
        summary = ", ".join(f"{count} {name}" for name, count in outcomes.most_common())
        lost = ", ".join(f"{count} {name}" for name, count in false_rejections.most_common()) or "none"
        print(f"s = {separation:4.2f} mm: {summary}; single fiducials turned down "
              f"(of {24 * args.placements}): {lost}", flush=True)


if __name__ == "__main__":
    main()
