"""Stage keys against the options each stage reads (issue 40: "forget one and a stale mesh is
reused without a word").

stage_reads.json records, for tiny runs of each mode and mesh method, which config options each
stage read (tests/pipeline/stage_reads.py says how). For every leaf option of `Config` changed
to each other valid value, the fast tests assert, stage by stage:

(a) when the stage, or a stage whose output it consumes, read the option, its key changes
    (reads that cannot alter a result are set aside first: `INERT_READS` says which and why);
(b) when none of them read it, its key does not change (unless `EXTRA_IN_KEY` says why the key
    holds it anyway; mostly whole config sections hashed into a key, which stay for the keys of
    existing run folders).

Only stages that run under both configs count: a stage that does not run has no result to
reuse. The slow test reruns the recording and compares it with stage_reads.json, so the table
follows the code.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from collections.abc import Callable
from typing import Any, get_type_hints

import pytest
from stage_reads import SECTIONS, base_configs, leaf_options, load_table, record_all

from svolsdf.config import Config, validate_config
from svolsdf.config.schema import choices
from svolsdf.errors import InputError
from svolsdf.pipeline import options as opt
from svolsdf.pipeline.keys import STAGES, stage_keys

VIEWS = [0, 1, 2]
SCENE = "/nonexistent/tiny-scene"  # the keys read no scene

# --------------------------------------------------------------------------- the data flow
def runs(stage: str, cfg: Config) -> bool:
    """``stage`` computes something in a run of ``cfg`` (`Pipeline._run` and the stages'
    early returns)."""
    return {"mvs1": opt.runs_mvs1, "field": opt.has_field, "guide": opt.has_guide,
            "mvs23": lambda c: True, "unguided": opt.wants_unguided, "fusion": lambda c: True,
            "mesh": opt.has_field}[stage](cfg)


def upstream(stage: str, record: dict) -> set[str]:
    """``stage``, the stages whose outputs it consumed in the recorded run, directly or through
    others, and the scene every stage reads."""
    seen, todo = {"scene"}, [stage]
    while todo:
        s = todo.pop()
        if s not in seen:
            seen.add(s)
            todo += record["consumes"].get(s, [])
    return seen


# --------------------------------------------------------------------------- the exceptions
Rule = tuple[str, Callable[[Config], bool]]


def always(cfg: Config) -> bool:
    return True


#: (a) reads that cannot alter the reading stage's result, set aside before the check:
#: {"option" (by any stage) or "stage:option": (why, when it holds: for the recorded config and
#: the changed one)}.
INERT_READS: dict[str, Rule] = {
    "scene.view_selection": (
        "enters through the views it picks (stage_keys' views argument), not by name",
        always),
    "train.grid_eikonal_weight": (
        "the field started from the MVS surface reads it but the term applies only to a grid "
        "started from a sphere (Trainer: not mvs_initialised); keys.py leaves it out then",
        lambda c: not opt.grid_from_sphere(c)),
    "mesh.cull_tol": (
        "passed to the mesh methods, used only with mesh.cull_unseen",
        lambda c: not c.mesh.cull_unseen),
    "mesh.fit_points": (
        "read to ask whether the fit applies (options.wants_mesh_fit); it does not here",
        lambda c: not opt.wants_mesh_fit(c)),
    "train.snapshot_every": (
        "pictures of the surface as the field trains (OUT/field/snapshots/), not what it "
        "computes; keys.py leaves it out", always),
    "mvs.save_volumes": (
        "which files the stages 2-3 keep (their volumes), not what they compute; keys.py leaves "
        "it out", always),
    "mvs1:mvs.crop_to_masks": (
        "the backbone is built with it (backbone_kwargs) for stage 1, which it does not crop: "
        "only stages 2-3 are cropped, and their keys hold it", always),
    "mvs1:mvs.width": (
        "the backbone is built with it for stage 1, which spans the whole depth range at r = 1 "
        "under every width (mvs.hypotheses.WIDTHS); keys.py keeps half-default under the name "
        "its ratios had, paper, and marks today's paper in the stages 2-3 keys", always),
    "mesh:mvs.width": (
        "the mesh reads the final stage's depth step (fusion.observe.final_depth_step), r = "
        "0.5 at stage 3 under every width", always),
    "mvs1:scene.use_masks": (
        "ditto: backbone_kwargs reads it to leave the crop out when the run ignores the masks",
        always),
    "mvs23:scene.use_masks": (
        "ditto, for the guided stages 2-3: read with the crop; without one it changes nothing",
        lambda c: c.mvs.crop_to_masks is None),
    "guide:scene.use_masks": (
        "the field's PSNR over the masks, for timing.json only, when the guide is rendered on "
        "every pixel", lambda c: c.guide.mask_dilation is None),
}

#: (b) options a stage's key holds although neither it nor the stages it consumes read them:
#: {option or "prefix*": (why, when: as `INERT_READS`)}. None of them makes a stale result
#: reused; each only reruns a stage, and dropping it would change the keys of existing run
#: folders.
EXTRA_IN_KEY: dict[str, Rule] = {
    "mvs.*": ("the mvs section is hashed whole into the mvs1 key (which every key chains) and "
             "the mvs23 and unguided keys, also in modes that run no MVS", always),
    "field.*": ("the field section is hashed whole into the field key (the MLP's sizes with a "
               "grid field, the sphere's settings with an MVS start are out of it)", always),
    "train.*": ("the train section is hashed whole into the field key (options of other "
               "samplers, ablations and fields)", always),
    "preset": ("its name is hashed into the field key; its values are the other options",
               always),
    "fusion.*": ("the fusion section is hashed whole into the fusion key", always),
    "mesh.resolution": (
        "the field's marching cubes: a mesh method that fails (too few points) falls back to "
        "the field's zero level, which reads it", always),
    "guide.mask_dilation": (
        "in the guide key, which the mvs23 key chains in every mode, also where no field renders "
        "the guide (mvs-only, the soft-consistency ablation)", lambda c: not opt.has_field(c)),
    "guide.low_weight_rule": ("ditto", lambda c: not opt.has_field(c)),
}

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

#: options no recorded run takes another value of: {option: why}.
NOT_VARIED = {
    "fusion.network_weights": (
        "valid only with fusion.network, whose network no recorded run can start (no "
        "weights ship with the package); both enter the fusion key when set (keys.py)"),
}


# --------------------------------------------------------------------------- the changes
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


def _rule(rules: dict[str, Rule], option: str, cfgs: tuple[Config, ...], stage: str = ""
          ) -> str | None:
    """The rule of ``rules`` that names ``option`` ("train.*": every option it begins;
    "guide:option": the option read by that stage) and holds for each of ``cfgs`` (the
    recorded config and the changed one), or None."""
    def names(k: str) -> bool:
        if ":" in k:
            on, k = k.split(":")
            if on != stage:
                return False
        return option == k or k.endswith("*") and option.startswith(k[:-1])
    return next((k for k, (_, when) in rules.items()
                 if names(k) and all(when(c) for c in cfgs)), None)


def violations(name: str, record: dict, keys_of=stage_keys
               ) -> tuple[list[str], set[str], set[str]]:
    """([violations], {options another value of which was checked}, {rules of `INERT_READS` and
    `EXTRA_IN_KEY` that excused one}) of the recorded run ``name`` under the key function
    ``keys_of`` (`stage_keys`)."""
    cfg, reads = base_configs(SCENE)[name], record["reads"]
    base = keys_of(cfg, VIEWS)
    bad, checked, used = [], set(), set()
    for option in leaf_options():
        sec, _, field = option.rpartition(".")
        value = getattr(functools.reduce(getattr, sec.split("."), cfg) if sec else cfg, field)
        for v in other_values(option, value):
            alt = changed(cfg, option, v)
            try:
                validate_config(alt)  # e.g. no fusion network outside svolsdf mode
            except InputError:
                continue
            keys = keys_of(alt, VIEWS)
            checked.add(option)
            for stage in STAGES:
                if not (runs(stage, cfg) and runs(stage, alt)):
                    continue
                ups = upstream(stage, record)
                inert = {_rule(INERT_READS, option, (cfg, alt), u) for u in ups
                         if option in reads.get(u, ())}
                read = None in inert  # a read no rule sets aside
                moved = keys[stage] != base[stage]
                rule = (_rule(EXTRA_IN_KEY, option, (cfg, alt)) if moved and not read
                        else "")
                if not moved and not read:
                    used |= inert  # the rules that kept these reads from a violation
                used.add(rule or "")
                if read and not moved:
                    bad.append(f"{name}: stage {stage} reads {option} (directly or through "
                               f"what it consumes) but its key ignores {option}={v!r}")
                if rule is None and not read:
                    bad.append(f"{name}: the key of stage {stage} changes with {option}={v!r} "
                               f"but neither it nor what it consumes reads {option}")
    return bad, checked, used - {""}


TABLE = load_table()


@functools.cache
def _checked(name: str) -> tuple[tuple[str, ...], frozenset[str], frozenset[str]]:
    bad, checked, used = violations(name, TABLE[name])
    return tuple(bad), frozenset(checked), frozenset(used)


@pytest.mark.parametrize("name", sorted(TABLE))
def test_stage_keys_change_with_the_options_the_stages_read_and_only_those(name):
    bad = _checked(name)[0]
    assert not bad, "\n".join(bad)


def test_every_option_is_changed_in_some_run():
    """Each option but `NOT_VARIED`'s takes another valid value in at least one recorded run
    (some values are refused in some modes)."""
    checked = set().union(*(_checked(name)[1] for name in TABLE))
    assert checked == set(leaf_options()) - set(NOT_VARIED)


def test_every_exception_is_needed():
    """Each rule of `INERT_READS` and `EXTRA_IN_KEY` excuses some change of some run: a rule the
    keys no longer need goes."""
    used = set().union(*(_checked(name)[2] for name in TABLE))
    assert used == set(INERT_READS) | set(EXTRA_IN_KEY)


def test_a_forgotten_option_is_found():
    """A key function that forgets an option a stage reads (the mesh key without
    mesh.poisson.trim) or holds one no stage reads is caught, with the stage named."""
    def forgets(cfg, views):
        c = copy.deepcopy(cfg)
        c.mesh.poisson.trim = 5.0
        return stage_keys(c, views)

    bad = violations("svolsdf-poisson", TABLE["svolsdf-poisson"], forgets)[0]
    assert bad == ["svolsdf-poisson: stage mesh reads mesh.poisson.trim (directly or through "
                   "what it consumes) but its key ignores mesh.poisson.trim=10.0"]

    def holds(cfg, views):
        keys = stage_keys(cfg, views)
        return {**keys, "fusion": keys["fusion"] + str(cfg.mesh.support)}

    bad = violations("svolsdf-poisson", TABLE["svolsdf-poisson"], holds)[0]
    # the value tried is the first other valid one, which follows the preset's default
    assert len(bad) == 1 and bad[0].startswith(
        "svolsdf-poisson: the key of stage fusion changes with mesh.support=")
    assert bad[0].endswith(" but neither it nor what it consumes reads mesh.support")


def test_the_table_covers_every_stage_and_the_setup_reads_are_known():
    assert set(TABLE) == set(base_configs(SCENE))
    for name, record in TABLE.items():
        cfg, reads = base_configs(SCENE)[name], record["reads"]
        assert record["ran"] == [s for s in STAGES if runs(s, cfg)], name
        assert set(record["ran"]) <= set(reads) <= {*STAGES, "scene", "setup"}, name
        unknown = set(reads.get("setup", ())) - set(SETUP_READS)
        assert not unknown, f"{name}: read outside every stage: {sorted(unknown)}"
        # a stage consumes only what ran before it
        for s, ups in record["consumes"].items():
            assert set(ups) <= set(record["ran"][:record["ran"].index(s)]), (name, s, ups)
    every = set(leaf_options())
    for rules in (SETUP_READS, NOT_VARIED):
        assert set(rules) <= every, set(rules) - every
    for rules in (INERT_READS, EXTRA_IN_KEY):
        for k in rules:
            k = k.split(":")[-1]
            assert k in every or k.endswith("*") and any(o.startswith(k[:-1]) for o in every), k


#: stage keys (in `STAGES` order) of the defaults and the presets, with the version "pinned":
#: the keys of existing run folders must not change (issue 40: keys.py's fixes enter only when
#: set). Change them only with a change that means to rerun those stages (a backbone default).
PINNED = {
    # every preset: the stages 2-3 keys (and those chained on them) changed when mvs.width
    # "paper" became the paper's explicit intervals 1, 0.5, 0.5 (the old reading is
    # "half-default", with the old keys: test_width_half_default_keeps_the_keys_paper_had)
    "defaults": "d260427d8ce9 16dbf7e854f9 d9476149c525 e566642d357a 4176f0fee367 570ed9a7dc69 "
                "5fa6188dcc53",
    # the mesh key changed with mesh.support = 4 in the fast preset (issue 47); the field key
    # (and the keys chained on it) with train.colour_min_weight and train.prior_floor in the
    # fast preset (issue 48): an earlier fast run reruns from its field on (stage 1 is reused);
    # the stages 2-3 keys with mvs.crop_to_masks = 16 (issue 48)
    "fast": "d260427d8ce9 11eef0e27282 1c56f9684c56 ddd6930391aa db6ed3132a8b def80ccacd2a "
            "c045e97438aa",
    "paper": "d260427d8ce9 407d7e6ab236 70cdfa8b5213 ca48d7438d86 4176f0fee367 39f7eb1fcecf "
             "595955346277",
}


@pytest.mark.parametrize("name", sorted(TABLE))
def test_the_declared_reads_and_consumes_cover_what_the_stages_were_seen_doing(name):
    """Each stage's declaration (`svolsdf.pipeline.stages`: `Stage.reads` of the run's config,
    `Stage.consumes`) covers the options and the earlier stages the recorded run saw it read."""
    from svolsdf.pipeline.stages import stage

    cfg, record, bad = base_configs(SCENE)[name], TABLE[name], []
    for s in STAGES:
        declared = stage(s)
        bad += [f"{name}: stage {s} reads {o} but does not declare it"
                for o in record["reads"].get(s, []) if not declared.declares(cfg, o)]
        bad += [f"{name}: stage {s} consumes {c} but does not declare it"
                for c in record["consumes"].get(s, []) if c not in declared.consumes]
    assert not bad, "\n".join(bad)


def test_an_undeclared_read_is_found(monkeypatch):
    from svolsdf.pipeline.stages.guide import Guide

    monkeypatch.setattr(Guide, "reads", lambda self, cfg: ("scene.use_masks",))
    with pytest.raises(AssertionError, match="stage guide reads guide.mask_dilation but does not"):
        test_the_declared_reads_and_consumes_cover_what_the_stages_were_seen_doing(
            "svolsdf-poisson")


def test_the_keys_of_existing_run_folders_stay(monkeypatch):
    import svolsdf
    from svolsdf.config import preset

    monkeypatch.setattr(svolsdf, "__version__", "pinned")
    for name, pinned in PINNED.items():
        cfg = Config() if name == "defaults" else preset(name)
        cfg.scene.path = SCENE
        keys = stage_keys(cfg, VIEWS)
        assert " ".join(keys[s] for s in STAGES) == pinned, name


def test_use_masks_enters_the_stages_that_read_the_masks():
    """Issue 40: scene.use_masks = false changes the field started from the MVS surface (its
    start votes inside the masks) and the guide rendered within the dilated masks; it was in
    no key before fusion's. The default (true) adds nothing to any key."""
    from svolsdf.config import preset

    cfg = preset("fast")
    cfg.scene.path = SCENE
    no = changed(cfg, "scene.use_masks", False)
    k, k_no = stage_keys(cfg, VIEWS), stage_keys(no, VIEWS)
    # the fast preset crops stages 2-3 to the masks (mvs.crop_to_masks): the unguided ones too
    assert k_no["mvs1"] == k["mvs1"] and k_no["unguided"] != k["unguided"]
    assert all(k_no[s] != k[s] for s in ("field", "guide", "mvs23", "fusion", "mesh"))
    cfg.mvs.crop_to_masks = None
    k, k_no = stage_keys(cfg, VIEWS), stage_keys(changed(cfg, "scene.use_masks", False), VIEWS)
    assert k_no["mvs1"] == k["mvs1"] and k_no["unguided"] == k["unguided"]
    # VolSDF's field reads no mask (its sphere start, every ray uniform): only its guide does
    cfg.train.mode = "volsdf"
    k, k_no = stage_keys(cfg, VIEWS), stage_keys(changed(cfg, "scene.use_masks", False), VIEWS)
    assert k_no["field"] == k["field"] and k_no["guide"] != k["guide"]
    cfg.train.object_ray_fraction = 0.5  # rays drawn inside the masks: the field reads them
    k, k_no = stage_keys(cfg, VIEWS), stage_keys(changed(cfg, "scene.use_masks", False), VIEWS)
    assert k_no["field"] != k["field"]
    cfg.train.mode = "mvs-only"  # no field, no rendered guide: only fusion reads the masks
    k, k_no = stage_keys(cfg, VIEWS), stage_keys(changed(cfg, "scene.use_masks", False), VIEWS)
    assert [s for s in ("mvs1", "mvs23", "unguided", "fusion") if k_no[s] != k[s]] == ["fusion"]


@pytest.mark.slow
def test_the_recorded_table_is_what_the_stages_read(tmp_path):
    """The tiny runs of stage_reads.py read what stage_reads.json says (regenerate it with
    ``PYTHONPATH=src python tests/pipeline/stage_reads.py`` when a stage reads other options,
    then check the fast tests above)."""
    now, diff = record_all(tmp_path), []
    for name in sorted(set(now) | set(TABLE)):
        for part in ("reads", "consumes", "ran"):
            got, had = now.get(name, {}).get(part, {}), TABLE.get(name, {}).get(part, {})
            if part == "ran":
                got, had = {"": got}, {"": had}
            for stage in sorted(set(got) | set(had)):
                new, gone = (set(got.get(stage, [])) - set(had.get(stage, [])),
                             set(had.get(stage, [])) - set(got.get(stage, [])))
                if new or gone:
                    diff.append(f"{name} {part} {stage}: now also {sorted(new)}, no longer "
                                f"{sorted(gone)}")
    assert not diff, "stage_reads.json is stale (regenerate it):\n" + "\n".join(diff)


def test_width_half_default_keeps_the_keys_paper_had(monkeypatch):
    """``mvs.width = half-default`` is the ratios ``paper`` meant before it became the paper's
    explicit numbers: its stage keys are those the old ``paper`` had (run folders of that
    reading keep their stages), and today's ``paper`` has others (its stages rerun)."""
    import svolsdf.pipeline.keys as keys
    from svolsdf.config import preset

    def keyed(width: str) -> dict:
        c = preset("fast")
        c.scene.path = "scene"
        c.mvs.width = width
        return keys.stage_keys(c, [0, 1, 2])

    new_paper, half = keyed("paper"), keyed("half-default")
    monkeypatch.setattr(keys, "_WIDTH_KEYS", {})  # the keys before the rename
    monkeypatch.setattr(keys, "_WIDTH_MARKED", ())
    old_paper = keyed("paper")
    assert half == old_paper
    # stage 1 and the field do not depend on the finer stages' width: kept; the rest reruns
    assert [s for s in keys.STAGES if new_paper[s] != old_paper[s]] == [
        "mvs23", "unguided", "fusion", "mesh"]
