"""Field speed: one training step's field work on 512 rays x 96 samples, grid field vs VolSDF MLP.

A step here is what the trainer does with the field for one batch: ``sdf_and_grad`` with
create_graph on every sample, Laplace density, colour, alpha compositing along the rays
(docs/method.md 5.4), an L1 RGB loss plus 0.1 x eikonal (docs/method.md 4.6), backward, and (timed
separately) an Adam step. Also measured: three ways to get the SDF grid's spatial gradient with
create_graph (closed form from 8 gathered corners, autograd through ``grid_sample``, central finite
differences at half a cell), and ``torch.compile`` of the grid field's forward.

Run (from the repo root):

    python benchmarks/field_speed.py --out benchmarks/results/field_speed.md

The configurations are timed interleaved (round-robin) so that load from other processes on a
shared machine spreads over all of them; the table reports the median.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F

from svolsdf.field.base import SurfaceModel
from svolsdf.field.grid import GridFieldConfig, GridSDFField
from svolsdf.field.grid_ops import trilinear_with_grad

RAYS, SAMPLES = 512, 96
HEADER = (
    "| field | params (M) | fwd+bwd wall (ms) | fwd+bwd CPU (ms) | Adam step wall (ms) "
    "| speed-up vs MLP, wall | speed-up vs MLP, CPU |"
)


def _machine() -> str:
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    load = os.getloadavg() if hasattr(os, "getloadavg") else ("?",)
    return (
        f"- CPU: {cpu}, {os.cpu_count()} logical cores; torch threads: {torch.get_num_threads()}\n"
        f"- torch {torch.__version__}, Python {platform.python_version()}, {platform.system()}\n"
        f"- load average at start: {', '.join(f'{v:.1f}' for v in load)} "
        "(the machine is shared; see the note below)"
    )


def _batch(seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    origins = F.normalize(torch.randn(RAYS, 3, generator=g), dim=-1) * 2.5
    target = F.normalize(torch.randn(RAYS, 3, generator=g), dim=-1) * 0.3
    dirs = F.normalize(target - origins, dim=-1)
    z = torch.linspace(0.5, 4.5, SAMPLES).expand(RAYS, SAMPLES)
    z = z + torch.rand(RAYS, SAMPLES, generator=g) * (4.0 / SAMPLES)
    return {
        "x": (origins[:, None] + dirs[:, None] * z[..., None]).reshape(-1, 3),
        "d": dirs[:, None].expand(RAYS, SAMPLES, 3).reshape(-1, 3),
        "z": z,
        "rgb": torch.rand(RAYS, 3, generator=g),
    }


def _loss(field: SurfaceModel, b: dict[str, torch.Tensor]) -> torch.Tensor:
    sdf, grad, feat = field.sdf_and_grad(b["x"], create_graph=True)
    sigma = field.density(sdf).view(RAYS, SAMPLES)
    rgb = field.colour(b["x"], b["d"], grad, feat).view(RAYS, SAMPLES, 3)
    delta = torch.cat([b["z"][:, 1:] - b["z"][:, :-1], torch.full((RAYS, 1), 1e10)], dim=1)
    # docs/method.md 5.4: alpha_i = 1 - exp(-sigma_i delta_i), T_i = exp(-sum_j<i)
    sd = sigma * delta
    trans = torch.exp(-torch.cumsum(torch.cat([torch.zeros(RAYS, 1), sd[:, :-1]], 1), 1))
    w = (1 - torch.exp(-sd)) * trans
    colour = (w[..., None] * rgb).sum(1)
    eik = (grad.norm(dim=-1) - 1).square().mean()
    return (colour - b["rgb"]).abs().mean() + 0.1 * eik  # docs/method.md 4.6 weights


def _fwd_bwd(field: SurfaceModel, b) -> Callable[[], None]:
    def run() -> None:
        field.zero_grad(set_to_none=True)
        _loss(field, b).backward()

    return run


def _adam(field: SurfaceModel) -> Callable[[], None]:
    opt = torch.optim.Adam(field.parameters(), lr=1e-3, foreach=False)
    for p in field.parameters():
        p.grad = torch.zeros_like(p)

    def run() -> None:
        opt.step()

    return run


def _gradient_methods(res: int, n: int) -> dict[str, Callable[[], None]]:
    """SDF-grid value + spatial gradient + eikonal loss + backward, three ways."""
    grid = (torch.randn(1, 1, res, res, res) * 0.01).requires_grad_(True)
    x0 = torch.rand(n, 3) * 1.8 - 0.9  # grid_sample coordinates in [-1, 1]

    def closed_form() -> None:
        v, g = trilinear_with_grad(grid[0], (x0 + 1) * 0.5 * (res - 1))
        g = g[:, 0] * 0.5 * (res - 1)
        grid.grad = None
        (v.abs().mean() + (g.norm(dim=-1) - 1).square().mean()).backward()

    def autograd() -> None:
        x = x0.clone().requires_grad_(True)
        v = F.grid_sample(grid, x.view(1, n, 1, 1, 3), align_corners=True).view(n)
        (g,) = torch.autograd.grad(v.sum(), x, create_graph=True)
        grid.grad = None
        (v.abs().mean() + (g.norm(dim=-1) - 1).square().mean()).backward()

    def finite_diff() -> None:
        h = 1.0 / (res - 1)  # half a cell in [-1, 1] coordinates
        off = torch.tensor([[0, 0, 0], [h, 0, 0], [-h, 0, 0], [0, h, 0], [0, -h, 0], [0, 0, h],
                            [0, 0, -h]])
        xs = (x0[None] + off[:, None]).view(1, 7 * n, 1, 1, 3)
        y = F.grid_sample(grid, xs, align_corners=True).view(7, n)
        g = torch.stack([y[1] - y[2], y[3] - y[4], y[5] - y[6]], -1) / (2 * h)
        grid.grad = None
        (y[0].abs().mean() + (g.norm(dim=-1) - 1).square().mean()).backward()

    return {
        f"grad {res}^3, closed form (8 gathers)": closed_form,
        f"grad {res}^3, autograd through grid_sample": autograd,
        f"grad {res}^3, central FD at half a cell": finite_diff,
    }


CPU_TIMES: dict[tuple[str, str], list[float]] = {}


def _time(fns: dict[str, Callable[[], None]], repeats: int, what: str) -> dict[str, list[float]]:
    """Wall times per key, interleaved round-robin; process CPU times go to
    CPU_TIMES[(what, key)] (``what`` keeps a field's step and Adam timings apart)."""
    for fn in fns.values():  # warm-up
        fn()
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            times[k].append(time.perf_counter() - t0)
            CPU_TIMES.setdefault((what, k), []).append(time.process_time() - c0)
    return times


def _try_compile(field: GridSDFField, b) -> str:
    """Compile the grid field's sdf_and_grad + colour on CPU; report whether it pays off."""
    def fwd(x, d):
        s, g, f = field.sdf_and_grad(x, create_graph=True)
        return s, g, field.colour(x, d, g, f)

    def step(fn):
        def run():
            field.zero_grad(set_to_none=True)
            s, g, c = fn(b["x"], b["d"])
            (s.abs().mean() + c.mean() + (g.norm(dim=-1) - 1).square().mean()).backward()
        return run

    try:
        t0 = time.perf_counter()
        compiled = torch.compile(fwd)
        step(compiled)()
        t_compile = time.perf_counter() - t0
        t = _time({"eager": step(fwd), "compiled": step(compiled)}, 5, "compile")
    except Exception as e:  # noqa: BLE001 - report any backend failure as a result
        return f"torch.compile failed here: {type(e).__name__}: {str(e).splitlines()[0][:200]}"
    e, c = statistics.median(t["eager"]), statistics.median(t["compiled"])
    return (
        "sdf_and_grad + colour + backward (default grid field, 49k points): "
        f"eager {e * 1e3:.0f} ms, compiled {c * 1e3:.0f} ms (x{e / c:.2f}); "
        f"first compiled call incl. compilation {t_compile:.1f} s. Over the fast preset's 500 "
        f"steps that would save ~{(e - c) * 500:.0f} s of field work against the compilation "
        "(which is paid again for each grid resolution the coarse-to-fine schedule grows to); "
        "the trainer does not compile (svolsdf.optimize.trainer runs eager)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--mlp-repeats", type=int, default=3, help="repeats for the slow 8x256 MLP")
    ap.add_argument("--no-compile", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    machine = _machine()
    b = _batch()
    box = torch.tensor([[-1.2] * 3, [1.2] * 3])

    fields: dict[str, SurfaceModel] = {
        "grid, res 64 (default start; features 16/32/64 x 8)": GridSDFField(box),
        "grid, res 128 (features 32/64/128 x 8)": GridSDFField(box, GridFieldConfig(128)),
        "grid, res 160 (features 40/80/160 x 8)": GridSDFField(box, GridFieldConfig(160)),
        "grid, res 128 + SDF residual MLP": GridSDFField(
            box, GridFieldConfig(128, sdf_residual=True)
        ),
    }
    try:
        from svolsdf.field.volsdf import VolSDFField

        mlp: SurfaceModel = VolSDFField()
        mlp_name = "VolSDFField (paper: 8x256, PE 6, weight norm, IDR colour 4x256)"
    except ImportError:  # the paper field not there: a plain 8x256 MLP stand-in is not built
        sys.exit("svolsdf.field.volsdf.VolSDFField is required for the comparison")

    fast = {k: _fwd_bwd(f, b) for k, f in fields.items()}
    t_fast = _time(fast, args.repeats, "step")
    t_mlp = _time({mlp_name: _fwd_bwd(mlp, b)}, args.mlp_repeats, "step")
    t_adam = _time({k: _adam(f) for k, f in {**fields, mlp_name: mlp}.items()}, args.repeats,
                   "adam")
    t_grad = _time(_gradient_methods(128, RAYS * SAMPLES), args.repeats, "grad")
    compile_note = "not run (--no-compile)" if args.no_compile else _try_compile(
        GridSDFField(box), b
    )

    all_t = {**t_fast, **t_mlp}
    ref = statistics.median(t_mlp[mlp_name])
    ref_cpu = statistics.median(CPU_TIMES[("step", mlp_name)])
    rows = []
    for k, ts in all_t.items():
        m = statistics.median(ts)
        a = statistics.median(t_adam[k])
        n_par = sum(p.numel() for p in ({**fields, mlp_name: mlp}[k]).parameters())
        cpu = statistics.median(CPU_TIMES[("step", k)])
        rows.append(
            f"| {k} | {n_par / 1e6:.2f} | {m * 1e3:.0f} | {cpu * 1e3:.0f} | {a * 1e3:.0f} "
            f"| {ref / m:.1f}x | {ref_cpu / cpu:.1f}x |"
        )
    grad_rows = [
        f"| {k} | {statistics.median(ts) * 1e3:.1f} | "
        f"{statistics.median(CPU_TIMES[('grad', k)]) * 1e3:.1f} |"
        for k, ts in t_grad.items()
    ]
    load_end = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    cmd = "python benchmarks/field_speed.py " + " ".join(sys.argv[1:])
    text = f"""# Field speed: grid field vs the paper's VolSDF MLP

Command: `{cmd}`

{machine}
- load average at end: {load_end}

Workload: {RAYS} rays x {SAMPLES} samples = {RAYS * SAMPLES} points; one step = `sdf_and_grad`
(create_graph) + Laplace density + colour + alpha compositing + L1 RGB + 0.1 x eikonal on every
sample, then backward. Median of {args.repeats} ({args.mlp_repeats} for the MLP) interleaved runs
after one warm-up. "Adam" is one `optimizer.step()` over all of the field's parameters (dense).
CPU = process CPU time summed over threads (less sensitive than wall time to other processes on a
shared machine).

{HEADER}
|---|---|---|---|---|---|---|
{chr(10).join(rows)}

Spatial gradient of a 128^3 SDF grid with create_graph, {RAYS * SAMPLES} points, value + eikonal
loss + backward:

| method | wall ms | CPU ms |
|---|---|---|
{chr(10).join(grad_rows)}

torch.compile (CPU, inductor): {compile_note}
"""
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)


if __name__ == "__main__":
    main()
