"""Training-step speed of the fast preset: the current code against its previous versions.

One fast-preset field step (`Trainer.train_step`: rays, MVS-guided sampler, prior lookups,
rendering, losses, backward, NaN-safe clipping, Adam) on a finished run's stage-1 volumes, with
the field at its full grid resolution. Variants, each with its own trainer, timed round-robin in
blocks of steps (the machine is shared; ratios in one run are what counts):

- "current": the code as it is;
- "previous": the parts below (one set, ``--parts``) as they were;
- "previous X": only part X as it was.

Parts before issue 39 (``--parts 39``, the default): "corners" (`trilinear_sample`
differentiated by autograd through its corners-last (C, N, 8) expression instead of its own
backward on corner-major tensors), "eikonal" (the eikonal points read with `sdf_and_grad`, the
colour features computed and discarded, instead of `GridSDFField.sdf_grad`), "buffers" (the
feature grids' gradients freed every step and allocated anew instead of reused,
`GridSDFField.recycle_grads`).

Parts before commit 467f395 (``--parts 467f395``): "features" (the colour feature grids read with
``F.grid_sample`` instead of `trilinear_sample`), "prior" (each stage-1 volume read by one
``F.grid_sample`` batch entry, i.e. one thread, instead of one entry per thread), "clip" (the
per-tensor finite check, ``nan_to_num_`` and ``clip_grad_norm_``), "adam" (``torch.optim.Adam``
with the per-tensor loop instead of the fused kernel). A corner gather for the one-channel
volumes was also tried and was slower than ``grid_sample`` (40 against 30 ms for the three
volumes at a step's 41k samples).

Run (from the repo root), on a finished `svolsdf reconstruct` folder of the fast preset:

    python benchmarks/train_step_speed.py --run OUT [--phase 64|91|128] [--parts 39|467f395]
        [--out benchmarks/results/train_step_speed.md]
"""

from __future__ import annotations

import os

# before torch loads its OpenMP runtime (as svolsdf/__init__.py does): threads that spin while
# waiting make every step several times slower when another process shares the cores
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import logging  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import types  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import cpu_name, write_results  # noqa: E402

from svolsdf.config import load_config  # noqa: E402
from svolsdf.config.io import apply_overrides  # noqa: E402
from svolsdf.field.grid_ops import _corners, device_vector  # noqa: E402
from svolsdf.field.initial import init_grid_from_mvs  # noqa: E402
from svolsdf.optimize.trainer import Trainer  # noqa: E402
from svolsdf.pipeline import Pipeline  # noqa: E402
from svolsdf.pipeline.builders import build_sampler, grid_schedule  # noqa: E402
from svolsdf.prior.consistency import _MIN_Z, _Z_LIMIT, MVSPrior, _depth_coord, _project  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PARTS = ("features", "prior", "clip", "adam")  # before commit 467f395
PARTS_39 = ("corners", "eikonal", "buffers")  # before issue 39's changes


# ---------------------------------------------------------------------- previous versions
def features_grid_sample(self, p: torch.Tensor) -> torch.Tensor:
    """The previous `GridSDFField._features`: p (N, 3) -> (N, F) with ``F.grid_sample``."""
    lo, hi = self.bounds
    g = ((p - lo) / (hi - lo) * 2 - 1).view(1, -1, 1, 1, 3)
    feats = [F.grid_sample(fg[None], g, mode="bilinear", align_corners=True).view(fg.shape[0], -1)
             for fg in self.feature_grids]
    return torch.cat(feats, dim=0).T


def view_lookup_one_batch(self, i: int, pts: torch.Tensor):
    """The previous `MVSPrior.view_lookup`: one ``grid_sample`` batch entry (one thread)."""
    view = self.views[i]
    uh, vh, z, valid = _project(view, pts)
    uh = torch.where(valid, uh, torch.full_like(uh, -99.0))
    vh = torch.where(valid, vh, torch.full_like(vh, -99.0))
    grid2 = torch.stack([uh, vh], dim=-1)[None, None]
    nf = torch.stack([view.near, view.far])[None]
    nf_s = F.grid_sample(nf, grid2, mode="bilinear", padding_mode="zeros",
                         align_corners=True)[0, :, 0]
    near, far = nf_s[0], nf_s[1]
    zh = _depth_coord(view, z, near, far)
    valid = valid & (near >= _MIN_Z) & (far >= _MIN_Z) & (zh.abs() <= _Z_LIMIT)
    zh = torch.where(valid, zh, torch.full_like(zh, -99.0))
    grid3 = torch.stack([uh, vh, zh], dim=-1)[None, None, None]
    cost = F.grid_sample(view.prob[None, None], grid3, mode="bilinear", padding_mode="zeros",
                         align_corners=True)[0, 0, 0, 0]
    return torch.where(valid, cost, torch.zeros_like(cost)), valid


def trilinear_sample_autograd(grid: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """The previous `trilinear_sample`: (C, Z, Y, X), (N, 3) -> (N, C), differentiated by
    autograd through the gather, the product and the transposed sum."""
    C = grid.shape[0]
    idx, f = _corners(u, tuple(grid.shape[1:]))
    wx, wy, wz = (torch.stack([1.0 - f[:, k], f[:, k]], dim=-1) for k in range(3))
    w = (wz[:, :, None, None] * wy[:, None, :, None] * wx[:, None, None, :]).reshape(1, -1, 8)
    c = grid.reshape(C, -1).index_select(1, idx.reshape(-1)).view(C, -1, 8)
    return (c * w).sum(-1).T


def features_autograd(self, p: torch.Tensor) -> torch.Tensor:
    """The previous `GridSDFField._features`: p (N, 3) -> (N, F) with the autograd gather."""
    lo, hi = self.bounds
    t = (p - lo) / (hi - lo)
    feats = []
    for fg in self.feature_grids:
        Z, Y, X = fg.shape[1:]
        scale = device_vector([X - 1, Y - 1, Z - 1], t.device, t.dtype)
        feats.append(trilinear_sample_autograd(fg, t * scale))
    return torch.cat(feats, dim=1)


def sdf_grad_with_features(self, x: torch.Tensor, create_graph: bool = True,
                           clamp: bool = True):
    """The previous eikonal lookup: `sdf_and_grad`, its colour features discarded; x (N, 3) ->
    sdf (N,), grad (N, 3)."""
    sdf, grad, _ = self.sdf_and_grad(x, create_graph=create_graph, clamp=clamp)
    return sdf, grad


def no_recycling() -> None:
    """The previous gradient clearing: the feature grids' gradients freed, new ones allocated
    by the next backward (instead of `GridSDFField.recycle_grads`)."""


def safe_clip_previous(self, params: list[torch.Tensor]) -> None:
    """The previous NaN-safe update: a finite check per tensor, then clip_grad_norm_."""
    finite = torch.stack([torch.isfinite(p.grad).all() for p in params]).all()
    for p in params:
        p.grad.nan_to_num_(0.0, 0.0, 0.0).mul_(finite)
    if self.cfg.grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(params, self.cfg.grad_clip)


# ---------------------------------------------------------------------- set-up
def build_trainer(run: Path, previous: set[str] = frozenset(), steps: int | None = None,
                  overrides: dict | None = None) -> Trainer:
    """The field stage's trainer on ``run``'s config and stage-1 volumes (model, MVS
    initialisation, prior, sampler and grid schedule as the pipeline builds them), at step 0 with
    the grid at its start resolution, with the ``previous`` parts swapped in; ``steps`` replaces
    ``train.steps`` (the grid schedule follows it); ``overrides`` ({"section.option": value}, as
    ``--set``) change the run's config. It reads ``run`` and writes nothing there."""
    cfg = load_config(run / "config.yaml")
    if overrides:
        apply_overrides(cfg, overrides)
    if steps is not None:
        cfg.train.steps = steps
    p = Pipeline(cfg, run, progress=False)
    scene = p.load()
    p.keys = p.stage_keys()
    p.volumes1 = p.run_stage("mvs1")
    torch.manual_seed(0)
    model = p.build_model()
    prior = MVSPrior(p.volumes1, scene.normalization, device=p.device)
    init_grid_from_mvs(model, p.regressed_volumes1(), scene.normalization,
                       scene.masks if cfg.scene.use_masks else None,
                       init_unverified_weight=cfg.field.init_unverified_weight)
    if "features" in previous:
        model._features = types.MethodType(features_grid_sample, model)
    elif "corners" in previous:
        model._features = types.MethodType(features_autograd, model)
    if "eikonal" in previous:
        model.sdf_grad = types.MethodType(sdf_grad_with_features, model)
    if "buffers" in previous:
        model.recycle_grads = no_recycling
    if "prior" in previous:
        prior.view_lookup = types.MethodType(view_lookup_one_batch, prior)
    t = Trainer(model, p.train_data(), cfg.train, prior=prior, sampler=build_sampler(p.cfg, prior),
                out_dir=None, device=p.device, grid_schedule=grid_schedule(p.cfg))
    if "clip" in previous:
        t._safe_clip = types.MethodType(safe_clip_previous, t)
    return t


def make_trainer(run: Path, previous: set[str], warm_steps: int, phase: int | None = None,
                 overrides: dict | None = None) -> Trainer:
    """A fast-preset trainer on ``run``'s stage-1 volumes with the ``previous`` parts swapped
    in, after ``warm_steps`` steps. ``phase`` None: a run of ``warm_steps`` steps (its grid
    reaches the full resolution at half of them). ``phase`` = a grid resolution of the run's
    schedule (or its start resolution): the run's own steps, the grid set to that resolution
    and the step counter past the phase's start (the RGB warm-up over), so the warm-up steps
    and the timed ones see that phase's losses, grid and schedules."""
    if phase is None:
        t = build_trainer(run, previous, steps=warm_steps, overrides=overrides)
        t.fit(progress=False)  # warm-up: grid growth done, optimizer state built
    else:
        t = build_trainer(run, previous, overrides=overrides)
        starts = {t.model.resolution: 0} | {r: k for k, r in t.grid_schedule}
        if phase not in starts:
            sys.exit(f"train_step_speed: --phase {phase} is not a grid resolution of the run "
                     f"({sorted(starts)})")
        if phase > t.model.resolution:
            t.model.upsample(phase)
            t._build_optimizer()
        t.step = max(starts[phase], t.cfg.anneal_rgb) + 10
        t.fit(steps=t.step + warm_steps, progress=False)
    if "adam" in previous:
        state = t.optimizer.state_dict()
        groups = [{"params": g["params"], "lr": g["lr"]} for g in t.optimizer.param_groups]
        t.optimizer = torch.optim.Adam(groups, foreach=False)
        t.optimizer.load_state_dict(state)  # this also restores the groups' "fused" flag
        for g in t.optimizer.param_groups:
            g["fused"], g["foreach"] = False, False
    return t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, required=True,
                    help="a finished fast-preset `svolsdf reconstruct` folder")
    ap.add_argument("--warm", type=int, default=24, help="warm-up steps per trainer")
    ap.add_argument("--block", type=int, default=10, help="steps per timed block")
    ap.add_argument("--repeats", type=int, default=5, help="timed blocks per variant")
    ap.add_argument("--parts", choices=("39", "467f395"), default="39",
                    help="which previous versions: before issue 39 (corners, eikonal, "
                         "buffers) or before commit 467f395 (features, prior, clip, adam)")
    ap.add_argument("--phase", type=int, default=None,
                    help="time the steps at this grid resolution of the run's schedule (the "
                         "run's own step count); default: a run of --warm steps, full grid")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks/results/train_step_speed.md")
    args = ap.parse_args()
    if not (args.run / "config.yaml").is_file():
        sys.exit(f"train_step_speed: {args.run} has no config.yaml (not a run folder)")
    logging.disable(logging.INFO)
    parts = PARTS if args.parts == "467f395" else PARTS_39
    variants = {"current": set(), "previous": set(parts)}
    variants.update({f"previous {k}": {k} for k in parts})
    trainers = {k: make_trainer(args.run, v, args.warm, args.phase) for k, v in variants.items()}
    first_step = trainers["current"].step - args.warm  # where the warm-up steps started
    times = {k: [] for k in trainers}
    cpu = {k: [] for k in trainers}
    for _ in range(args.repeats):
        for k, t in trainers.items():
            t0, c0 = time.perf_counter(), time.process_time()
            for _ in range(args.block):
                t.train_step()
            times[k].append((time.perf_counter() - t0) / args.block)
            cpu[k].append((time.process_time() - c0) / args.block)
    med = {k: statistics.median(v) for k, v in times.items()}
    medc = {k: statistics.median(v) for k, v in cpu.items()}
    m = trainers["current"].model
    n_par = sum(p.numel() for p in m.parameters()) / 1e6
    lines = [
        "# Training-step speed of the fast preset (current vs previous code)",
        "",
        f"- command: `python benchmarks/train_step_speed.py --run {args.run} --warm {args.warm} "
        f"--block {args.block} --repeats {args.repeats} --parts {args.parts}"
        + (f" --phase {args.phase}`" if args.phase is not None else "`"),
        f"- machine: {os.cpu_count()} logical cores, {cpu_name()}; torch "
        f"{torch.__version__}, {torch.get_num_threads()} threads; Python "
        f"{platform.python_version()}; shared machine (other jobs may run)",
        f"- field: grid {getattr(m, 'grid_shape', '?')} SDF nodes, {n_par:.1f} M parameters; "
        f"{trainers['current'].cfg.rays} rays per step; {len(trainers['current'].prior)} "
        f"stage-1 volumes",
        f"- each variant: its own trainer, {args.warm} warm-up steps ("
        + ("past the grid growth" if args.phase is None else
           f"from step {first_step} of the run's schedule")
        + f"), then "
        f"{args.repeats} blocks of {args.block} steps, round-robin; median per step (CPU: "
        f"the process's CPU time, both threads)",
        "",
        "| variant | wall ms / step | CPU ms / step | wall, current = 1 | CPU, current = 1 "
        "| fastest block's wall ms / step |",
        "|---|---|---|---|---|---|",
    ]
    for k in trainers:
        lines.append(f"| {k} | {med[k] * 1000:.0f} | {medc[k] * 1000:.0f} | "
                     f"{med[k] / med['current']:.2f} | {medc[k] / medc['current']:.2f} | "
                     f"{min(times[k]) * 1000:.0f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    write_results(args.out, text)


if __name__ == "__main__":
    main()
