"""The machine a run uses: its device, torch threads and peak memory."""

from __future__ import annotations

import os
import re
import resource
import sys

import torch

from svolsdf.errors import InputError

__all__ = ["peak_rss_gb", "resolve_device", "set_threads"]


def resolve_device(name: str) -> torch.device:
    """The torch device of ``--device`` auto (CUDA when available), cpu, cuda or cuda:N.

    Raises:
        InputError: cuda without a CUDA device, cuda:N beyond the devices there are, or an
            unknown name.
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    m = re.fullmatch(r"cpu|cuda(?::(\d+))?", str(name))
    if m is None:
        raise InputError(f"unknown device {name!r} (auto, cpu, cuda or cuda:N)")
    if name.startswith("cuda"):
        n = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if n == 0:
            raise InputError(f"--device {name}: no CUDA device is available")
        if m.group(1) is not None and int(m.group(1)) >= n:
            raise InputError(f"--device {name}: there {'is' if n == 1 else 'are'} {n} CUDA "
                             f"device{'s' if n > 1 else ''} (cuda:0 .. cuda:{n - 1})")
    return torch.device(name)


def peak_rss_gb() -> float:
    """Peak resident memory of this process in GiB.

    Linux: the ``VmHWM`` line of /proc/self/status, which belongs to this process's own address
    space. ``ru_maxrss`` is not used there: it survives fork + exec, so a pipeline started by a
    process that once held 3 GB would report 3 GB (benchmarks start the pipeline that way).
    Elsewhere: ``ru_maxrss`` (KiB on Linux and the BSDs, bytes on macOS).
    """
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024**2  # kB
    except OSError:
        pass
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 1024**3 if sys.platform == "darwin" else rss / 1024**2


def set_threads(n: int = 0) -> int:
    """Set torch's intra-op threads and return the number in use.

    ``n`` > 0 is used as given. ``n`` = 0 means the number of cores this process may run on,
    ``os.sched_getaffinity`` (it sees a container's cpuset or `taskset`, where ``os.cpu_count``
    reports the whole host; a CPU quota it does not see: pass ``n`` then). With ``n`` = 0 and
    OMP_NUM_THREADS set, torch keeps what that variable chose.
    """
    if n <= 0:
        if os.environ.get("OMP_NUM_THREADS"):
            return torch.get_num_threads()
        try:
            n = len(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            n = os.cpu_count() or 1
    if n != torch.get_num_threads():
        torch.set_num_threads(n)
    return torch.get_num_threads()
