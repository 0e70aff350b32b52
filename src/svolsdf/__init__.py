"""svolsdf: S-VolSDF surface reconstruction from a few calibrated views, fast on a CPU."""

import os as _os

# OpenMP threads that spin while waiting make torch 4-7x slower per step as soon as any other
# process shares the cores (measured: 2.4 s vs 0.5 s per training step on 2 busy cores; see
# benchmarks/results/history/fast_preset.md). PASSIVE only matters before torch loads its OpenMP
# runtime, so it is set here, at the package's first import; a user's explicit setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# Large CPU tensors (the feature grids' gradients, the cost volumes) on transparent huge pages:
# torch's allocator madvises them only when this is set before it starts; a fresh 52 MB tensor
# filled once took 16 instead of 42 ms (benchmarks/results/history/train_step_speed.md, leads);
# values unchanged.
_os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

__version__ = "0.1.0"
