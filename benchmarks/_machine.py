"""Machine description shared by the benchmark scripts (results files name the machine)."""

from __future__ import annotations

import platform
from collections.abc import Callable
from pathlib import Path

__all__ = ["copy_run", "cpu_name", "git_commit", "peak_rss_gb", "public_argv", "write_results"]


def cpu_name() -> str:
    """The CPU model from /proc/cpuinfo, else `platform.processor()`, else "unknown"."""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def git_commit() -> str:
    """The repository's short HEAD commit, or "unknown" outside a git checkout."""
    import subprocess

    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"],
                              cwd=Path(__file__).resolve().parents[1], check=True,
                              capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def peak_rss_gb() -> float:
    """Peak resident memory of this process in GiB (svolsdf.pipeline.peak_rss_gb: VmHWM, which,
    unlike ru_maxrss, does not carry a parent's peak into a child process)."""
    from svolsdf.pipeline import peak_rss_gb as _peak

    return _peak()


def public_argv(argv: list[str]) -> str:
    """A command line as a results file prints it: a path inside the repository relative to
    it, any other absolute path as DATA/<its name> (also in NAME=PATH), so no machine's
    folders are committed."""
    repo = Path(__file__).resolve().parents[1]

    def path(p: str) -> str:
        q = Path(p).resolve()
        return str(q.relative_to(repo)) if q.is_relative_to(repo) else f"DATA/{q.name}"

    def one(a: str) -> str:
        name, eq, rest = a.partition("=")
        if eq and rest.startswith("/") and not name.startswith("-"):
            return f"{name}={path(rest)}"
        return path(a) if a.startswith("/") else a

    return " ".join(one(a) for a in argv)


def write_results(path: Path, text: str) -> None:
    """Write a results file: the generated ``text``, then the hand-written notes the file already
    has (everything from its first "## Notes" heading on), which a rerun keeps."""
    notes = ""
    if path.is_file():
        old = path.read_text()
        i = old.find("\n## Notes")
        notes = old[i:] if i >= 0 else ""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text + notes)


def copy_run(src: Path, dst: Path, edit: Callable) -> Path:
    """A fresh copy of the run folder ``src`` at ``dst`` whose config.yaml ``edit(cfg)`` changes
    in place; `svolsdf reconstruct --config dst/config.yaml -o dst` then reruns only the stages
    whose keys the change touches. Returns ``dst``."""
    import shutil

    from svolsdf.config import load_config, save_config

    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    cfg = load_config(dst / "config.yaml")
    edit(cfg)
    save_config(cfg, dst / "config.yaml")
    return dst
