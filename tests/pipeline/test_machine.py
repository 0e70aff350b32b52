"""The machine a run uses (`svolsdf.pipeline.machine`): torch threads and peak memory."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from svolsdf.pipeline import peak_rss_gb


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="VmHWM is Linux's /proc")
def test_peak_memory_of_a_child_does_not_include_its_parents_peak():
    """timing.json's peak memory: a pipeline started by a process that once held ~400 MB more
    (a benchmark) must not report that peak as its own (ru_maxrss survives fork + exec)."""
    big = np.ones(400 * 2**20 // 8)  # 400 MiB, touched
    big += 1
    code = "from svolsdf.pipeline import peak_rss_gb; print(peak_rss_gb())"
    child = float(subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                                 text=True).stdout)
    assert peak_rss_gb() > child + 0.3
    del big


def test_set_threads(monkeypatch):
    """--threads N is used as given; 0 is the cores this process may run on, unless
    OMP_NUM_THREADS is set."""
    from svolsdf.pipeline import set_threads

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert set_threads(1) == 1 and torch.get_num_threads() == 1  # applied, not only returned
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
        if hasattr(os, "sched_getaffinity"):
            assert set_threads(0) == len(os.sched_getaffinity(0))
        torch.set_num_threads(1)
        monkeypatch.setenv("OMP_NUM_THREADS", "1")
        assert set_threads(0) == 1  # left to OMP_NUM_THREADS
    finally:
        torch.set_num_threads(before)
