"""Every experiment file shipped in experiments/ parses, and every job's config is valid (the
variants with the file's sizes and view sets), without running anything or needing the data."""

from __future__ import annotations

from pathlib import Path

import pytest

from svolsdf.commands.benchmark import benchmark_jobs, job_config
from svolsdf.commands.experiment import experiment_config

EXPERIMENTS = Path(__file__).resolve().parents[2] / "experiments"
FILES = sorted(EXPERIMENTS.glob("*.yaml"))


def test_the_papers_tables_each_have_a_file():
    assert {f.stem for f in FILES} >= {"ablation", "views", "resolution", "stages", "gce_q",
                                       "fusion_thresholds"}


@pytest.mark.parametrize("path", FILES, ids=[f.stem for f in FILES])
def test_experiment_file_is_valid(path, tmp_path):
    cfg = experiment_config(path, out=tmp_path / "out", data=tmp_path, check_scenes=False)
    jobs = benchmark_jobs(cfg)
    assert len(jobs) == len(cfg.scenes) * len(cfg.view_sets or [None]) * len(cfg.variants)
    for job in jobs:
        c = job_config(job)  # validated
        assert c.scene.path == str(job.scene)
    assert cfg.experiment["paper"], "say which table of the paper it reproduces"


def test_the_files_set_what_their_tables_vary(tmp_path):
    def configs(name):
        cfg = experiment_config(EXPERIMENTS / f"{name}.yaml", out=tmp_path, data=tmp_path,
                                check_scenes=False)
        return {j.variant: job_config(j) for j in benchmark_jobs(cfg)}

    ab = configs("ablation")
    assert {k: c.train.ablation for k, c in ab.items()} == {
        "full": None, "soft-consistency-only": "soft-consistency-only", "mse": "mse",
        "no-prob-volume": "no-prob-volume", "no-gce": "ce"}
    res = configs("resolution")
    assert {k: (tuple(c.scene.image_size), c.mvs.scale) for k, c in res.items()} == {
        "low": ((768, 576), 2.0), "mid": ((1152, 864), pytest.approx(4 / 3)),
        "high": ((1536, 1152), 1.0)}
    st = configs("stages")
    assert [(c.mvs.finer_stage_optimization, c.mvs.third_stage_optimization)
            for c in st.values()] == [(False, False), (True, False), (True, True)]
    assert [c.train.gce_q for c in configs("gce_q").values()] == [0.2, 0.35, 0.5, 0.65, 0.8]
    vw = experiment_config(EXPERIMENTS / "views.yaml", out=tmp_path, data=tmp_path,
                           check_scenes=False)
    assert [len(v) for v in vw.view_sets] == [3, 6, 9]


def test_the_blendedmvs_file_runs_each_scan_from_the_protocols_inputs(tmp_path):
    from svolsdf.evaluate.blendedmvs import protocol, protocol_scans

    cfg = experiment_config(EXPERIMENTS / "blendedmvs.yaml", out=tmp_path, data=tmp_path,
                            check_scenes=False)
    jobs = benchmark_jobs(cfg)
    scans = sorted({int(j.scene.name.removeprefix("bmvs_scan")) for j in jobs})
    assert scans == protocol_scans()
    for j in jobs:
        c = job_config(j)
        assert c.scene.views == protocol(int(j.scene.name.removeprefix("bmvs_scan")))["inputs"]
        assert c.field.background  # unbounded scenes: the paper's BlendedMVS setting
        assert c.train.mode == {"full": "svolsdf", "volsdf": "volsdf"}[j.variant]
