"""Tests of svolsdf.commands.executors and the benchmark on them: the local and Ray executors
write the same table for the same jobs, a failed job is a row with its error, a rerun skips
finished jobs and resumes interrupted ones, a task whose worker dies is a row too.

Ray runs locally with 2 CPUs, started once for the module (the CLI test before it starts and
stops its own). Scenes are tiny synthetic ones; jobs are real mvs-only pipeline runs."""

from __future__ import annotations

import csv
import io
import json
import logging

import pytest
import ray  # the dev extra installs it, as the cluster extra

from svolsdf.cli import main
from svolsdf.commands.benchmark import ROW_FILE, BenchmarkConfig, run_benchmark
from svolsdf.commands.executors import (
    ExecutorConfig,
    check_executor,
    check_ray_address,
    run_local,
    run_ray,
)
from svolsdf.errors import InputError

# view 3's object mask is empty (the scene fixture): that job fails in the pipeline's scene
# checks, the other runs (view ids a scene lacks are refused before any job starts)
VIEW_SETS = [[0, 1, 2], [0, 1, 3]]
#: torch threads of every job under both executors: the same count, the same sums
THREADS = 1


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    import numpy as np
    from PIL import Image

    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    root = tmp_path_factory.mktemp("exec") / "synth_r"
    made = make_synthetic_scene(root, SynthConfig(views=4, width=96, height=72, gt_points=3000,
                                                  supersample=1, mesh_resolution=6.0))
    mask = made / "mask" / "003.png"
    Image.fromarray(np.zeros_like(np.asarray(Image.open(mask)))).save(mask)
    return made


@pytest.fixture(scope="module", autouse=True)
def workers_import_this_code():
    """Ray's workers are new processes: PYTHONPATH, which they inherit, points them at the
    svolsdf under test (not at another installed copy, whose rows would be compared)."""
    import os
    from pathlib import Path

    import svolsdf

    before = os.environ.get("PYTHONPATH")
    here = str(Path(svolsdf.__file__).parents[1])
    os.environ["PYTHONPATH"] = os.pathsep.join([here] + ([before] if before else []))
    yield
    if before is None:
        del os.environ["PYTHONPATH"]
    else:
        os.environ["PYTHONPATH"] = before


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray with 2 CPUs for the module's tests (the benchmark uses it, and leaves it
    running, when it finds it started)."""
    started = not ray.is_initialized()
    if started:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    if started:
        ray.shutdown()


def _cfg(scene, out, executor="local", **kw):
    return BenchmarkConfig(scenes=[scene], modes=["mvs-only"], out=out, view_sets=VIEW_SETS,
                           size=(96, 72), device="cpu", threads=THREADS,
                           executor=ExecutorConfig(name=executor, **kw))


#: how far two executors' floats may differ: the last digits of a float32 pipeline's sums can
#: still differ between processes (library builds, vector paths), never the numbers
REL = 1e-6


def _table_without_time(path, approx=False):
    """The CSV's cells without the time columns, numbers as floats (``approx``: as
    `pytest.approx` within `REL`, to compare another table with)."""
    rows = list(csv.reader(io.StringIO(path.read_text())))
    keep = [i for i, h in enumerate(rows[0]) if not h.endswith("_time_s")]

    def cell(text):
        try:
            x = float(text)
        except ValueError:
            return text
        return pytest.approx(x, rel=REL, abs=1e-12) if approx else x

    return [[cell(r[i]) for i in keep] for r in rows]


# --------------------------------------------------------------------------- no Ray needed
def test_executor_options_are_checked():
    with pytest.raises(InputError, match="unknown executor"):
        check_executor(ExecutorConfig(name="dask"))
    with pytest.raises(InputError, match="--address, --gpus-per-job: only with --executor ray"):
        check_executor(ExecutorConfig(address="auto", gpus_per_job=1))
    with pytest.raises(InputError, match="--cpus-per-job must be > 0"):
        check_executor(ExecutorConfig(name="ray", cpus_per_job=0))
    check_executor(ExecutorConfig(name="ray", address="auto", cpus_per_job=2, gpus_per_job=1))


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow  # Ray's own start-up and a bounded join: ~8 s
def test_a_wrong_ray_address_fails_within_30_s(scene, tmp_path, capsys):
    """Issue 38: ray.init retried a wrong --address for ~12 minutes. Now: exit 2 within 30 s,
    one line naming the address and what to do, before any job or folder."""
    import socket
    import time

    out = tmp_path / "b"
    for address, says in ((f"127.0.0.1:{_free_port()}", "nothing answers"),
                          ("WRONG", "no port"), ("http://head:6379", "not a Ray address")):
        t0 = time.monotonic()
        with pytest.raises(SystemExit) as e:
            main(["benchmark", "--scenes", str(scene), "--modes", "mvs-only", "-o", str(out),
                  "--executor", "ray", "--address", address])
        err = capsys.readouterr().err.strip()
        assert e.value.code == 2 and time.monotonic() - t0 < 30, err
        assert len(err.splitlines()) == 1 and f"--address {address}" in err and says in err
        assert "leave --address out" in err or "give host:port" in err, err
        assert not out.exists()
    # a port that answers but is not Ray's: the bounded join gives up
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        address = f"127.0.0.1:{server.getsockname()[1]}"
        t0 = time.monotonic()
        with pytest.raises(InputError, match="answers but no Ray cluster"):
            check_ray_address(address, join_timeout=8)
        assert time.monotonic() - t0 < 30


def test_cuda_on_ray_needs_gpus_per_job(scene, tmp_path):
    cfg = _cfg(scene, tmp_path / "o", "ray")
    cfg.device = "cuda"
    with pytest.raises(InputError, match="needs --gpus-per-job > 0"):
        run_benchmark(cfg)
    assert not ray.is_initialized()


def test_every_job_carries_its_torch_thread_count(scene, tmp_path):
    """The job sets torch's threads itself (config ``threads``): on Ray the CPUs it reserves,
    not whatever OMP_NUM_THREADS the worker inherited; --threads the same under both executors.
    How many threads does not decide the row's key (as the device does not)."""
    from svolsdf.commands.benchmark import benchmark_jobs, job_config

    def threads(cfg):
        return {job_config(j).threads for j in benchmark_jobs(cfg)}

    ray_cfg = _cfg(scene, tmp_path, "ray", cpus_per_job=3.5)
    ray_cfg.threads = None
    local_cfg = _cfg(scene, tmp_path)
    local_cfg.threads = None
    assert threads(ray_cfg) == {3} and threads(local_cfg) == {0}  # 0: this process's cores
    ray_cfg.threads = local_cfg.threads = 2
    assert threads(ray_cfg) == threads(local_cfg) == {2}
    assert [j.key() for j in benchmark_jobs(ray_cfg)] == [
        j.key() for j in benchmark_jobs(_cfg(scene, tmp_path, "ray", cpus_per_job=3.5))]


def test_local_executor_runs_in_order():
    got = []
    run_local(lambda j: {"job": j * 10}, [1, 2, 3], lambda i, r: got.append((i, r)),
              progress=False)
    assert got == [(0, {"job": 10}), (1, {"job": 20}), (2, {"job": 30})]


# --------------------------------------------------------------------------- Ray
@pytest.mark.slow  # a local Ray: ~5-13 s each
def test_cli_ray_executor_starts_and_stops_a_local_ray(scene, tmp_path, capsys, caplog):
    """Without --address the command starts a local Ray and shuts it down at the end."""
    if ray.is_initialized():  # pragma: no cover - another module left one running
        pytest.skip("a Ray is already running in this process")
    out = tmp_path / "cli"
    with caplog.at_level(logging.INFO, logger="svolsdf"):
        main(["benchmark", "--scenes", str(scene), "--modes", "mvs-only", "-o", str(out),
              "--views", "0 1 2", "--size", "96x72", "--device", "cpu", "--executor", "ray",
              "--cpus-per-job", "1"])
    assert not ray.is_initialized()
    text = capsys.readouterr().out
    assert "| synth_r |" in text and "1 runs)" in text
    assert "with the ray executor (local Ray)" in caplog.text
    for f in ("benchmark.md", "benchmark.csv", "benchmark.json", "benchmark.png"):
        assert (out / f).is_file()
    (row,) = json.loads((out / "benchmark.json").read_text())
    assert row["status"] == "ok" and row["overall"] > 0 and row["views"] == [0, 1, 2]


@pytest.mark.slow  # a local Ray: ~5-13 s each
def test_ray_and_local_executors_write_the_same_table(scene, tmp_path, local_ray, caplog):
    with caplog.at_level(logging.INFO, logger="svolsdf"):
        rows_r = run_benchmark(_cfg(scene, tmp_path / "ray", "ray"), progress=False)
    assert "with the ray executor" in caplog.text
    rows_l = run_benchmark(_cfg(scene, tmp_path / "local"), progress=False)
    assert [(r["scene"], r["mode"], r["views"]) for r in rows_r] == [
        ("synth_r [0,1,2]", "mvs-only", [0, 1, 2]), ("synth_r [0,1,3]", "mvs-only", [0, 1, 3])]
    ok, bad = rows_r
    # the failed job is a row with its error; the other finished
    assert ok["status"] == "ok" and ok["overall"] > 0
    assert bad["status"].startswith("failed: ") and "mask of view 3 is empty" in bad["status"]
    assert bad["overall"] is None
    # the job set torch's threads itself, in the Ray worker as here
    assert ok["threads"] == rows_l[0]["threads"] == THREADS
    for r, l in zip(rows_r, rows_l, strict=True):
        assert r["status"] == l["status"]
        for k in ("accuracy", "completeness", "overall", "fscore"):
            if l[k] is None:  # a failed job scores nothing, under either executor
                assert r[k] is None, k
            else:
                assert r[k] == pytest.approx(l[k], rel=REL, abs=1e-12), k
    assert _table_without_time(tmp_path / "ray" / "benchmark.csv") == \
        _table_without_time(tmp_path / "local" / "benchmark.csv", approx=True)
    md = (tmp_path / "ray" / "benchmark.md").read_text()
    assert "| synth_r [0,1,2] |" in md and "- synth_r [0,1,3] / mvs-only: failed: " in md
    assert (tmp_path / "ray" / "benchmark.png").stat().st_size > 1000
    for sub in ("views-0-1-2", "views-0-1-3"):
        assert (tmp_path / "ray" / "synth_r" / sub / "mvs-only" / ROW_FILE).is_file()


@pytest.mark.slow  # a local Ray: ~5-13 s each
def test_rerun_skips_finished_jobs_and_resumes_interrupted_ones(scene, tmp_path, local_ray,
                                                                 caplog):
    out = tmp_path / "b"
    first = run_benchmark(_cfg(scene, out, "ray"), progress=False)
    ok_dir = out / "synth_r" / "views-0-1-2" / "mvs-only"
    bad_dir = out / "synth_r" / "views-0-1-3" / "mvs-only"
    row_time = (ok_dir / ROW_FILE).stat().st_mtime_ns
    bad_time = (bad_dir / ROW_FILE).stat().st_mtime_ns
    with caplog.at_level(logging.INFO, logger="svolsdf"):
        again = run_benchmark(_cfg(scene, out, "ray"), progress=False)
    assert again == first
    assert "1 of 2 job(s) finished before" in caplog.text
    assert (ok_dir / ROW_FILE).stat().st_mtime_ns == row_time  # not run again
    assert (bad_dir / ROW_FILE).stat().st_mtime_ns != bad_time  # a failed job is retried
    # an interrupted job (no row yet) resumes: its finished pipeline stages are reused
    (ok_dir / ROW_FILE).unlink()
    points_time = (ok_dir / "points.ply").stat().st_mtime_ns
    resumed = run_benchmark(_cfg(scene, out, "ray"), progress=False)
    assert (ok_dir / "points.ply").stat().st_mtime_ns == points_time
    assert resumed[0]["overall"] == pytest.approx(first[0]["overall"], rel=1e-12)
    # other settings are another job: it runs
    other = _cfg(scene, out, "ray")
    other.steps = 5
    other.view_sets = [[0, 1, 2], [0, 1, 3]]
    assert run_benchmark(other, progress=False)[0]["status"] == "ok"
    assert (ok_dir / ROW_FILE).stat().st_mtime_ns != row_time


@pytest.mark.slow  # a local Ray: ~5-13 s each
def test_a_task_whose_worker_dies_is_a_row(local_ray):
    def job(k):
        if k == 2:
            import os

            os._exit(3)  # the worker process dies: Ray reports it, no Python exception
        return {"k": k, "status": "ok"}

    got = {}
    run_ray(job, [1, 2, 3], lambda i, r: got.__setitem__(i, r), ExecutorConfig(name="ray"),
            on_error=lambda j, e: {"k": j, "status": f"failed: {type(e).__name__}"},
            progress=False)
    assert got[0] == {"k": 1, "status": "ok"} and got[2] == {"k": 3, "status": "ok"}
    assert got[1]["k"] == 2 and got[1]["status"].startswith("failed: ")


@pytest.mark.slow  # a local Ray: ~5-13 s each
def test_a_running_clusters_address_passes_the_check(local_ray):
    """The address check joins a real cluster (the module's local Ray, by its GCS address)."""
    check_ray_address(local_ray.get_runtime_context().gcs_address)
