"""Machine description shared by the benchmark scripts (results files name the machine)."""

from __future__ import annotations

import platform
import resource

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
    """Peak resident memory of this process in GiB (Linux ru_maxrss is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
