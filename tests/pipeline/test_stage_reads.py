"""Stage keys against the stages' declarations (docs/run-folder.md, "Stage keys from the
declarations").

The keys are computed from what each stage declares (`svolsdf.pipeline.keys.stage_keys`: the
options it reads, less those that cannot act, and the keys of the stages it uses), so two things
are checked:

(a) the declarations cover what the stages are seen doing: tiny runs of every mode and mesh
    method (`stage_reads.base_configs`) record each option a stage reads and each earlier stage
    whose output it loads (`stage_reads.record_run`); every read must be declared
    (`Stage.declares`), every loaded stage among `Stage.uses` (slow: ten tiny runs);
(b) a changed option reruns exactly the stages that key it and those that use them: for every
    option of `Config` changed to each other valid value in every recorded config, the keys
    that change are those the declarations name (fast: the keys read no scene); and rerun after
    such a change, a finished tiny run runs exactly those stages (slow, on the runs of (a)).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
import shutil
from pathlib import Path
from typing import Any, get_type_hints

import pytest
from stage_reads import SECTIONS, base_configs, leaf_options, record_all

from svolsdf.config import Config, load_config, validate_config
from svolsdf.config.schema import choices
from svolsdf.errors import InputError
from svolsdf.pipeline.keys import STAGES, config_options, stage_keys
from svolsdf.pipeline.stages import PIPELINE_STAGES, SCENE_OPTIONS, Stage, stage

VIEWS = [0, 1, 2]
SCENE = "/nonexistent/tiny-scene"  # the keys read no scene

#: the options that pick the input views: they enter every key as the views they pick
VIEW_OPTIONS = ("scene.views", "scene.num_views", "scene.view_selection")

#: options read outside every stage (`Pipeline`'s construction and `Pipeline._run` before its
#: stages, which asks each stage whether it applies): {option: why}.
SETUP_READS = {
    "device": "where the stages run, not what they compute: no key holds it, so finished stages "
              "are reused on another device (`get_backbone`)",
    "train.mode": "which stages run, and the log line (the stages read it too)",
    "train.ablation": "which stages run (the stages read it too)",
    "fusion.unguided": "whether the unguided stage applies (`Stage.applies`, decided by the "
                       "runner before the stages; the fusion stage reads it too)",
    "preset": "the log line",
    "threads": "torch's thread count: how fast, not what is computed",
    "scene.path": "views.json records it (the scene is read by Run.load)",
    "scene.use_masks": "check_scene's refusal of empty masks; the stages read it themselves",
    "mvs.backbone": "the paper and released presets' log line naming the MVS backbone "
                    "(backbone_provenance); the MVS stages read it themselves",
    "mvs.weights": "ditto: the weights file's name in that line",
}

#: options no recorded config takes another valid value of: {option: why}.
NOT_VARIED = {
    "fusion.network_weights": (
        "valid only with fusion.network, whose network no recorded run can start (no "
        "weights ship with the package)"),
}


# --------------------------------------------------------------------------- (a) the reads
def undeclared(name: str, record: dict, cfg: Config) -> list[str]:
    """What the recorded run ``name`` (`stage_reads.record_run`'s ``record`` of ``cfg``) saw a
    stage read or load that the stage does not declare, one line each."""
    bad = []
    for s, opts in record["reads"].items():
        if s == "scene":
            bad += [f"{name}: the scene's loading reads {o}, neither in SCENE_OPTIONS nor a "
                    f"view option" for o in opts if o not in SCENE_OPTIONS + VIEW_OPTIONS]
        elif s == "setup":
            bad += [f"{name}: {o} is read outside every stage" for o in opts
                    if o not in SETUP_READS]
        else:
            bad += [f"{name}: stage {s} reads {o} but does not declare it" for o in opts
                    if not stage(s).declares(cfg, o)]
    for s, ups in record["consumes"].items():
        bad += [f"{name}: stage {s} loads {c} but does not declare using it" for c in ups
                if c not in stage(s).uses(cfg) or c not in stage(s).consumes]
    if record["ran"] != [s.name for s in PIPELINE_STAGES if s.applies(cfg)]:
        bad.append(f"{name}: ran {record['ran']}, which is not the stages that apply")
    return bad


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, dict]:
    """(the folder of the tiny runs, {run name: its record})."""
    folder = tmp_path_factory.mktemp("reads")
    return folder, record_all(folder)


@pytest.mark.slow
def test_the_declarations_cover_what_the_stages_are_seen_reading(recorded):
    _, table = recorded
    cfgs = base_configs(SCENE)
    assert set(table) == set(cfgs)
    bad = [line for name, record in sorted(table.items())
           for line in undeclared(name, record, cfgs[name])]
    assert not bad, "\n".join(bad)


def test_an_undeclared_read_or_use_is_found(monkeypatch):
    """A stage that reads an option it does not declare, or loads a stage it does not declare
    using, is named (on a made-up record: the check itself, without the runs)."""
    from svolsdf.pipeline.stages.guide import Guide
    from svolsdf.pipeline.stages.mesh import Mesh

    cfg = base_configs(SCENE)["svolsdf-field"]
    record = {"reads": {"guide": ["guide.mask_dilation", "scene.use_masks"],
                        "mesh": ["mesh.resolution"], "scene": ["scene.path"]},
              "consumes": {"mesh": ["field", "fusion"]},
              "ran": [s.name for s in PIPELINE_STAGES if s.applies(cfg)]}
    assert undeclared("r", record, cfg) == []
    monkeypatch.setattr(Guide, "reads", lambda self, cfg: ("scene.use_masks",))
    monkeypatch.setattr(Mesh, "uses", lambda self, cfg: ("mvs1", "field"))
    assert undeclared("r", record, cfg) == [
        "r: stage guide reads guide.mask_dilation but does not declare it",
        "r: stage mesh loads fusion but does not declare using it"]


# --------------------------------------------------------------------------- (b) the keys
def _field(option: str) -> tuple[Any, str, Any]:
    """(owner dataclass, name, type) of ``option``."""
    sec, _, name = option.rpartition(".")
    cls = next(c for c, s in SECTIONS.items() if s == sec)
    return cls, name, get_type_hints(cls)[name]


def other_values(option: str, value: Any) -> list[Any]:
    """Other values of ``option`` (``value`` now), to be checked by validate_config."""
    cls, name, tp = _field(option)
    limits = next(f for f in dataclasses.fields(cls) if f.name == name).metadata.get(
        "limits", {})
    hi = limits.get("max")
    out: list[Any] = []
    try:
        out += [c for c in choices(option) if c != value]
    except KeyError:
        pass
    if option == "device":  # a pattern, not a list: auto, cpu, cuda or cuda:N
        return [d for d in ("auto", "cpu", "cuda", "cuda:1") if d != value]
    if value is None:
        if out:
            return out
        return {"scene.views": [[0, 1, 3]], "scene.image_size": [[80, 64]], "mvs.scale": [2.0]
                }.get(option, ["/nonexistent/weights.pt"] if str in tp.__args__ else [2])
    if type(None) in getattr(tp, "__args__", ()):
        out.append(None)
    if isinstance(value, bool):
        out.append(not value)
    elif isinstance(value, int):
        out.append(value + 1 if hi is None or value + 1 <= hi else value - 1)
    elif isinstance(value, float):
        v = value * 2 if value else 0.5
        out.append(v if hi is None or v <= hi else value / 2 if value else hi)
    elif isinstance(value, list):
        out.append([x + 1 for x in value])
    elif isinstance(value, str) and not out:
        out.append(value + "-other")
    return out


def changed(cfg: Config, option: str, value: Any) -> Config:
    c = copy.deepcopy(cfg)
    sec, _, name = option.rpartition(".")
    owner = functools.reduce(getattr, sec.split("."), c) if sec else c
    setattr(owner, name, value)
    return c


def _keyed(s: Stage, cfg: Config) -> set[str]:
    return {o for o in config_options() if s.keyed(cfg, o)}


def rerun_by_declaration(cfg: Config, alt: Config, option: str) -> set[str]:
    """The stages whose keys the declarations say differ between ``cfg`` and ``alt`` (``cfg``
    with ``option`` changed): a stage that applies under one config only; one that applies
    under both and keys ``option`` (`SCENE_OPTIONS` through the scene it reads; the view
    options act through the views, here the same), keys another set of options, uses other
    stages, or uses a stage that differs."""
    out: set[str] = set()
    for s in PIPELINE_STAGES:
        if s.applies(cfg) != s.applies(alt):
            out.add(s.name)
        elif s.applies(cfg) and (
                (s.scene_inputs and option in SCENE_OPTIONS)
                or s.keyed(cfg, option) or s.keyed(alt, option)
                or _keyed(s, cfg) != _keyed(s, alt) or s.uses(cfg) != s.uses(alt)
                or any(u in out for u in s.uses(cfg))):
            out.add(s.name)
    return out


def violations(name: str) -> tuple[tuple[str, ...], frozenset[str]]:
    """([the options whose change moves other keys than the declarations say], {the options
    another value of which was checked}) in the recorded config ``name``."""
    cfg = base_configs(SCENE)[name]
    base = stage_keys(cfg, VIEWS)
    bad, checked = [], set()
    for option in leaf_options():
        for v in other_values(option, functools.reduce(getattr, option.split("."), cfg)):
            alt = changed(cfg, option, v)
            try:
                validate_config(alt)  # e.g. no fusion network outside svolsdf mode
            except InputError:
                continue
            checked.add(option)
            keys = stage_keys(alt, VIEWS)
            moved = {s for s in STAGES if keys[s] != base[s]}
            want = rerun_by_declaration(cfg, alt, option)
            if moved != want:
                bad.append(f"{name}: {option}={v!r} changes the keys of {sorted(moved)}, the "
                           f"declarations say {sorted(want)}")
    return tuple(bad), frozenset(checked)


_checked = functools.cache(violations)


@pytest.mark.parametrize("name", sorted(base_configs(SCENE)))
def test_a_changed_option_changes_the_keys_of_the_stages_that_read_it_and_their_users(name):
    bad = _checked(name)[0]
    assert not bad, "\n".join(bad)


def test_a_key_that_misses_an_option_is_found(monkeypatch):
    """Keys that leave out the value of an option the mesh declares (mesh.poisson.trim) are
    caught, with the option and the stages named."""
    import svolsdf.pipeline.keys as keys

    value = keys.option_value
    monkeypatch.setattr(keys, "option_value",
                        lambda cfg, o: None if o == "mesh.poisson.trim" else value(cfg, o))
    bad = violations("svolsdf-poisson")[0]
    assert bad == ("svolsdf-poisson: mesh.poisson.trim=10.0 changes the keys of [], the "
                   "declarations say ['mesh']",)


def test_every_option_is_changed_in_some_config():
    """Each option but `NOT_VARIED`'s takes another valid value in at least one recorded
    config (some values are refused in some modes)."""
    checked = set().union(*(_checked(name)[1] for name in base_configs(SCENE)))
    assert checked == set(leaf_options()) - set(NOT_VARIED)
    assert set(leaf_options()) == set(config_options())


def test_the_declarations_name_options_and_consumed_stages():
    """What a stage reads, ignores and uses, for every recorded config, names options of `Config`
    (or whole sections of them) and stages it consumes."""
    every = set(config_options())
    for name, cfg in base_configs(SCENE).items():
        for s in PIPELINE_STAGES:
            for o in s.reads(cfg) + s.key_ignores(cfg):
                assert o in every or o.endswith(".*") and any(
                    x.startswith(o[:-1]) for x in every), (name, s.name, o)
            assert set(s.uses(cfg)) <= set(s.consumes), (name, s.name)
            assert set(s.backbones(cfg)) <= {"mvs", "fusion"}, (name, s.name)


def test_options_that_cannot_act_stay_out_of_the_keys():
    """What a stage reads without it changing the result stays out of its key: the pictures of
    the surface as the field trains, which stage-2/3 volumes are kept, where and how fast the
    stages run; a stage that does not apply has one key whatever the config."""
    cfg = base_configs(SCENE)["svolsdf-field"]
    base = stage_keys(cfg, VIEWS)
    for option, value in (("train.snapshot_every", 7), ("mvs.save_volumes", True),
                          ("device", "cuda"), ("threads", 3), ("preset", "paper")):
        assert stage_keys(changed(cfg, option, value), VIEWS) == base, option
    mvs_only = changed(cfg, "train.mode", "mvs-only")
    assert not stage("mesh").applies(mvs_only)
    assert stage_keys(mvs_only, VIEWS)["mesh"] == stage_keys(
        changed(mvs_only, "mesh.resolution", 64), VIEWS)["mesh"]


@pytest.mark.slow
@pytest.mark.parametrize("option, value", [("mesh.resolution", 40), ("fusion.min_views", 2),
                                           ("guide.low_weight_rule", "mvs")])
def test_a_changed_option_reruns_exactly_those_stages(recorded, tmp_path, option, value):
    """A finished tiny run (the fast preset's field mesh fitted to the fused points), rerun
    with one option changed, runs the stages the declarations name and reads back the rest."""
    from svolsdf.pipeline import Pipeline

    folder, _ = recorded
    out = Path(shutil.copytree(folder / "svolsdf-field", tmp_path / "run"))
    cfg = load_config(out / "config.yaml")
    assert functools.reduce(getattr, option.split("."), cfg) != value
    alt = changed(cfg, option, value)
    want = rerun_by_declaration(cfg, alt, option)
    assert want and want != set(STAGES), want  # some stages run again, not all
    p = Pipeline(alt, out, progress=False)
    p.run()
    assert set(p.timing) - {"total"} == want
    state = json.loads((out / "stages.json").read_text())
    assert all(state[s] == p.keys[s] for s in p.timing if s != "total")
