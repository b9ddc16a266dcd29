"""Whether a change to the fiducial measurement kept its results bit for bit (issue 33 item 3).

``dump`` measures every condition of ``rendering.vision_conditions`` and both renderers' conditions of
``plate_renderers`` (30 renders of 19x19 plates) with the ``measure_fiducials`` on the path and
writes each result's arrays (centres, sigmas, coverage, radii, quality, rejections and their
reasons, counts) to ``DIR/<render>.npz``, with its process CPU time on stdout. ``compare`` reports,
per render, the arrays that differ between two such folders (``np.array_equal``, NaN equal to NaN)
and their largest difference. Run the dump once with main's tree on the path and once with the
changed one:

    PYTHONPATH=/work/main OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/fiducial_identity.py dump /tmp/before
    PYTHONPATH=. OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/fiducial_identity.py dump /tmp/after
    .venv/bin/python benchmarks/fiducial_identity.py compare /tmp/before /tmp/after
"""
from __future__ import annotations

import argparse
from pathlib import Path
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
from plate_renderers import CONDITIONS, RENDERERS, render  # noqa: E402
from rendering import render_condition, vision_conditions  # noqa: E402

from gls_calibration.fiducials.measure import measure_fiducials  # noqa: E402
from gls_calibration.scan.plate_pose import estimate_plate_pose  # noqa: E402

PER_SIDE = 19


def _renders():
    """Yield (name, xyz, intensity) for every render compared."""
    for name in vision_conditions(PER_SIDE):
        xyz, intensity, _, _ = render_condition(name, PER_SIDE)
        yield f"vision_{name}", xyz, intensity
    for renderer in RENDERERS:
        for condition in CONDITIONS:
            cloud, _ = render(renderer, condition, PER_SIDE)
            yield f"{renderer}_{condition}", cloud[:, :3], cloud[:, 3]


def _save_atomically(path: Path, arrays: dict) -> None:
    """Write ``arrays`` to ``path`` (.npz) through a temporary file in the same folder."""
    with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".npz", delete=False) as handle:
        np.savez(handle, **arrays)
    Path(handle.name).replace(path)


def dump(folder: Path) -> None:
    """Measure every render and store its result's arrays in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, xyz, intensity in _renders():
        pose = estimate_plate_pose(xyz)
        start = time.process_time()
        found = measure_fiducials(xyz, intensity, pose, expected_count=PER_SIDE**2, marks_darker=None,
                                  allow_empty=True)
        cpu_s = time.process_time() - start
        _save_atomically(folder / f"{name}.npz", dict(
            centres=found.centres, centres_plane=found.centres_plane, quality=found.quality, radii=found.radii,
            inner_radii=found.inner_radii, sigma_xy=found.sigma_xy_mm, sigma_plane=found.sigma_plane_mm,
            coverage=found.coverage, rejected_centres=found.rejected_centres,
            rejected_reasons=np.array(found.rejected_reasons, dtype=str), rejected_sigma=found.rejected_sigma_xy_mm,
            rejected_coverage=found.rejected_coverage,
            counts=np.array([found.merged, found.rejected, -1 if found.missing is None else found.missing]),
            image_shape=np.array(found.image_shape), pitch_mm=np.array(found.pixel_pitch_mm)))
        print(f"{name:40s} {len(found.centres):4d} found {found.rejected:4d} rejected  cpu {cpu_s:.3f} s", flush=True)


def compare(before: Path, after: Path) -> int:
    """Print per render the arrays that differ; return the number of renders with a difference."""
    differing = 0
    for path in sorted(before.glob("*.npz")):
        other = after / path.name
        if not other.exists():
            print(f"{path.stem:40s} missing in {after}")
            differing += 1
            continue
        old, new = np.load(path), np.load(other)
        notes = []
        for key in old.files:
            a, b = old[key], new[key]
            if a.shape != b.shape:
                notes.append(f"{key} shape {a.shape} -> {b.shape}")
            elif not np.array_equal(a, b, equal_nan=a.dtype.kind == "f"):
                notes.append(f"{key} max |diff| {np.nanmax(np.abs(a - b)):.3g}" if a.dtype.kind == "f" else f"{key}")
        differing += bool(notes)
        print(f"{path.stem:40s} {'; '.join(notes) or 'identical'}")
    print("all identical" if differing == 0 else f"{differing} render(s) differ")
    return differing


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("dump").add_argument("folder", type=Path)
    pair = commands.add_parser("compare")
    pair.add_argument("before", type=Path)
    pair.add_argument("after", type=Path)
    args = parser.parse_args()
    if args.command == "dump":
        dump(args.folder)
    else:
        sys.exit(1 if compare(args.before, args.after) else 0)


if __name__ == "__main__":
    main()
