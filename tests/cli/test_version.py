"""``svolsdf --version``: the package's version, the one pyproject.toml gives."""

from __future__ import annotations

import re
from pathlib import Path

from svolsdf.cli import main

REPO = Path(__file__).resolve().parents[2]


def test_version_prints_the_project_version(capsys):
    text = (REPO / "pyproject.toml").read_text()
    version = re.search(r'^version = "([^"]+)"', text, re.M).group(1)
    main(["--version"])  # returns: exit status 0
    assert capsys.readouterr().out.strip() == f"svolsdf {version}"
