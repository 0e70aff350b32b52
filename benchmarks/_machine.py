"""Machine description shared by the benchmark scripts (results files name the machine)."""

from __future__ import annotations

import platform

__all__ = ["cpu_name", "peak_rss_gb"]


def cpu_name() -> str:
    """The CPU model from /proc/cpuinfo, else `platform.processor()`, else "unknown"."""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def peak_rss_gb() -> float:
    """Peak resident memory of this process in GiB (svolsdf.pipeline.peak_rss_gb: VmHWM, which,
    unlike ru_maxrss, does not carry a parent's peak into a child process)."""
    from svolsdf.pipeline import peak_rss_gb as _peak

    return _peak()
