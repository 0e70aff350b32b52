"""Where the jobs of ``svolsdf benchmark`` run: in this process, one after another (``local``),
or as Ray tasks on a local or remote Ray cluster (``ray``).

An executor takes a job function (one job -> one result row, never raising: the function turns
its own errors into rows) and the jobs, and calls ``on_row(index, row)`` as each job finishes,
with a progress bar over the jobs. The Ray executor runs the same function in Ray workers, so
both produce the same rows; a job whose worker dies (out of memory, a lost node) becomes a row
made by ``on_error(job, exception)``.

Ray is optional (``pip install "svolsdf[cluster]"``) and imported only by `run_ray`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from svolsdf.errors import InputError, raise_if_interrupted
from svolsdf.runtime import CPU_ENV

__all__ = ["EXECUTORS", "ExecutorConfig", "check_executor", "check_ray_address", "job_threads",
           "run_jobs", "run_local", "run_ray"]

log = logging.getLogger(__name__)

EXECUTORS = ("local", "ray")
"""Executor names of ``svolsdf benchmark --executor``."""


@dataclass
class ExecutorConfig:
    """Where and with what resources the jobs run."""

    name: str = "local"
    """local (this process, one job after another) or ray (one Ray task per job)."""
    address: str | None = None
    """Ray cluster to join (``ray://head:10001``, ``head:6379`` or ``auto``); None starts a
    local Ray with this machine's CPUs (and shuts it down at the end). Ray only."""
    cpus_per_job: float = 1.0
    """CPUs Ray reserves for each job; the job's torch uses that many threads (rounded down, at
    least 1: `job_threads`) unless the benchmark gives its own count. Ray only."""
    gpus_per_job: float = 0.0
    """GPUs Ray reserves for each job (Ray sets CUDA_VISIBLE_DEVICES to them, so ``--device
    cuda`` uses the job's own GPU). Ray only."""
    local_cpus: int | None = None
    """CPUs of the local Ray started without ``address`` (None: all of this machine's)."""


def job_threads(cfg: ExecutorConfig) -> int:
    """The torch threads a job uses on this executor when the benchmark names none: on Ray the
    CPUs each task reserves (``cpus_per_job`` rounded down, at least 1), set in the worker by
    the job itself rather than left to the OMP_NUM_THREADS the worker inherits; locally 0, the
    pipeline's rule (this process's cores: `svolsdf.pipeline.set_threads`).

    A job's numbers depend on the count in their last digits (torch splits its sums over the
    threads), so the same count under both executors gives the same rows."""
    if cfg.name == "ray":
        return max(1, int(cfg.cpus_per_job))
    return 0


def check_executor(cfg: ExecutorConfig) -> None:
    """Raise `InputError` for an unknown executor, Ray options without Ray, bad resources, or
    ``--executor ray`` where Ray is not installed."""
    if cfg.name not in EXECUTORS:
        raise InputError(f"--executor: unknown executor {cfg.name!r} (choose from "
                         f"{', '.join(EXECUTORS)})")
    if cfg.name == "local":
        given = [o for o, v in (("--address", cfg.address is not None),
                                ("--cpus-per-job", cfg.cpus_per_job != 1.0),
                                ("--gpus-per-job", cfg.gpus_per_job != 0.0)) if v]
        if given:
            raise InputError(f"{', '.join(given)}: only with --executor ray (the local executor "
                             "runs the jobs in this process)")
    if not cfg.cpus_per_job > 0:
        raise InputError(f"--cpus-per-job must be > 0, got {cfg.cpus_per_job}")
    if cfg.gpus_per_job < 0:
        raise InputError(f"--gpus-per-job must be >= 0, got {cfg.gpus_per_job}")
    if cfg.name == "ray":
        _import_ray()
        if cfg.address is not None:
            check_ray_address(cfg.address)


def check_ray_address(address: str, timeout: float = 5.0, join_timeout: float = 20.0) -> None:
    """Raise `InputError` unless a Ray cluster answers at ``address``: ``ray.init`` retries a
    wrong one for about 12 minutes, silently. First a TCP connection to host:port (``timeout``
    seconds), then ``ray.init`` in a child process, stopped after ``join_timeout`` seconds (a
    port that answers need not be Ray's). ``auto`` (Ray finds the cluster this node joined)
    is not checked.

    Args:
        address: ``ray://host:port``, ``host:port`` or ``auto``.
    """
    import socket
    import subprocess
    import sys
    from urllib.parse import urlsplit

    if address in ("auto", "local"):
        return
    what = "give host:port (the head's GCS, e.g. head:6379), ray://host:port or auto"
    try:
        parts = urlsplit(address if "://" in address else f"//{address}")
        scheme, host, port = parts.scheme, parts.hostname, parts.port
    except ValueError:  # a port that is not a number
        scheme, host, port = "", None, None
    if not host or scheme not in ("", "ray"):
        raise InputError(f"--address {address}: not a Ray address; {what}")
    if port is None:
        raise InputError(f"--address {address}: no port; {what}")
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except OSError as e:
        reason = "no answer" if isinstance(e, TimeoutError) else (e.strerror or str(e))
        raise InputError(f"--address {address}: nothing answers at {host}:{port} ({reason} "
                         f"within {timeout:g} s); start the cluster there (`ray start --head`), "
                         "check the address with `ray status` on its head node, or leave "
                         "--address out to start a local Ray") from None
    code = (f"import ray; ray.init(address={address!r}, log_to_driver=False, "
            "logging_level='ERROR'); ray.shutdown()")
    try:
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           timeout=join_timeout)
    except subprocess.TimeoutExpired:
        raise InputError(f"--address {address}: {host}:{port} answers but no Ray cluster let "
                         f"this node join within {join_timeout:g} s; give the head's GCS "
                         "address (`ray status` on the head node prints it, e.g. head:6379; "
                         "ray://head:10001 for Ray Client) or leave --address out to start a "
                         "local Ray") from None
    if r.returncode != 0:
        last = (r.stderr.strip().splitlines() or ["ray.init failed"])[-1]
        raise InputError(f"--address {address}: could not join a Ray cluster there ({last}); "
                         "check `ray status` on that node, or leave --address out to start a "
                         "local Ray")


def _progress(total: int, done: int, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=done, desc="benchmark jobs", unit="job",
                disable=not enabled)


def run_local(fn: Callable[[Any], dict], jobs: Sequence, on_row: Callable[[int, dict], None],
              progress: bool = True, done: int = 0) -> None:
    """Run ``fn(job)`` for each job in this process, in order.

    Args:
        fn: the job function; it returns a row and does not raise.
        jobs: the jobs to run.
        on_row: called with (index into ``jobs``, row) after each job.
        progress: show a progress bar over the jobs.
        done: jobs finished before (skipped), counted in the bar's total.
    """
    with _progress(len(jobs) + done, done, progress) as bar:
        for i, job in enumerate(jobs):
            on_row(i, fn(job))
            bar.update(1)


def _import_ray():
    try:
        import ray
    except ImportError:
        raise InputError("--executor ray needs Ray: pip install \"svolsdf[cluster]\" (or "
                         "pip install ray)") from None
    return ray


def run_ray(fn: Callable[[Any], dict], jobs: Sequence, on_row: Callable[[int, dict], None],
            cfg: ExecutorConfig, on_error: Callable[[Any, BaseException], dict],
            progress: bool = True, done: int = 0) -> None:
    """Run ``fn(job)`` for each job as a Ray task; ``on_row`` as each one finishes.

    Joins the cluster at ``cfg.address``, or starts a local Ray (``cfg.local_cpus`` CPUs) when
    there is none; uses the Ray this process already started when there is one. Shuts down only
    what it started. Each task reserves ``cfg.cpus_per_job`` CPUs and ``cfg.gpus_per_job`` GPUs;
    Ray runs as many at once as the cluster's resources allow.

    Args:
        fn: the job function (importable by the workers: svolsdf installed on every node).
        jobs: the jobs to run.
        on_row: called with (index into ``jobs``, row) as each job finishes, in finishing order.
        cfg: `ExecutorConfig`.
        on_error: makes the row of a job whose task failed in Ray itself (worker died, node
            lost) from the job and the exception.
        progress: show a progress bar over the jobs.
        done: jobs finished before (skipped), counted in the bar's total.
    """
    ray = _import_ray()
    started = False
    if not ray.is_initialized():
        if cfg.address is not None:
            log.info("joining the Ray cluster at %s", cfg.address)
            try:
                ray.init(address=cfg.address, log_to_driver=False)
            except (ConnectionError, RuntimeError, ValueError) as e:
                raise InputError(f"--address {cfg.address}: could not join a Ray cluster there "
                                 f"({str(e).strip().splitlines()[0] if str(e) else e!r}); "
                                 "check `ray status` on that node, or leave --address out to "
                                 "start a local Ray") from None
        else:
            ray.init(num_cpus=cfg.local_cpus, include_dashboard=False, log_to_driver=False)
        started = True
    try:
        res = ray.cluster_resources()
        log.info("Ray: %g CPUs, %g GPUs in the cluster; %g CPUs and %g GPUs per job",
                 res.get("CPU", 0), res.get("GPU", 0), cfg.cpus_per_job, cfg.gpus_per_job)
        if cfg.gpus_per_job > res.get("GPU", 0) or cfg.cpus_per_job > res.get("CPU", 0):
            log.warning("a job needs %g CPUs and %g GPUs but the cluster has %g and %g: Ray waits "
                        "until a node that big joins", cfg.cpus_per_job, cfg.gpus_per_job,
                        res.get("CPU", 0), res.get("GPU", 0))
        # one retry when a worker or its node is lost; the job resumes its finished stages
        # the workers load torch with svolsdf's settings (`svolsdf.runtime.CPU_ENV`)
        task = ray.remote(num_cpus=cfg.cpus_per_job, num_gpus=cfg.gpus_per_job,
                          max_retries=1, runtime_env={"env_vars": {
                              k: os.environ.get(k, v) for k, v in CPU_ENV.items()}})(fn)
        pending = {task.remote(job): i for i, job in enumerate(jobs)}
        with _progress(len(jobs) + done, done, progress) as bar:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                for ref in ready:
                    i = pending.pop(ref)
                    try:
                        row = ray.get(ref)
                    except Exception as e:  # the task itself failed: one row, the others go on
                        raise_if_interrupted()
                        log.error("job %d failed in Ray: %s", i, e)
                        row = on_error(jobs[i], e)
                    on_row(i, row)
                    bar.update(1)
    finally:
        if started:
            ray.shutdown()


def run_jobs(fn: Callable[[Any], dict], jobs: Sequence, on_row: Callable[[int, dict], None],
             cfg: ExecutorConfig, on_error: Callable[[Any, BaseException], dict],
             progress: bool = True, done: int = 0) -> None:
    """Run the jobs on the executor ``cfg.name`` (`run_local` or `run_ray`)."""
    check_executor(cfg)
    log.info("running %d job(s) with the %s executor%s", len(jobs), cfg.name,
             "" if cfg.name == "local" else
             f" ({'cluster ' + cfg.address if cfg.address else 'local Ray'})")
    if not jobs:
        return
    if cfg.name == "ray":
        run_ray(fn, jobs, on_row, cfg, on_error, progress=progress, done=done)
    else:
        run_local(fn, jobs, on_row, progress=progress, done=done)
