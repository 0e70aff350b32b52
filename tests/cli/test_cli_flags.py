"""The `reconstruct` flags generated from the schema (`svolsdf.cli.flags`): each maps to a config
option, its help is that option's first docstring sentence (with its choices), and passing it
sets that option."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from svolsdf.cli import app, main
from svolsdf.cli.app import _RECONSTRUCT_OPTIONS
from svolsdf.cli.flags import (
    RECONSTRUCT_FLAGS,
    first_sentence,
    flag_overrides,
    option_choices,
    with_flags,
)
from svolsdf.config import option_docs, preset


def _get(cfg, key: str):
    for part in key.split("."):
        cfg = getattr(cfg, part)
    return cfg


def _param(flag: str):
    cmd = typer.main.get_command(app).commands["reconstruct"]
    return next(p for p in cmd.params if flag in p.opts)


def _other_value(key: str, default):
    """A value of option ``key`` that is not ``default``, as typed on the command line."""
    allowed = option_choices(key)
    if allowed:
        return next(c for c in allowed if c != default)
    if isinstance(default, bool):
        return not default
    if key.endswith("weights"):
        return "w.pt"
    if key == "device":  # a GPU by number
        return "cpu" if default != "cpu" else "cuda:1"
    if isinstance(default, int):
        return str(default + 1)
    return "1.5" if default is None else str(default * 2)  # a float option


def test_every_flag_is_a_documented_option_with_its_label():
    docs = option_docs()
    assert len(set(RECONSTRUCT_FLAGS.values())) == len(RECONSTRUCT_FLAGS)
    for flag, key in RECONSTRUCT_FLAGS.items():
        assert docs.get(key), (flag, key)
        assert _RECONSTRUCT_OPTIONS[key] == flag
        p = _param(flag)
        assert p.default is None and not p.required, flag


@pytest.mark.parametrize("flag", sorted(RECONSTRUCT_FLAGS))
def test_flag_help_is_the_first_sentence_of_the_schema_doc(flag):
    key = RECONSTRUCT_FLAGS[flag]
    help_text = _param(flag).help
    from svolsdf.cli.flags import user_help

    sentence = user_help(first_sentence(option_docs()[key]))  # without references to docs/
    assert "docs/" not in help_text and "svolsdf." not in help_text
    assert help_text.startswith(sentence) and sentence.endswith(".") and "``" not in sentence
    assert all(c in help_text for c in option_choices(key))
    if help_text != sentence:  # only the choices the sentence does not name are appended
        assert help_text == f"{sentence} (one of: {', '.join(option_choices(key))})"


def test_first_sentence_skips_dots_inside_parentheses_and_numbers():
    assert first_sentence("A (docs/method.md 5.5. x) b. C d.") == "A (docs/method.md 5.5. x) b."
    assert first_sentence("Runs ``scale`` x 2.5 times") == "Runs scale x 2.5 times"


@pytest.mark.parametrize("flag", sorted(RECONSTRUCT_FLAGS))
def test_passing_a_flag_sets_its_option(flag, seen, tmp_path):
    key = RECONSTRUCT_FLAGS[flag]
    base = preset("fast")
    default = _get(base, key)
    value = _other_value(key, default)
    if isinstance(value, bool):
        arg = [flag if value else f"--no-{flag[2:]}"]
    else:
        arg = [flag, value]
    main(["reconstruct", str(tmp_path), "-o", str(tmp_path / "o"), *arg])
    got = _get(seen["cfg"], key)
    assert got != default
    assert str(got) == str(value) or got == value or got == float(value), (flag, got, value)
    # nothing else changed but the scene
    cfg = seen["cfg"]
    for section in ("mvs", "train", "field", "guide", "fusion", "mesh"):
        for f in dataclasses.fields(getattr(base, section)):
            k = f"{section}.{f.name}"
            if k != key:
                assert _get(cfg, k) == _get(base, k), (flag, k)


def test_flag_overrides_leave_unset_flags_none_and_paths_strings():
    got = flag_overrides(RECONSTRUCT_FLAGS, {"steps": 5, "weights": Path("a/w.pt")})
    assert got["train.steps"] == 5 and got["mvs.weights"] == "a/w.pt"
    assert set(got) == set(RECONSTRUCT_FLAGS.values())
    assert all(v is None for k, v in got.items() if k not in ("train.steps", "mvs.weights"))


def test_a_new_table_line_is_a_new_flag():
    toy = typer.Typer()
    got = {}

    def cmd(name: str = "x", **options) -> None:
        got.update(flag_overrides(table, options))

    table = {"--rays": "train.rays", "--mesh-watertight": "mesh.watertight"}
    toy.command()(with_flags(cmd, table))
    res = CliRunner().invoke(toy, ["--rays", "64", "--mesh-watertight"])
    assert res.exit_code == 0, res.output
    assert got == {"train.rays": 64, "mesh.watertight": True}
    res = CliRunner().invoke(toy, ["--rays", "many"])
    assert res.exit_code == 2


# --------------------------------------------------------------------------- other commands
def _dataclass_tables():
    from svolsdf.calibrate import CalibrateConfig
    from svolsdf.cli.flags import CALIBRATE_FLAGS, EVALUATE_FLAGS, MVS_FLAGS, SYNTH_FLAGS
    from svolsdf.commands.mvs import MVSJobConfig
    from svolsdf.evaluate.scoring import EvaluateConfig
    from svolsdf.scene.synthetic import SynthConfig

    return [("calibrate", CalibrateConfig, CALIBRATE_FLAGS), ("mvs", MVSJobConfig, MVS_FLAGS),
            ("synth", SynthConfig, SYNTH_FLAGS), ("evaluate", EvaluateConfig, EVALUATE_FLAGS)]


@pytest.mark.parametrize("command", ["calibrate", "mvs", "synth", "evaluate"])
def test_each_commands_flags_are_its_config_fields(command):
    """Type, default and help (the docstring's first sentence, without references to the code
    or the docs) of every flag come from the field of the command's config it sets."""
    from svolsdf.cli.flags import field_docs, user_help

    _, cls, table = next(t for t in _dataclass_tables() if t[0] == command)
    cmd = typer.main.get_command(app).commands[command]
    docs = field_docs(cls)
    defaults = {f.name: f.default for f in dataclasses.fields(cls)}
    for flag, name in table.items():
        p = next(p for p in cmd.params if flag in p.opts)
        assert p.default == defaults[name], flag
        assert p.help.startswith(user_help(first_sentence(docs[name]))), flag
        assert "docs/" not in p.help and "svolsdf." not in p.help, flag


def test_flags_of_every_config_field_reach_the_command(tmp_path, monkeypatch):
    """A derived flag sets its field of the config the command runs with."""
    import svolsdf.calibrate as calibrate_pkg

    seen = {}

    def fake(inputs, out, cfg):
        seen["cfg"] = cfg
        raise SystemExit(0)

    monkeypatch.setattr(calibrate_pkg, "calibrate", fake)
    photos = tmp_path / "photos"
    photos.mkdir()
    runner = CliRunner()
    runner.invoke(app, ["calibrate", str(photos), "-o", str(tmp_path / "s"), "--max-features",
                        "500", "--seed", "3", "--no-progress", "--matcher", "sequential"])
    cfg = seen["cfg"]
    assert (cfg.max_features, cfg.seed, cfg.progress, cfg.matcher) == (500, 3, False,
                                                                       "sequential")


def test_help_says_what_an_option_does_not_where_the_code_is():
    from svolsdf.cli.flags import user_help

    assert user_help("Laplace scale (docs/method.md 5.4), learned.") == "Laplace scale, learned."
    assert user_help("Working size (svolsdf.scene.size) WxH.") == "Working size WxH."
    assert user_help("Points (.ply or (N, 3) .npy).") == "Points (.ply or (N, 3) .npy)."
