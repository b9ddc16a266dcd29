"""Operator tools on bad input and without a running system: clear message, exit code, no output."""
from __future__ import annotations

import io
import math
import os
from pathlib import Path
import subprocess
import sys

import pytest

from gls_calibration.cli.client import ProgressBar
from gls_calibration.cli.correct import main as correct_main, read_targets
from gls_calibration.common.files import atomic_write_text
from gls_calibration_msgs.msg import CalibrationProgress


@pytest.mark.parametrize("text, message", [
    ("x,z\n1,2\n", r"missing column\(s\) y \(header: x,z\)"),
    ("x,y\n", r"no targets"),
    ("x,y\n1,abc\n", r"non-numeric value"),
])
def test_gls_correct_rejects_bad_csv_with_exit_2(tmp_path, capsys, text, message):
    targets = tmp_path / "targets.csv"
    targets.write_text(text)
    with pytest.raises(ValueError, match=message):
        read_targets(targets)
    assert correct_main([str(targets), "--out", str(tmp_path / "out.csv")]) == 2
    assert not (tmp_path / "out.csv").exists()
    assert "targets.csv" in capsys.readouterr().err


def test_gls_calibrate_without_a_running_system_fails_cleanly():
    # A namespace nobody serves: the tool gives up after its wait and exits 1 with a message.
    tool = subprocess.run([sys.executable, "-m", "gls_calibration.cli.calibrate", "--namespace", "nobody_here",
                           "--timeout", "1"], capture_output=True, text=True, timeout=60)
    assert tool.returncode == 1
    assert tool.stderr.strip().splitlines() == ["gls-calibrate: action /nobody_here/calibrate",
                                                "action /nobody_here/calibrate is not available (waited 1 s)"]


def test_gls_calibrate_takes_ros_arguments():
    # --ros-args remaps the namespace like a node's; the tool prints the name it resolved.
    tool = subprocess.run([sys.executable, "-m", "gls_calibration.cli.calibrate", "--timeout", "1",
                           "--ros-args", "-r", "__ns:=/cell_elsewhere"], capture_output=True, text=True, timeout=60)
    assert tool.returncode == 1, tool.stderr
    assert "action /cell_elsewhere/calibrate is not available (waited 1 s)" in tool.stderr


@pytest.mark.parametrize("kind", ["device", "fifo", "directory", "symlink"])
def test_gls_correct_writes_only_regular_files(tmp_path, capsys, kind):
    targets = tmp_path / "targets.csv"
    targets.write_text("x,y\n0,0\n")
    out = {"device": Path("/dev/null"), "fifo": tmp_path / "pipe", "directory": tmp_path / "folder",
           "symlink": tmp_path / "link"}[kind]
    if kind == "fifo":
        os.mkfifo(out)
    elif kind == "directory":
        out.mkdir()
    elif kind == "symlink":
        out.symlink_to("/dev/null")
    before = os.stat(out, follow_symlinks=False)
    assert correct_main([str(targets), "--out", str(out)]) == 2      # refused before the service is asked
    assert "refused (outputs are written as regular files only)" in capsys.readouterr().err
    after = os.stat(out, follow_symlinks=False)
    assert (after.st_ino, after.st_mode) == (before.st_ino, before.st_mode)
    with pytest.raises(ValueError, match="refused"):
        atomic_write_text(out, "x")


def test_the_progress_bar_survives_nonsense_fractions():
    stream = io.StringIO()
    bar = ProgressBar(stream)
    fractions = (math.nan, math.inf, -3.0, 7.0, 0.5)
    for index, fraction in enumerate(fractions):
        bar.update(CalibrationProgress(stage=f"s{index}", fraction=fraction, text="t"))
    percents = [line.split("]")[1].split()[0] for line in stream.getvalue().splitlines()]
    assert percents == ["0%", "0%", "0%", "100%", "50%"]
