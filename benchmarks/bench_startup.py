"""Start-up of every executable: CPU and resident memory of importing its module in a fresh process.

In a real cell each node is a process of its own (``ros2 run``), so each pays its imports; in
``gls-sim-cell`` they are paid once, in the main thread, and are not part of ``compute_cpu_s``.
Printed per console script: the median over ``--repeats`` fresh interpreters of the import's CPU time
(user + system, all threads) and the process's peak RSS after it, and whether OpenCV, Open3D or
matplotlib were loaded. The last row is Open3D alone, the cost a process pays at its first plane fit.

Run: .venv/bin/python benchmarks/bench_startup.py [--repeats 3]
"""
from __future__ import annotations

import argparse
from importlib.metadata import entry_points
import json
import statistics
import subprocess
import sys

PROBE = """
import importlib, json, resource, sys, time
start = time.process_time()
importlib.import_module(sys.argv[1])
cpu_s = time.process_time() - start
print(json.dumps(dict(cpu_s=cpu_s, rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      loaded=[name for name in ("cv2", "open3d", "matplotlib") if name in sys.modules])))
"""


def probe(module: str, repeats: int) -> dict:
    """Median CPU (s) and peak RSS (MB) of importing ``module`` in ``repeats`` fresh interpreters."""
    runs = [json.loads(subprocess.run([sys.executable, "-c", PROBE, module], capture_output=True, text=True,
                                      check=True).stdout) for _ in range(repeats)]
    return dict(cpu_s=statistics.median(run["cpu_s"] for run in runs),
                rss_mb=statistics.median(run["rss_mb"] for run in runs), loaded=runs[0]["loaded"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    scripts = sorted((point.name, point.module) for point in entry_points(group="console_scripts")
                     if point.module.startswith("gls_calibration."))
    if not scripts:
        sys.exit("no gls_calibration console scripts installed (run make setup)")
    print(f"{'executable':26s} {'cpu s':>6s} {'rss MB':>7s}  loaded")
    for name, module in scripts + [("(open3d alone)", "open3d")]:
        figures = probe(module, args.repeats)
        print(f"{name:26s} {figures['cpu_s']:6.2f} {figures['rss_mb']:7.0f}  {' '.join(figures['loaded'])}")


if __name__ == "__main__":
    main()
