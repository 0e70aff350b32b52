"""`svolsdf.config`: presets, YAML round trips and the validation of every field (types,
enumerations, ranges) when a config is built, including a property-based test of loading."""

from __future__ import annotations

import dataclasses
import math
import re
import types
from dataclasses import asdict
from pathlib import Path
from typing import Literal, Union, get_args, get_origin, get_type_hints

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from svolsdf.config import (
    PRESETS,
    Config,
    apply_overrides,
    choices,
    config_from_dict,
    load_config,
    preset,
    save_config,
    validate_config,
)
from svolsdf.errors import InputError


def _leaves(cls=Config, prefix=""):
    """(dotted key, annotation, limits) of every non-dataclass field, recursively."""
    hints = get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            yield from _leaves(tp, prefix + f.name + ".")
        else:
            yield prefix + f.name, tp, f.metadata.get("limits", {})


LEAVES = list(_leaves())


def _nest(flat: dict) -> dict:
    out: dict = {}
    for key, v in flat.items():
        *parents, last = key.split(".")
        d = out
        for p in parents:
            d = d.setdefault(p, {})
        d[last] = v
    return out


def _get(cfg, key):
    for p in key.split("."):
        cfg = getattr(cfg, p)
    return cfg


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_pass_validation_unchanged(name):
    cfg = preset(name)
    before = asdict(cfg)
    validate_config(cfg)
    assert asdict(cfg) == before
    # and survive a YAML round trip exactly
    assert asdict(config_from_dict(yaml.safe_load(yaml.safe_dump(before)))) == before


def test_enumerations_are_literals():
    # every str option with a fixed set of values is a Literal; the pluggable kinds (backbones,
    # field kinds, samplers, mesh methods) are checked against their registries instead
    kinds = {key: tp for key, tp, _ in LEAVES}
    for key in ("preset", "mvs.width", "field.init", "train.mode",
                "train.gce_form", "train.sparse_norm", "mesh.format",
                "guide.low_weight_rule"):
        assert get_origin(kinds[key]) is Literal, key
    for key in ("mvs.backbone", "field.kind", "train.sampler", "mesh.method"):
        assert kinds[key] is str and choices(key), key
    assert "ce" in get_args(next(a for a in get_args(kinds["train.ablation"])
                                 if get_origin(a) is Literal))


@pytest.mark.parametrize("text, key, value", [
    ("train: {steps: fifty}", "train.steps", "'fifty'"),
    ("train: {lr: abc}", "train.lr", "'abc'"),
    ("scene: {image_size: 160x120}", "scene.image_size", "'160x120'"),
    ("scene: {image_size: [160]}", "scene.image_size", "[160]"),
    ("scene: {views: '0 1 2'}", "scene.views", "'0 1 2'"),
    ("scene: {views: [0, 1, 1]}", "scene.views", "1 is repeated"),
    ("scene: {views: [3]}", "scene.views", "[3]"),
    ("scene: {use_masks: 'no'}", "scene.use_masks", "'no'"),
    ("scene: {use_masks: 1}", "scene.use_masks", "1"),
    ("train: {rays: -4}", "train.rays", "-4"),
    ("train: {steps: -5}", "train.steps", "-5"),
    ("threads: -2", "threads", "-2"),
    ("train: {mode: fast}", "train.mode", "'fast'"),
    ("train: {ablation: none}", "train.ablation", "'none'"),
    ("mvs: {backbone: colmap}", "mvs.backbone", "'colmap'"),
    ("mvs: {ndepths: [192, 32]}", "mvs.ndepths", "[192, 32]"),
    ("mvs: {scale: 0}", "mvs.scale", "0"),
    ("train: {object_ray_fraction: 1.5}", "train.object_ray_fraction", "1.5"),
    ("train: {gce_q: .nan}", "train.gce_q", "nan"),
    ("device: gpu", "device", "'gpu'"),
    ("scene: {path: 3}", "scene.path", "3"),
    ("scene: {lighting: 7}", "scene.lighting", "7"),
    ("mvs: {finer_stage_optimization: true}\ntrain: {mode: volsdf}",
     "mvs.finer_stage_optimization", "train.mode"),
])
def test_bad_values_name_the_key_the_value_and_what_is_allowed(tmp_path, text, key, value):
    p = tmp_path / "c.yaml"
    p.write_text(text + "\n")
    with pytest.raises(InputError) as e:
        load_config(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}: ") and key in msg and value in msg, msg
    assert "expected" in msg or "needs" in msg, msg


def test_values_are_normalized():
    cfg = config_from_dict({"train": {"lr": 1, "beta_end": "1e-3"},  # PyYAML: '1e-3' is a str
                            "scene": {"views": (2, 0, 1), "lighting": "max"},
                            "mvs": {"weights": Path("w.pt")}})
    assert cfg.train.lr == 1.0 and isinstance(cfg.train.lr, float)
    assert cfg.train.beta_end == 1e-3 and cfg.scene.views == [2, 0, 1]
    assert cfg.scene.lighting == "max" and cfg.mvs.weights == "w.pt"
    import numpy as np  # numbers from code: numpy scalars become Python numbers

    cfg.train.steps, cfg.scene.image_size = np.int64(5), [np.int32(64), np.int64(48)]
    validate_config(cfg)
    assert type(cfg.train.steps) is int and [type(x) for x in cfg.scene.image_size] == [int, int]


def test_overrides_are_validated_and_name_their_option():
    cfg = preset("fast")
    with pytest.raises(InputError, match=r"^--steps \(train\.steps\) = -5: expected an integer"):
        apply_overrides(cfg, {"train.steps": -5}, labels={"train.steps": "--steps"})
    with pytest.raises(InputError, match="unknown option 'train.nope'"):
        apply_overrides(preset("fast"), {"train.nope": 1})
    with pytest.raises(InputError, match="unknown option 'nope.steps'"):
        apply_overrides(preset("fast"), {"nope.steps": 1})
    # a field set in code is checked too, when the pipeline is built (before any stage)
    from svolsdf.pipeline import Pipeline

    cfg = preset("fast")
    cfg.scene.path = "somewhere"
    cfg.train.rays = 0
    with pytest.raises(InputError, match="train.rays = 0"):
        Pipeline(cfg, "never-created")
    assert not Path("never-created").exists()


# issue 38: pairs of options where one silently disabled or contradicted the other
@pytest.mark.parametrize("name, given, a, b", [
    ("fast", {"train.mode": "volsdf", "train.ablation": "mse"}, "train.mode", "train.ablation"),
    ("fast", {"train.mode": "mvs-only", "train.ablation": "ce"}, "train.mode", "train.ablation"),
    ("fast", {"train.mode": "volsdf", "guide.low_weight_rule": "mvs"}, "train.mode",
     "guide.low_weight_rule"),
    ("fast", {"train.mode": "volsdf", "fusion.network": "patchmatchnet"}, "train.mode",
     "fusion.network"),
    ("fast", {"fusion.network_weights": "w.pt"}, "fusion.network_weights",
     "fusion.network"),
    ("fast", {"field.grid_start_resolution": 256}, "field.grid_start_resolution",
     "field.grid_resolution"),
    ("fast", {"train.mode": "volsdf", "field.sphere_start_resolution": 64,
              "field.grid_resolution": 32}, "field.sphere_start_resolution",
     "field.grid_resolution"),
    ("fast", {"train.beta_start": 1e-3, "train.beta_end": 1e-2}, "train.beta_start",
     "train.beta_end"),
    ("fast", {"mesh.watertight": True}, "mesh.watertight", "mesh.method"),
    ("paper", {"train.mode": "mvs-only"}, "train.mode", "mesh.method"),
    ("fast", {"field.kind": "mlp"}, "field.kind", "field.init"),
    ("paper", {"field.init": "mvs"}, "field.kind", "field.init"),
    ("paper", {"field.mlp_depth": 2}, "field.kind", "field.mlp_depth"),
    ("paper", {"field.mlp_width": 32}, "field.kind", "field.mlp_width"),
    ("fast", {"mvs.finer_stage_optimization": True, "train.ablation": "mse"},
     "mvs.finer_stage_optimization", "train.ablation"),
])
def test_contradicting_options_are_refused_naming_both(name, given, a, b):
    cfg = preset(name)
    for key, value in given.items():  # set in code: the pipeline's own check refuses them
        obj, *path, last = [cfg, *key.split(".")]
        for part in path:
            obj = getattr(obj, part)
        setattr(obj, last, value)
    with pytest.raises(InputError) as e:
        validate_config(cfg)
    msg = str(e.value)
    assert a in msg and b in msg and len(msg.splitlines()) == 1, msg


def test_mvs_only_with_the_field_mesh_is_told_that_no_method_makes_a_mesh():
    """Issue 50: mvs-only runs no mesh stage (no field; `test_cli.py` checks that its run makes
    no mesh.ply with mesh.method poisson), so the refusal must not send the user to
    mesh.method=poisson for a mesh."""
    cfg = preset("paper")
    cfg.train.mode = "mvs-only"
    with pytest.raises(InputError) as e:
        validate_config(cfg)
    msg = str(e.value)
    assert "makes no mesh of any method, only points.ply" in msg, msg
    assert "for a mesh use train.mode svolsdf" in msg, msg
    assert "use mesh.method=poisson" not in msg, msg
    # the way out it names for the points alone is accepted
    apply_overrides(cfg, {"mesh.method": "poisson"})


def test_draft_with_casmvsnet_runs_casmvsnet_at_its_own_size():
    """Issue 50: the draft preset's mvs.scale 1.5 is the plane sweep's; --backbone casmvsnet
    (which runs at 1 or 2 only) takes its own size instead of failing on a scale the user never
    set, and the plane sweep gets 1.5 back."""
    from svolsdf.config.presets import MVS_SCALE_BY_BACKBONE
    from svolsdf.mvs.backbone import backbone_options

    labels = {"mvs.backbone": "--backbone"}
    cfg = apply_overrides(preset("draft"), {"mvs.backbone": "casmvsnet"}, labels=labels)
    assert cfg.mvs.scale is None and "x2_mvsres" not in backbone_options("casmvsnet", cfg.mvs)
    assert apply_overrides(cfg, {"mvs.backbone": "planesweep"}).mvs.scale == 1.5
    assert MVS_SCALE_BY_BACKBONE["draft"] == {"planesweep": 1.5}
    # a scale the user gives stays theirs: accepted where it runs, refused where not
    cfg = apply_overrides(preset("draft"), {"mvs.backbone": "casmvsnet", "mvs.scale": 1.0})
    assert backbone_options("casmvsnet", cfg.mvs)["x2_mvsres"] is False
    cfg = apply_overrides(preset("draft"), {"mvs.backbone": "casmvsnet", "mvs.scale": 1.5})
    assert backbone_options("casmvsnet", cfg.mvs)["scale"] == 1.5  # CasMVSNet runs at any scale
    with pytest.raises(InputError, match=r"^--set mvs\.scale=1\.5 with --backbone patchmatchnet "
                                         r"\(mvs\.backbone\): the patchmatchnet backbone runs "):
        apply_overrides(preset("draft"), {"mvs.backbone": "patchmatchnet", "mvs.scale": 1.5},
                        labels={**labels, "mvs.scale": "--set mvs.scale"})
    # the other presets have no per-backbone scale: nothing changes
    assert apply_overrides(preset("fast"), {"mvs.backbone": "casmvsnet"}).mvs.scale is None


@pytest.mark.parametrize("backbone, why", [
    ("patchmatchnet", "the patchmatchnet backbone runs at the working size only"),
])
def test_a_scale_the_backbone_cannot_run_at_is_refused_by_validation(backbone, why):
    """Set in code (no override to follow), the draft's 1.5 with another backbone is refused
    when the config is validated, before any work, naming both options, the cause and that the
    value is the preset's."""
    cfg = preset("draft")
    cfg.mvs.backbone = backbone
    with pytest.raises(InputError) as e:
        validate_config(cfg)
    msg = str(e.value)
    assert msg.startswith(f"mvs.scale = 1.5 with mvs.backbone = {backbone}: {why}"), msg
    assert "(1.5 is the draft preset's scale for planesweep)" in msg, msg
    assert "--set mvs.scale=null" in msg and len(msg.splitlines()) == 1, msg


def test_cli_draft_with_casmvsnet(seen, tmp_path, capsys):
    """`reconstruct --preset draft --backbone casmvsnet` reaches the pipeline with CasMVSNet at
    its own size; `--backbone patchmatchnet --set mvs.scale=1.5` exits 2 in one line before any
    folder is made."""
    from svolsdf.cli import main

    out = tmp_path / "out"
    main(["reconstruct", str(tmp_path), "-o", str(out), "--preset", "draft",
          "--backbone", "casmvsnet"])
    cfg = seen["cfg"]
    assert (cfg.preset, cfg.mvs.backbone, cfg.mvs.scale, cfg.train.steps) == (
        "draft", "casmvsnet", None, 500)
    with pytest.raises(SystemExit) as e:
        main(["reconstruct", str(tmp_path), "-o", str(out), "--preset", "draft",
              "--backbone", "patchmatchnet", "--set", "mvs.scale=1.5"])
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and len(err.splitlines()) == 1, err
    assert "mvs.scale=1.5" in err and "patchmatchnet" in err, err
    assert not out.exists()


def test_contradictions_name_the_command_line_options():
    with pytest.raises(InputError, match=r"^--mode volsdf \(train\.mode\) with --ablation mse "
                                         r"\(train\.ablation\): .*never see MVS"):
        apply_overrides(preset("fast"), {"train.mode": "volsdf", "train.ablation": "mse"},
                        labels={"train.mode": "--mode", "train.ablation": "--ablation"})
    cfg = apply_overrides(preset("fast"), {"train.mode": "volsdf"})
    with pytest.raises(InputError, match="--set guide.low_weight_rule=mvs"):
        apply_overrides(cfg, {"guide.low_weight_rule": "mvs"},
                        labels={"guide.low_weight_rule": "--set guide.low_weight_rule"})


def test_cli_refuses_a_baseline_that_would_see_mvs(tmp_path, capsys):
    """`--mode volsdf --ablation mse`: exit 2, one line naming both options; nothing written."""
    from svolsdf.cli import main

    out = tmp_path / "out"
    for extra in (["--ablation", "mse"], ["--set", "guide.low_weight_rule=mvs"]):
        with pytest.raises(SystemExit) as e:
            main(["reconstruct", str(tmp_path), "-o", str(out), "--mode", "volsdf", *extra])
        err = capsys.readouterr().err.strip()
        assert e.value.code == 2 and len(err.splitlines()) == 1, err
        # --set is applied after the other options, so the mode is named by its key there
        assert ("--mode volsdf" in err or "train.mode = volsdf" in err) and \
            extra[1].split("=")[0] in err, err
    assert not out.exists()


@pytest.mark.parametrize("name, given", [
    ("fast", {}), ("paper", {}),
    ("fast", {"train.mode": "volsdf", "field.kind": "mlp"}),  # the MLP baseline
    ("fast", {"field.kind": "mlp", "field.init": "sphere"}),
    ("fast", {"mesh.watertight": True, "mesh.method": "field"}),
    ("fast", {"train.beta_start": 0.0025, "train.beta_end": 0.0025}),  # a constant beta
    ("fast", {"train.beta_start": 0.0, "train.beta_end": 0.01}),  # learned: no anneal
    ("fast", {"train.mode": "mvs-only"}),
    ("fast", {"train.mode": "volsdf", "field.grid_start_resolution": 256}),  # the sphere's start
    ("paper", {"train.mode": "volsdf"}),
])
def test_options_that_agree_are_accepted(name, given):
    apply_overrides(preset(name), given)


def test_unreadable_config_file(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_bytes(b"\xff\xfe\x00bad")
    with pytest.raises(InputError, match="c.yaml"):
        load_config(p)


# --------------------------------------------------------------------------- property-based
def _is_allowed(value, tp, lim) -> bool:
    """An independent oracle: does ``value`` (as YAML gives it) fit ``tp`` and its limits?"""
    origin, args = get_origin(tp), get_args(tp)
    if origin is Union or origin is types.UnionType:
        return (value is None and type(None) in args) or any(
            _is_allowed(value, a, lim) for a in args if a is not type(None))
    if origin is Literal:
        return isinstance(value, str) and value in args
    if tp is bool:
        return isinstance(value, bool)
    if tp in (int, float):
        if isinstance(value, bool):
            return False
        if tp is float and isinstance(value, str):
            try:
                value = float(value)
            except ValueError:
                return False
        if not isinstance(value, (float, int) if tp is float else int):
            return False
        if not math.isfinite(value):
            return False
        return (lim.get("min") is None or value >= lim["min"]) and (
            lim.get("max") is None or value <= lim["max"]) and (
            lim.get("gt") is None or value > lim["gt"])
    if tp is str:
        if "choices" in lim:
            return value in lim["choices"]()
        if "pattern" in lim:  # (device: auto, cpu, cuda or cuda:N)
            return isinstance(value, str) and re.fullmatch(lim["pattern"], value) is not None
        return isinstance(value, str)
    if origin is list:
        if not isinstance(value, list):
            return False
        if "len" in lim and len(value) != lim["len"]:
            return False
        if "min_len" in lim and len(value) < lim["min_len"]:
            return False
        if lim.get("unique") and len(set(map(repr, value))) != len(value):
            return False
        item = {k: v for k, v in lim.items() if k in ("min", "max", "gt")}
        return all(_is_allowed(v, args[0], item) for v in value)
    raise AssertionError(f"no oracle for {tp}")


_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-10, 1000), st.floats(allow_nan=True),
    st.sampled_from(["", "no", "yes", "fifty", "1e-3", "160x120", "0 1 2", "max", "mvs", "grid",
                     "svolsdf", "mse", "ply", "cuda", "planesweep", "paper", "released"]),
)
_values = st.one_of(_scalars, st.lists(st.integers(-3, 300), max_size=4),
                    st.lists(_scalars, max_size=3), st.dictionaries(st.text(max_size=3), _scalars,
                                                                    max_size=2))


def _valid(tp, lim) -> st.SearchStrategy:
    """Values that fit ``tp`` and its limits (so that loading also succeeds, not only fails)."""
    origin, args = get_origin(tp), get_args(tp)
    if origin is Union or origin is types.UnionType:
        return st.one_of(*[st.none() if a is type(None) else _valid(a, lim) for a in args])
    if origin is Literal:
        return st.sampled_from(args)
    if tp is bool:
        return st.booleans()
    lo = lim.get("min", lim.get("gt"))
    if tp is int:
        lo = 0 if lo is None else lo
        return st.integers(lo, lim.get("max", lo + 1000))
    if tp is float:
        return st.floats(lo if lo is not None else -1e6, lim.get("max", 1e6),
                         exclude_min=lim.get("gt") is not None, allow_nan=False)
    if tp is str:
        return st.sampled_from(lim["choices"]()) if "choices" in lim else st.text(max_size=8)
    if origin is list:
        n = lim.get("len")
        item = {k: v for k, v in lim.items() if k in ("min", "max", "gt")}
        return st.lists(_valid(args[0], item), min_size=n or lim.get("min_len", 0),
                        max_size=n or 4, unique=bool(lim.get("unique")))
    raise AssertionError(f"no strategy for {tp}")


@st.composite
def _mappings(draw) -> dict:
    """{dotted key: value} for up to four keys, each value valid or not, about half and half."""
    keys = draw(st.lists(st.sampled_from(LEAVES), max_size=4, unique_by=lambda leaf: leaf[0]))
    return {k: draw(st.one_of(_valid(tp, lim), _values)) for k, tp, lim in keys}


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_mappings(), st.sampled_from(sorted(PRESETS)))
def test_loading_any_mapping_gives_a_valid_config_or_a_named_error(flat, name):
    data = {"preset": name, **_nest(flat)}
    ok = all(_is_allowed(v, tp, lim) for key, tp, lim in LEAVES if key in flat
             for v in [flat[key]])
    try:
        cfg = config_from_dict(data, where="t.yaml")
    except InputError as e:
        msg = str(e)
        assert msg.startswith("t.yaml: ") and "Traceback" not in msg
        bad = [k for k, tp, lim in LEAVES if k in flat and not _is_allowed(flat[k], tp, lim)]
        cross = " with " in msg and "expected" not in msg  # two options that contradict
        assert cross or any(f"{k} = " in msg for k in bad), (msg, bad)
        assert cross or not ok, msg
        return
    assert ok, f"accepted a value the oracle rejects: {flat}"
    for key, value in flat.items():  # each given value is kept (normalized)
        got = _get(cfg, key)
        assert got == value or (isinstance(got, float) and got == float(value)), (key, value)
    # a loaded config is valid as it is and survives the YAML round trip exactly
    before = asdict(cfg)
    validate_config(cfg)
    assert asdict(cfg) == before
    again = config_from_dict(yaml.safe_load(yaml.safe_dump(before)))
    assert asdict(again) == before


@settings(max_examples=150, deadline=None)
@given(st.text(max_size=60))
def test_any_yaml_text_loads_or_fails_with_the_file_name(tmp_path_factory, text):
    p = tmp_path_factory.mktemp("y") / "c.yaml"
    p.write_text(text)
    try:
        cfg = load_config(p)
    except InputError as e:
        assert str(e).startswith(str(p))
        return
    assert asdict(validate_config(cfg)) == asdict(cfg)


def test_saved_config_loads_back(tmp_path):
    cfg = config_from_dict({"train": {"steps": 7, "mode": "volsdf"},
                            "scene": {"views": [1, 0]}})
    save_config(cfg, tmp_path / "c.yaml")
    assert asdict(load_config(tmp_path / "c.yaml")) == asdict(cfg)


def test_draft_is_fast_with_half_the_steps_and_a_smaller_sweep():
    fast, draft = asdict(preset("fast")), asdict(preset("draft"))
    assert draft.pop("preset") == "draft" and fast.pop("preset") == "fast"
    assert draft["train"].pop("steps") == fast["train"].pop("steps") // 2
    assert (draft["mvs"].pop("scale"), fast["mvs"].pop("scale")) == (1.5, None)
    assert draft == fast


# --------------------------------------------------------------------------- old names
def test_every_old_name_maps_to_an_option_and_every_option_has_one_name():
    from svolsdf.config.io import RENAMED

    leaves = {k for k, _, _ in LEAVES}
    assert set(RENAMED.values()) <= leaves
    assert len(set(RENAMED.values())) == len(RENAMED)
    assert not any(k.startswith("output.") for k in leaves)


def test_an_old_config_file_loads_with_one_deprecation_line(tmp_path, caplog):
    p = tmp_path / "old.yaml"
    p.write_text("output:\n  mesh_method: tsdf\n  poisson_depth: 8\n  fusion_views: 2\n"
                 "  use_masks: false\n  finer_stage_optimization: true\n"
                 "mesh:\n  resolution: 128\n")
    with caplog.at_level("WARNING", logger="svolsdf.config"):
        cfg = load_config(p)
    assert (cfg.mesh.method, cfg.mesh.poisson.depth, cfg.fusion.min_views) == ("tsdf", 8, 2)
    assert cfg.scene.use_masks is False and cfg.mvs.finer_stage_optimization is True
    assert cfg.mesh.resolution == 128
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "old.yaml" in lines[0] and "output.mesh_method -> mesh.method" \
        in lines[0] and "deprecated" in lines[0]


def test_an_option_under_both_names_is_refused(tmp_path):
    p = tmp_path / "both.yaml"
    p.write_text("output:\n  mesh_method: tsdf\nmesh:\n  method: poisson\n")
    with pytest.raises(InputError, match=r"both.yaml: option mesh.method given twice.*"
                                         r"output.mesh_method"):
        load_config(p)


def test_an_unknown_old_key_is_named_as_such(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("output:\n  mesh_colour: red\n")
    with pytest.raises(InputError, match="bad.yaml: unknown key 'output.mesh_colour' .*now in "
                                         "the sections guide, fusion and mesh"):
        load_config(p)
    with pytest.raises(InputError, match="unknown option 'output.mesh_colour'.*now in the "
                                         "sections guide, fusion and mesh"):
        apply_overrides(preset("fast"), {"output.mesh_colour": "red"})


def test_an_empty_old_section_is_dropped_and_a_bad_one_named(tmp_path):
    for text in ("output: {}\n", "output:\n"):
        p = tmp_path / "empty.yaml"
        p.write_text(text)
        assert load_config(p) == preset("fast")
    p = tmp_path / "bad.yaml"
    p.write_text("output: 5\n")
    with pytest.raises(InputError, match="bad.yaml: unknown key 'output'"):
        load_config(p)


def test_old_names_on_the_command_line_set_the_new_options(caplog):
    with caplog.at_level("WARNING", logger="svolsdf.config"):
        cfg = apply_overrides(preset("fast"), {"output.poisson_trim": 3.0,
                                               "output.low_weight_rule": "mvs"})
    assert cfg.mesh.poisson.trim == 3.0 and cfg.guide.low_weight_rule == "mvs"
    assert "output.poisson_trim -> mesh.poisson.trim" in caplog.text


def test_the_old_layout_holds_every_option_once():
    from svolsdf.config.io import legacy_layout

    for name in PRESETS:
        cfg = preset(name)
        old = legacy_layout(cfg)
        assert set(old) == {"preset", "device", "threads", "scene", "mvs", "field", "train",
                            "output"}
        assert config_from_dict(old) == cfg


@pytest.mark.parametrize("device", ["auto", "cpu", "cuda", "cuda:0", "cuda:3"])
def test_device_takes_a_gpu_by_number(device):
    cfg = preset("fast")
    cfg.device = device
    assert validate_config(cfg).device == device


@pytest.mark.parametrize("device", ["gpu", "cuda:", "cuda:x", "cuda1", "cpu:0"])
def test_a_device_of_no_such_form_is_refused_saying_the_forms(device):
    cfg = preset("fast")
    cfg.device = device
    with pytest.raises(InputError, match=r"device = .*: expected auto, cpu, cuda or cuda:N$"):
        validate_config(cfg)


def test_resolve_device_checks_the_gpu_number(monkeypatch):
    import torch

    from svolsdf.pipeline.machine import resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("cuda:1") == torch.device("cuda:1")
    with pytest.raises(InputError, match=r"--device cuda:2: there are 2 CUDA devices "
                                         r"\(cuda:0 \.\. cuda:1\)"):
        resolve_device("cuda:2")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(InputError, match="--device cuda:0: no CUDA device is available"):
        resolve_device("cuda:0")
