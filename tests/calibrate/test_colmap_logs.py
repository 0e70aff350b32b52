"""COLMAP's own log (glog, through pycolmap) goes to files in the scene's colmap_logs/, not to
the terminal: no "COULD NOT CREATE LOGFILE", no warning lines among the progress bars."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "src"

CODE = """
import pycolmap
from pathlib import Path
from svolsdf.calibrate.sfm import _colmap_log_files
pycolmap.logging.minloglevel = 1
_colmap_log_files(pycolmap, Path({folder!r}))
pycolmap.logging.warning("a warning of the run")
pycolmap.logging.error("an error of the run")
_colmap_log_files(pycolmap, None)
"""


def test_colmap_log_goes_to_files_not_the_terminal(tmp_path):
    pytest.importorskip("pycolmap")
    folder = tmp_path / "colmap_logs"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH",
                                                                                "")])}
    res = subprocess.run([sys.executable, "-c", CODE.format(folder=str(folder))], env=env,
                         capture_output=True, text=True, check=True)
    assert "LOGFILE" not in res.stderr and "log file" not in res.stderr, res.stderr
    assert "a warning of the run" not in res.stderr, res.stderr
    text = "".join(p.read_text() for p in folder.iterdir())
    assert "a warning of the run" in text and "an error of the run" in text
