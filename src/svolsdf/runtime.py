"""What a process that runs svolsdf's work sets before torch starts: `CPU_ENV`, set by the
command line (`svolsdf.cli`) before its first import of torch and passed to the benchmark's Ray
workers. Importing the package sets nothing: a program that imports svolsdf as a library keeps
its own environment (and may call `set_cpu_env` itself, first thing)."""

from __future__ import annotations

import os

__all__ = ["CPU_ENV", "set_cpu_env"]

#: environment variables torch reads once, when it loads, and their values for svolsdf's work:
#:
#: - OMP_WAIT_POLICY=PASSIVE: OpenMP threads that spin while waiting make torch 4-7x slower per
#:   step as soon as any other process shares the cores (2.4 s vs 0.5 s per training step on 2
#:   busy cores, benchmarks/results/history/fast_preset.md);
#: - THP_MEM_ALLOC_ENABLE=1: large CPU tensors (the feature grids' gradients, the cost volumes) on
#:   transparent huge pages; a fresh 52 MB tensor filled once took 16 instead of 42 ms
#:   (benchmarks/results/history/train_step_speed.md, leads); values unchanged.
CPU_ENV: dict[str, str] = {"OMP_WAIT_POLICY": "PASSIVE", "THP_MEM_ALLOC_ENABLE": "1"}


def set_cpu_env() -> None:
    """Set `CPU_ENV` in this process's environment where the user has not set a variable
    (their setting wins). Effective only before torch is first imported."""
    for k, v in CPU_ENV.items():
        os.environ.setdefault(k, v)
