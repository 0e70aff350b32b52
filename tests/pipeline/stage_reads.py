"""Which config options each pipeline stage reads, and which earlier stages' outputs it loads: a
recorder of attribute reads on the config dataclasses and tiny runs of the pipeline's modes under
it, which tests/pipeline/test_stage_reads.py checks the stages' declarations against.

How reads are recorded: while a run records, every config dataclass (`Config`, `SceneConfig`,
...) gets a ``__getattribute__`` that notes each read of one of its leaf fields ("train.steps";
also through objects the stages hand the sections to, such as the `Trainer`'s ``TrainConfig``)
under the stage the `Pipeline` is in (its ``_stage``). Reads while the pipeline loads the scene
(`Run.load`) count as the pseudo-stage "scene", which every stage reads. Reads that decide nothing
a stage computes are not recorded: the key and input-key computation itself, writing
config.yaml, validation and the refusals before a stage (`validate_config`,
`Pipeline._check_options`, `check_scene`). Other reads outside a stage (the device, which stages
run, the log line, the thread count) count as "setup".

Which earlier stages' outputs a stage consumes is recorded in the same runs: the files of the run
folder it loads (`numpy.load`, `torch.load`, `read_ply`, `ProbabilityVolume.load`; each file's
folder names the stage that writes it, `_producer`) and the results the `Pipeline` holds in
memory (`IN_MEMORY`: the stage-1 volumes, the field). "ran" lists the stages that ran.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path

from svolsdf.config import Config
from svolsdf.config.schema import (
    FieldConfig,
    FusionConfig,
    GuideConfig,
    MeshConfig,
    MVSConfig,
    PoissonConfig,
    SceneConfig,
    TrainConfig,
    TSDFConfig,
)
from svolsdf.pipeline.keys import STAGES

SECTIONS = {Config: "", SceneConfig: "scene", MVSConfig: "mvs", FieldConfig: "field",
            TrainConfig: "train", GuideConfig: "guide", FusionConfig: "fusion",
            MeshConfig: "mesh", PoissonConfig: "mesh.poisson", TSDFConfig: "mesh.tsdf"}


def _leaves(cls) -> set[str]:
    """The names of ``cls``'s fields that are options, not sections."""
    return {f.name for f in dataclasses.fields(cls)
            if not (f.default_factory is not dataclasses.MISSING
                    and dataclasses.is_dataclass(f.default_factory()))}


def leaf_options() -> list[str]:
    """Every leaf option of `Config` ("preset", "scene.path", ..., "mesh.tsdf.resolution")."""
    out = []
    for cls, sec in SECTIONS.items():
        for f in dataclasses.fields(cls):
            if f.name in _leaves(cls):
                out.append(f"{sec}.{f.name}" if sec else f.name)
    return out


# --------------------------------------------------------------------------- the runs
def _tiny(cfg: Config, scene: Path) -> Config:
    """``cfg`` shortened for the tiny scene (seconds per run)."""
    cfg.scene.path = str(scene)
    cfg.train.steps = 12
    cfg.train.rays = 64
    cfg.train.anneal_rgb = 4
    cfg.train.checkpoint_every = 0
    cfg.field.grid_start_resolution = 16
    cfg.field.grid_resolution = 32
    cfg.field.sphere_start_resolution = 16
    cfg.mvs.ndepths = [32, 8, 4]
    cfg.mesh.resolution = 48
    cfg.mesh.fit_points = 20
    cfg.mesh.tsdf.resolution = 64
    cfg.mesh.poisson.depth = 6
    cfg.device = "cpu"
    return cfg


def base_configs(scene: Path) -> dict[str, Config]:
    """The recorded runs: {name: config}. The fast preset in each mode and with each mesh
    method (it turns on most conditional options: the unguided set, guide masks, culling,
    free space), and the paper's ablation-free options that the fast preset leaves off."""
    from svolsdf.config import preset

    cfgs = {}
    for method in ("poisson", "field", "tsdf"):
        c = _tiny(preset("fast"), scene)
        c.mesh.method = method
        cfgs[f"svolsdf-{method}"] = c
    # the other options the fast preset leaves off: finer-stage optimization (after stages 2
    # and 3), unseen culling
    # off, support trimming, the object-ray share, the MLP field
    c = _tiny(preset("fast"), scene)
    c.mesh.method = "field"
    c.mesh.fit_points = 0
    c.mesh.cull_unseen = False
    c.mesh.support = 3.0
    c.mvs.finer_stage_optimization = True
    c.mvs.third_stage_optimization = True  # and once more after stage 3 (stages 1, 2, 3)
    c.train.object_ray_fraction = 0.5
    cfgs["svolsdf-finer"] = c
    # the paper preset: the MLP field from the sphere, the guide on every pixel, no unguided
    # set, no culling (with the fast sampler: VolSDF's takes minutes on the whole guide); and
    # the watertight mesh
    c = _tiny(preset("paper"), scene)
    c.field.mlp_depth, c.field.mlp_width = 5, 48
    c.train.sampler = "mvs"
    c.train.samples_uniform = c.train.samples_fine = 16  # the MLP renders the whole guide
    c.scene.image_size = [64, 48]
    c.mesh.watertight = True
    cfgs["paper-watertight"] = c
    # two of the paper's ablations: the guide from the stage-1 volumes' consistency (no
    # field), and the field fitted to the filtered stage-1 depth
    for ablation in ("soft-consistency-only", "mse"):
        c = _tiny(preset("fast"), scene)
        c.train.ablation = ablation
        cfgs[f"ablation-{ablation.split('-')[0]}"] = c
    c = _tiny(preset("fast"), scene)
    c.train.mode = "volsdf"
    cfgs["volsdf"] = c
    c = _tiny(preset("fast"), scene)
    c.train.mode = "mvs-only"
    cfgs["mvs-only"] = c
    return cfgs


# --------------------------------------------------------------------------- the recorder
class Reads:
    """{stage: set of options} read while recording (`recording`)."""

    def __init__(self):
        self.by_stage: dict[str, set[str]] = defaultdict(set)
        self.where: Callable[[], str | None] = lambda: None
        self.override: list[str | None] = []  # innermost last; None = not recorded

    def note(self, option: str) -> None:
        stage = self.override[-1] if self.override else self.where()
        if stage is not None:
            self.by_stage[stage].add(option)

    @contextlib.contextmanager
    def as_stage(self, stage: str | None) -> Iterator[None]:
        self.override.append(stage)
        try:
            yield
        finally:
            self.override.pop()

    def wrap(self, fn: Callable, stage: str | None) -> Callable:
        """``fn`` whose reads count as ``stage`` (None: not recorded)."""
        @functools.wraps(fn)
        def inner(*a, **k):
            with self.as_stage(stage):
                return fn(*a, **k)
        return inner


@contextlib.contextmanager
def recording(reads: Reads) -> Iterator[Reads]:
    """Record reads of the config dataclasses' leaf fields into ``reads`` while inside."""
    leaves = {cls: _leaves(cls) for cls in SECTIONS}
    for cls, sec in SECTIONS.items():
        def getattribute(self, name, _leaves=leaves[cls], _sec=sec):
            if name in _leaves:
                reads.note(f"{_sec}.{name}" if _sec else name)
            return object.__getattribute__(self, name)
        cls.__getattribute__ = getattribute
    try:
        yield reads
    finally:
        for cls in SECTIONS:
            del cls.__getattribute__


def _producer(d, path) -> str | None:
    """The stage that writes ``path`` in the run folder ``d`` (a `RunDir`), or None."""
    try:
        rel = Path(path).resolve().relative_to(d.root.resolve()).as_posix()
    except (TypeError, ValueError):  # a file object, or a file outside the run folder
        return None
    # the finer-stage optimization (field/stage2) runs in the mvs23 stage
    for prefix, stage in (("mvs/stage1/", "mvs1"), ("field/stage2/", "mvs23"),
                          ("field/render_depth/", "guide"), ("field/surface", "mesh"),
                          ("field/", "field"), ("mvs/", "mvs23"), ("depth/", "mvs23"),
                          ("confidence/", "mvs23"), ("unguided/", "unguided"),
                          ("network/", "fusion"), ("points.ply", "fusion")):
        if rel.startswith(prefix):
            return stage
    return None


#: Pipeline attributes that hold a stage's result in memory: {attribute: stage}.
IN_MEMORY = {"_volumes1": "mvs1", "_reg1": "mvs1", "_model": "field"}


def record_run(cfg: Config, out: Path) -> dict[str, dict[str, list[str]]]:
    """Run ``cfg`` into ``out``; returns {"reads": {stage: sorted options it read} (the stages
    it ran, "scene" and "setup"), "consumes": {stage: sorted earlier stages whose outputs it
    read, from the run folder's files or in memory}, "ran": [the stages that ran]} (see the
    module docstring)."""
    import numpy as np
    import torch

    import svolsdf.io.ply as ply
    import svolsdf.scene.checks as checks
    from svolsdf.mvs.volume import ProbabilityVolume
    from svolsdf.pipeline import Pipeline, loaded_run, runner

    reads, consumed = Reads(), defaultdict(set)
    run: dict = {}  # the Pipeline, once made

    def where() -> str | None:
        stage = run["p"]._stage if "p" in run else "setup"
        return stage if stage != "finish" else None

    reads.where = where

    def consume(stage: str | None) -> None:
        now = reads.where()
        if stage is not None and now in STAGES and stage != now:
            consumed[now].add(stage)

    def loads(fn):
        @functools.wraps(fn)
        def inner(path, *a, **k):
            if "p" in run:
                consume(_producer(run["p"].dir, path))
            return fn(path, *a, **k)
        return inner

    class Inputs(dict):
        """What the runner hands a stage: reading one of them consumes that stage."""

        def __getitem__(self, stage):
            value = super().__getitem__(stage)
            if value is not None:
                consume(stage)
            return value

    drive = Pipeline._drive

    def driven(self, stage, inputs):
        return drive(self, stage, Inputs(inputs))

    def getattribute(self, name):
        value = object.__getattribute__(self, name)
        if name in IN_MEMORY and value is not None:
            consume(IN_MEMORY[name])
        return value

    saved = {(loaded_run, "stage_keys"): reads.wrap(loaded_run.stage_keys, None),
             (runner, "input_keys"): reads.wrap(runner.input_keys, None),
             (runner, "save_config"): reads.wrap(runner.save_config, None),
             (runner, "validate_config"): reads.wrap(runner.validate_config, None),
             (checks, "check_scene"): reads.wrap(checks.check_scene, None),
             (np, "load"): loads(np.load), (torch, "load"): loads(torch.load),
             (ply, "read_ply"): loads(ply.read_ply),
             (ProbabilityVolume, "load"): staticmethod(loads(ProbabilityVolume.load))}
    # the attributes as stored (a class's classmethod itself)
    saved = {(o, n): (o.__dict__[n] if isinstance(o, type) else getattr(o, n), new)
             for (o, n), new in saved.items()}
    Pipeline.__getattribute__ = getattribute
    Pipeline._drive = driven
    try:
        for (owner, name), (_, new) in saved.items():
            setattr(owner, name, new)
        with recording(reads):
            p = run["p"] = Pipeline(cfg, out, progress=False)
            p._check_options = reads.wrap(p._check_options, None)
            p.load = reads.wrap(p.load, "scene")
            p.run()
    finally:
        del Pipeline.__getattribute__
        Pipeline._drive = drive
        for (owner, name), (old, _) in saved.items():
            setattr(owner, name, old)
    return {"reads": {s: sorted(o) for s, o in sorted(reads.by_stage.items())},
            "consumes": {s: sorted(c) for s, c in sorted(consumed.items())},
            "ran": [s for s in STAGES if s in p.timing]}


def record_all(folder: Path) -> dict:
    """{run name: `record_run`'s record} of every `base_configs` run of a tiny synthetic scene
    made in ``folder``."""
    from tiny_pipeline import make_tiny_scene

    scene = make_tiny_scene(folder / "scene")
    table = {}
    for name, cfg in base_configs(scene).items():
        table[name] = record_run(cfg, folder / name)
    return table
