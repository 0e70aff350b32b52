"""The ``svolsdf.*`` profiler labels of a training step (read by benchmarks/profile_fast.py): they
appear, nested as documented, in a profile of one tiny fast-preset step, and a profiled step
computes exactly what an unprofiled one does."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch
from test_sync_free import _trainer
from torch.profiler import ProfilerActivity, profile

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "profile_fast.py"


def _profile_fast():
    spec = importlib.util.spec_from_file_location("profile_fast", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_labels_appear_nested_in_a_profiled_step():
    pf = _profile_fast()
    t = _trainer("fast")  # grid field, MVS-guided sampler, MVS prior
    t.train_step()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        t.train_step()
    times = pf.label_times(prof.events())
    step = ("train_step",)
    for part in ("rays", "sampling", "render", "prior_lookup", "losses", "eikonal", "backward",
                 "clip", "optimizer"):
        assert step + (part,) in times, part
    for path in (("sampling", "sdf_lookup"), ("sampling", "prior_lookup"),
                 ("sampling", "composite"), ("render", "sdf_lookup"),
                 ("render", "feature_lookup"), ("render", "colour_mlp"),
                 ("render", "composite"), ("eikonal", "sdf_lookup")):
        assert step + path in times, path
    assert all(len(k) > 1 and k[0] == "train_step" for k in times if k != step)
    # the labelled parts fit inside the step, and the table's rows add up to it
    assert sum(v for k, v in times.items() if len(k) == 2) <= times[step] * 1.001
    rows = pf.part_rows(times)
    top = [r for r in rows if len(r) == 2]
    assert abs(sum(pf.row_time(times, r) for r in top) - times[step]) < 1e-6 * times[step] + 1
    comps = pf.component_times(times)
    assert comps["sdf_lookup"] == sum(v for k, v in times.items() if k[-1] == "sdf_lookup")
    assert pf.backward_node_times(prof.events())  # the backward pass's autograd nodes


def test_a_profiled_step_computes_the_same():
    a = _trainer("fast")  # (seeds the global generator the eikonal points come from)
    ta = [a.train_step() for _ in range(3)]
    b = _trainer("fast")
    with profile(activities=[ProfilerActivity.CPU]):
        tb = [b.train_step() for _ in range(3)]
    for x, y in zip(ta, tb, strict=True):
        assert x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x)
    for (n, p), (_, q) in zip(a.model.named_parameters(), b.model.named_parameters(),
                              strict=True):
        assert torch.equal(p, q), n
