"""The commands agree: the output is named with -o OUT wherever a command writes a new folder
(the run folder is positional only where it is an input), --views names the input views with
one default, 0 is "all cores" for every --threads, --device takes cuda:N, --preset's help lists
every preset, and importing the package changes no environment variable (the command line sets
torch's before loading it)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

import svolsdf
from svolsdf.cli import app, main
from svolsdf.config.presets import PRESETS

#: the package's source folder, for the child processes (which import this checkout's code)
_SRC = str(Path(svolsdf.__file__).resolve().parents[1])

#: the commands that write a new folder
WRITERS = ("reconstruct", "demo", "calibrate", "mvs", "synth", "benchmark")


def _command(name: str):
    return typer.main.get_command(app).commands[name]


@pytest.mark.parametrize("name", WRITERS)
def test_every_writer_names_its_output_with_o(name):
    cmd = _command(name)
    assert any("-o" in p.opts for p in cmd.params), name
    shown = [p.name for p in cmd.params if p.param_type_name == "argument" and not p.hidden]
    assert "out" not in shown, f"{name} takes its output folder as an argument"


def test_reconstruct_and_mvs_take_the_same_input_views():
    def views(name):
        return next(p for p in _command(name).params if "--views" in p.opts).help

    assert views("reconstruct") == views("mvs")


@pytest.mark.parametrize("name", ["reconstruct", "config"])
def test_preset_help_lists_every_preset(name):
    text = next(p for p in _command(name).params if "--preset" in p.opts).help
    assert all(p in text for p in PRESETS), text
    assert "docs/" not in text


def test_zero_threads_is_all_cores_everywhere():
    from svolsdf.calibrate.sfm import CalibrateConfig, num_threads
    from svolsdf.config import Config

    assert CalibrateConfig().threads == 0 == Config().threads
    assert num_threads(0) == len(os.sched_getaffinity(0)) and num_threads(3) == 3
    for name in ("reconstruct", "calibrate"):
        text = next(p for p in _command(name).params if "--threads" in p.opts).help
        assert "0 = the cores this process may run on" in text, (name, text)


def test_device_takes_a_gpu_by_number_on_every_command():
    for name in ("reconstruct", "mvs"):
        text = next(p for p in _command(name).params if "--device" in p.opts).help
        assert "cuda:N" in text, (name, text)


def test_synth_writes_to_o_and_mvs_takes_reconstructs_views(tmp_path, capsys):
    from svolsdf.cli.runs import _input_views
    from svolsdf.pipeline.views import default_views
    from svolsdf.scene.loaders import load_scene

    out = tmp_path / "s"
    main(["synth", "-o", str(out), "--size", "32x24", "--views", "5"])
    assert (out / "scene.json").is_file()
    with pytest.raises(SystemExit) as e:  # two output folders: which one?
        main(["synth", str(tmp_path / "a"), "-o", str(tmp_path / "b"), "--size", "32x24"])
    assert e.value.code == 2 and "give -o OUT only" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    want = default_views(load_scene(out, load_images=False))
    assert _input_views(out, None) == want and len(want) == 3
    assert _input_views(out, "4 0") == [4, 0]


def test_importing_the_package_sets_no_environment_variable():
    code = ("import os, svolsdf, svolsdf.config, svolsdf.pipeline\n"
            "print(os.environ.get('OMP_WAIT_POLICY'), os.environ.get('THP_MEM_ALLOC_ENABLE'))\n"
            "import svolsdf.cli\n"
            "print(os.environ.get('OMP_WAIT_POLICY'), os.environ.get('THP_MEM_ALLOC_ENABLE'))\n")
    env = {**{k: v for k, v in os.environ.items()
              if k not in ("OMP_WAIT_POLICY", "THP_MEM_ALLOC_ENABLE")}, "PYTHONPATH": _SRC}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       timeout=300, check=True)
    assert r.stdout.split("\n")[:2] == ["None None", "PASSIVE 1"]


def test_the_command_line_sets_them_before_torch_loads():
    code = ("import sys\nimport svolsdf.cli.flags\n")  # (svolsdf.cli runs first)
    env = {**{k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}, "PYTHONPATH": _SRC}
    r = subprocess.run([sys.executable, "-X", "importtime", "-c", code], capture_output=True,
                       text=True, env=env, timeout=300, check=True)
    lines = r.stderr.splitlines()
    first_torch = next(i for i, ln in enumerate(lines) if re.search(r"\|\s+torch$", ln))
    runtime = next(i for i, ln in enumerate(lines) if re.search(r"\|\s+svolsdf.runtime$", ln))
    assert runtime < first_torch


def test_help_runs(capsys):
    r = CliRunner().invoke(app, ["synth", "--help"])
    assert r.exit_code == 0 and "-o" in r.output


def test_no_help_cites_the_docs_or_the_code():
    """A help text says what the option does for the user, not where the method or the code
    is (no docs/ page, method.md section or module name)."""
    bad = [(name, p.opts, p.help) for name, cmd in typer.main.get_command(app).commands.items()
           for p in cmd.params if re.search(r"docs/|method\.md|svolsdf\.[a-z_]+\.",
                                            getattr(p, "help", None) or "")]
    assert not bad, bad
