"""svolsdf.pipeline: the reconstruction's stages in order (`Pipeline`), the run folder
(`RunDir`), stage keys (`stage_keys`), builders from the config to components
(`svolsdf.pipeline.builders`) and a finished run opened for the commands (`Run.open`).

Modules: ``runner`` (the `Pipeline`: order, reuse, marks, timing, lock, log, interrupts),
``stages`` (one declared `Stage` per file), ``loaded_run`` (`Run`), ``rundir`` (`RunDir`, the run
folder's writing side, atomic saves), ``records`` (a stage's marker and files), ``keys`` (from
the stages' declarations; ``legacy_keys``, the earlier formula, recognises old run folders),
``options`` (what a config turns on), ``builders``, ``views`` (input and test views),
``machine`` (device, threads, memory), and the stage helpers ``fusion_stage``, ``mesh``,
``finer`` and ``previews``.
"""

from svolsdf.pipeline.keys import STAGES, stage_keys
from svolsdf.pipeline.loaded_run import Run
from svolsdf.pipeline.machine import peak_rss_gb, resolve_device, set_threads
from svolsdf.pipeline.rundir import RunDir
from svolsdf.pipeline.runner import Pipeline
from svolsdf.pipeline.views import auto_views, default_views, test_views

__all__ = ["Pipeline", "Run", "RunDir", "STAGES", "auto_views", "default_views", "peak_rss_gb",
           "resolve_device", "set_threads", "stage_keys", "test_views"]
