"""The reconstruction pipeline: every stage in order, each result kept on disk, with resume.

Stages (ARCHITECTURE.md "Data flow"; METHOD.md 0 and 6):

1. ``mvs1``: stage-1 probability volumes of the input views (OUT/mvs/stage1/<id>.npz).
2. ``field``: the S-VolSDF optimization (OUT/field/model.pt; checkpoints in OUT/field/).
3. ``guide``: rendered z-depth of the input views, which replaces the stage-1 depth
   (METHOD.md 6.1; OUT/field/render_depth/<id>.npy).
4. ``mvs23``: stages 2 and 3 centred on that depth (OUT/mvs/stage{2,3}, OUT/depth/<id>.npy).
5. ``unguided`` (``output.fusion_unguided``, the fast preset's; not in the paper): stages 2 and 3
   centred on the stage-1 depth, as the backbone alone runs them (OUT/unguided/depth/<id>.npy);
   fusion takes them as every view's second depth hypothesis.
6. ``fusion``: geometric-consistency filtering and fusion (OUT/points.ply, METHOD.md 6.3).
7. ``mesh``: marching cubes of the SDF (OUT/mesh.ply).

A stage is skipped on a rerun when its marker in OUT/stages.json carries the same config hash;
a changed config reruns that stage and everything after it. The optimization resumes from its
last checkpoint after a kill. All files are written atomically.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import resource
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from svolsdf.config import DTU_EXCLUDED_IDS, DTU_TRAIN_IDS, Config, save_config, validate_config
from svolsdf.errors import InputError, RunInterrupted
from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.scene.scene import Scene

__all__ = ["Pipeline", "auto_views", "default_views", "test_views", "working_size",
           "resolve_device", "peak_rss_gb", "set_threads"]

log = logging.getLogger(__name__)

STAGES = ("mvs1", "field", "guide", "mvs23", "unguided", "fusion", "mesh")


def _load_maps(files: dict[int, Path]) -> dict[int, torch.Tensor]:
    """{view: (H, W) map} from .npy files."""
    return {v: torch.from_numpy(np.load(f)) for v, f in files.items()}


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split()) or e.__class__.__name__
    return text if len(text) <= 200 else text[:197] + "..."


# --------------------------------------------------------------------------- scene choices
def working_size(width: int, height: int, max_width: int = 768) -> tuple[int, int]:
    """Default working size: ``max_width`` wide (never upsampled), height a multiple of 8."""
    if width <= max_width:
        return width - width % 8, height - height % 8
    s = max_width / width
    return max_width, max(8, int(round(height * s / 8)) * 8)


def _is_dtu49(scene: Scene) -> bool:
    return bool(scene.extras.get("dtu")) and set(range(49)) <= set(scene.view_ids)


def default_views(scene: Scene, n: int = 3) -> list[int]:
    """Input views: DTU's protocol (METHOD.md 1.4) on DTU scans, else a central view and its
    n - 1 best source views (by the scene's pairs)."""
    if _is_dtu49(scene):
        return DTU_TRAIN_IDS[:n]
    cams = scene.cameras
    dirs = cams.view_dirs
    mean = dirs.mean(0)
    centre = int(torch.argmax(dirs @ mean))
    ref = scene.view_ids[centre]
    return [ref] + scene.source_views(ref)[: n - 1]


def auto_views(scene: Scene, n: int = 3) -> list[int]:
    """``--views auto``: n views with good overlap and baselines on any calibrated scene
    (`svolsdf.scene.pairs.select_views`), from the views' shared sparse points (COLMAP scenes)
    or points sampled in the object sphere, seen from the object centre."""
    from svolsdf.scene.loaders import read_source
    from svolsdf.scene.pairs import (
        covisibility,
        sample_sphere_points,
        select_views,
        visible_in_views,
    )

    src = read_source(scene.path, lighting=scene.extras.get("lighting", 3))
    cams = scene.cameras
    if src.points is not None and src.visibility is not None and len(src.points) > 0 and \
            list(src.view_ids) == list(scene.view_ids):
        vis = src.visibility
    else:
        vis = visible_in_views(cams, sample_sphere_points(scene.normalization, 4096))
    pos = select_views(covisibility(vis), cams.centers, scene.normalization.center.reshape(3), n)
    return [scene.view_ids[i] for i in pos]


def test_views(scene: Scene, inputs: list[int]) -> list[int]:
    """Held-out views: DTU's 15-view exclusion protocol on DTU scans, else every other view."""
    if _is_dtu49(scene):
        return [v for v in range(49) if v not in DTU_TRAIN_IDS and v not in DTU_EXCLUDED_IDS]
    return [v for v in scene.view_ids if v not in inputs]


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is available")
    if name not in ("cpu", "cuda"):
        raise InputError(f"unknown device {name!r} (auto, cpu or cuda)")
    return torch.device(name)


# OutputConfig fusion options that enter the fusion stage's key only when not None: they came
# after finished runs, which keep their keys (and their fused points) while the option is unset
_FUSION_KEYS_WHEN_SET = ("fusion_network", "fusion_network_weights", "fusion_unguided_dilation")


def _hash(*parts) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:12]


@contextlib.contextmanager
def _folder_lock(out: Path):
    """Hold an exclusive lock on OUT/.svolsdf.lock for a run.

    Two runs writing one output folder would mix their stages. The lock is an advisory ``flock``
    that the operating system drops when the process ends, so a killed run never leaves a stale
    lock behind. Where ``fcntl`` does not exist (Windows) runs are not locked.

    Raises:
        InputError: another process holds the folder; the message names the folder and its pid.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    path = out / ".svolsdf.lock"
    f = open(path, "a+")  # noqa: SIM115 - held for the whole run
    try:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.seek(0)
            pid = f.read().strip() or "?"
            raise InputError(f"{out}: another svolsdf run (pid {pid}) is writing this folder; "
                             "wait for it or choose another output folder") from None
        f.seek(0)
        f.truncate()
        f.write(str(os.getpid()))
        f.flush()
        yield
    finally:
        f.close()


def _save_npy(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npy")
    np.save(tmp, arr)
    os.replace(tmp, path)


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


# --------------------------------------------------------------------------- pipeline
class Pipeline:
    """Runs a `Config` into an output folder.

    Args:
        cfg: the run's configuration (``cfg.scene.path`` must be set).
        out: the output folder (created; must not be a file).
        progress: show progress bars.
    """

    def __init__(self, cfg: Config, out: str | Path, progress: bool = True):
        self.cfg = validate_config(cfg)  # a bad value fails here, before any stage
        self.out = Path(out)
        if self.out.exists() and not self.out.is_dir():
            raise InputError(f"{self.out}: output path exists and is not a folder")
        if not cfg.scene.path:
            raise InputError("no scene given (scene.path is empty)")
        self.progress = progress
        self.device = resolve_device(cfg.device)
        self.timing: dict[str, dict] = {}
        self._scene: Scene | None = None
        self._volumes1: list[ProbabilityVolume] | None = None
        self._reg1: tuple | None = None  # (volumes1, their regressed copies)
        self._model = None
        self._net: tuple | None = None  # (its config, the fusion network's backbone)
        self._stage = "setup"  # the stage run() is in, for the message of an interrupt
        self._trainer = None  # the field stage's Trainer while it runs (its step, ditto)
        self._warned_state = False

    # ------------------------------------------------------------------ bookkeeping
    def _state_path(self) -> Path:
        return self.out / "stages.json"

    def _state(self) -> dict:
        p = self._state_path()
        if not p.is_file():
            return {}
        try:
            st = json.loads(p.read_text())
            if isinstance(st, dict):
                return st
        except (ValueError, UnicodeDecodeError):
            pass
        if not self._warned_state:  # _mark replaces it
            log.warning("%s is unreadable; no stage counts as finished", p)
            self._warned_state = True
        return {}

    def _unmark_from(self, stage: str) -> None:
        """Forget ``stage`` and every later stage (their files no longer follow from earlier
        ones, e.g. after an unreadable file of ``stage`` was discarded)."""
        later = STAGES[STAGES.index(stage):]
        st = {k: v for k, v in self._state().items() if k not in later}
        tmp = self._state_path().with_suffix(".tmp")
        tmp.write_text(json.dumps(st, indent=1))
        os.replace(tmp, self._state_path())

    def _reuse(self, stage: str, read, discard: Path | None = None):
        """``read()`` the files of a finished (or, for the field, started) ``stage``; None when
        one is unreadable: a warning says so, ``discard`` is deleted, and the stage and the later
        ones run again."""
        try:
            return read()
        except Exception as e:  # a truncated or corrupt file: numpy, zip or pickle errors
            what = f"{discard} is" if discard is not None else "a file of the stage is"
            log.warning("%s: %s unreadable (%s); discarding it and running the stage %s again",
                        self.out, what, _one_line(e), stage)
            if discard is not None:
                discard.unlink(missing_ok=True)
            self._unmark_from(stage)
            return None

    def _mark(self, stage: str, key: str) -> None:
        st = self._state()
        st[stage] = key
        tmp = self._state_path().with_suffix(".tmp")
        tmp.write_text(json.dumps(st, indent=1))
        os.replace(tmp, self._state_path())

    def _keys(self) -> dict[str, str]:
        from svolsdf import __version__
        from svolsdf.mvs.backbone import backbone_signature

        c = asdict(self.cfg)
        # the backbone's full config (defaults included) and weights file: a changed default
        # or a replaced checkpoint must not reuse cached volumes
        sig = backbone_signature(self.cfg.mvs.backbone, weights=self.cfg.mvs.weights,
                                 **self._backbone_kwargs())
        # mvs.guide_network (the adapters' guide_init) changes only the guided stages 2-3: it
        # enters their key alone, and only for the backbones that take it
        guide_init = sig["config"].pop("guide_init", None)
        # native_images enters only when set: the default (the released upsampling) keeps the
        # keys run folders had before the option existed
        if not sig["config"].get("native_images", True):
            del sig["config"]["native_images"]
        c["mvs"] = {**{k: v for k, v in c["mvs"].items() if k != "guide_network"},
                    "signature": sig}
        # how the views were picked does not matter once they are known (self.views), and run
        # folders from before the option keep their keys
        c["scene"].pop("view_selection", None)
        # every key chains from this one: a new release recomputes rather than mixing versions
        k_mvs1 = _hash(c["scene"], c["mvs"], self.views, __version__)
        if not self._grid_from_sphere():
            # the sphere start's settings (issue 28) do not act on a field started from MVS:
            # they stay out of its key, and lr_sdf_sphere keeps the value it had in every key
            # before then, so such run folders keep their finished stages
            for k in ("sphere_radius", "sphere_start_resolution"):
                c["field"].pop(k)
            c["train"].pop("grid_eikonal_weight")
            c["train"]["lr_sdf_sphere"] = 1e-3
        k_field = _hash(k_mvs1, c["field"], c["train"], c["preset"])
        # guide_mask_dilation enters only when set, so runs that render every pixel keep the
        # keys they had before the option existed (their stages are reused)
        gmd = c["output"]["guide_mask_dilation"]
        k_guide = _hash(k_field, c["output"]["low_weight_rule"], *([gmd] if gmd is not None
                                                                       else []))
        k_mvs23 = _hash(k_guide, c["mvs"], c["output"]["finer_stage_optimization"],
                        *([guide_init] if guide_init is not None else []))
        k_unguided = _hash(k_mvs1, c["mvs"], "unguided stages 2-3")
        # options added after runs existed enter only when set: those runs keep their keys
        fo = {k: v for k, v in c["output"].items() if (k.startswith("fusion") or k == "use_masks")
              and not (k in _FUSION_KEYS_WHEN_SET and v is None)}
        net = None
        if self._wants_network():
            net = backbone_signature(self.cfg.output.fusion_network,
                                     weights=self.cfg.output.fusion_network_weights,
                                     max_sources=self.cfg.mvs.max_sources)
        k_fusion = _hash(k_mvs23, fo, k_unguided if self._wants_unguided() else None,
                         *([net] if net is not None else []))
        # mesh_fit_points enters only when set (with the fused points it fits): run folders
        # made before the option keep their mesh key
        fit = ([c["output"]["mesh_fit_points"], k_fusion] if self._wants_mesh_fit() else [])
        k_mesh = _hash(k_field, c["output"]["mesh_resolution"], c["output"]["mesh_format"],
                       *fit,
                       k_mvs23 if c["output"]["finer_stage_optimization"] else None,
                       c["output"]["use_masks"],
                       (k_guide, c["output"]["mesh_cull_tol"]) if c["output"]["mesh_cull_unseen"]
                       else None,
                       # enters only when set: earlier run folders keep their mesh key
                       *(["watertight"] if c["output"]["mesh_watertight"] else []),
                       # ditto: the Poisson surface of the fused points
                       *((["poisson", c["output"]["poisson_depth"], c["output"]["poisson_trim"],
                           k_fusion]) if self._wants_poisson() else []))
        return {"mvs1": k_mvs1, "field": k_field, "guide": k_guide, "mvs23": k_mvs23,
                "unguided": k_unguided,
                "fusion": k_fusion, "mesh": k_mesh}

    def _done(self, stage: str) -> bool:
        return self._state().get(stage) == self.keys[stage]

    def _time(self, stage: str, t0: float, **extra) -> None:
        self.timing[stage] = {"seconds": round(time.perf_counter() - t0, 3),
                              "peak_memory_gb": round(peak_rss_gb(), 3), **extra}
        prev = {}
        tp = self.out / "timing.json"
        if tp.is_file():
            try:
                prev = json.loads(tp.read_text())
            except (ValueError, UnicodeDecodeError):
                prev = None
            if not isinstance(prev, dict):
                log.warning("%s is unreadable; rewriting it", tp)
                prev = {}
        prev.update(self.timing)
        tmp = tp.with_suffix(".tmp")
        tmp.write_text(json.dumps(prev, indent=1))
        os.replace(tmp, tp)

    # ------------------------------------------------------------------ scene
    def load(self) -> Scene:
        """The input views at the working size (images, masks, cameras)."""
        if self._scene is not None:
            return self._scene
        from svolsdf.scene.loaders import load_scene

        sc = self.cfg.scene
        head = load_scene(sc.path, load_images=False, lighting=sc.lighting)
        self.all_view_ids = list(head.view_ids)
        if sc.views:
            views = list(sc.views)
        elif sc.view_selection == "auto":
            views = auto_views(head, sc.num_views)
            log.info("views auto: picked %s of %d (reference %d)", views, len(head),
                     views[0])
        elif sc.view_selection == "default":
            views = default_views(head, sc.num_views)
        else:
            raise InputError(f"scene.view_selection: unknown {sc.view_selection!r} (default "
                             f"or auto)")
        for v in views:
            head.index(v)  # raises a clear error for unknown ids
        if len(views) < 2:
            raise InputError(f"need at least 2 input views, got {views}")
        if sc.image_size:
            size = tuple(int(x) for x in sc.image_size)
        else:
            size = working_size(head.width, head.height)
        self.views = views
        self.test_view_ids = test_views(head, views)
        self._scene = load_scene(sc.path, views=views, image_size=size, lighting=sc.lighting)
        return self._scene

    # ------------------------------------------------------------------ run
    def run(self) -> dict:
        """Run (or resume) every stage; returns a summary dict.

        Raises:
            InputError: bad input (also written to OUT/log).
            RunInterrupted: Ctrl-C; its message, also in OUT/log, names the stage that stopped
                and says that a rerun resumes.
        """
        from svolsdf.io.folders import ensure_writable_folder

        t_all = time.perf_counter()
        self._check_options()
        ensure_writable_folder(self.out)
        with _folder_lock(self.out):
            handler = self._setup_log()
            try:
                return self._run(t_all)
            except KeyboardInterrupt:
                msg = self._interrupt_message()
                self._log_to_file(logging.WARNING, msg)
                raise RunInterrupted(msg) from None
            except InputError as e:  # the command line prints it; OUT/log keeps it too
                self._log_to_file(logging.ERROR, f"error: {e}")
                raise
            except Exception as e:
                self._log_to_file(logging.ERROR, f"failed in stage {self._stage}: "
                                  f"{_one_line(e)}", exc_info=True)
                raise
            finally:
                if handler is not None:  # this run's OUT/log only gets this run's messages
                    logging.getLogger("svolsdf").removeHandler(handler)
                    handler.close()

    def _check_options(self) -> None:
        """Fail on a missing scene folder or on backbone options (weights, scale) that cannot
        run before the output folder is touched."""
        path = Path(self.cfg.scene.path)
        if not path.exists():
            raise InputError(f"{path}: scene folder does not exist")
        if not path.is_dir():
            raise InputError(f"{path} is not a folder; pass the scene folder")
        c = self.cfg
        if c.train.mode in ("svolsdf", "mvs-only") or c.train.ablation:
            self.backbone()  # built once and dropped: its weights load again in stage 1
        if self._wants_network():
            self._network_backbone()  # kept: the fusion stage reuses it

    def _interrupt_message(self) -> str:
        msg = f"interrupted: stage {self._stage} stopped"
        t, resumes = self._trainer, ""
        if self._stage == "field" and t is not None:
            msg += f" at step {t.step} of {self.cfg.train.steps}"
            if self.cfg.train.checkpoint_every > 0:
                resumes = "; the optimization continues from its last checkpoint"
        return (f"{msg}; rerun the same command to resume (finished stages in {self.out} are "
                f"kept{resumes})")

    def _log_to_file(self, level: int, msg: str, exc_info: bool = False) -> None:
        """Write ``msg`` to OUT/log alone (the console gets it from the command line)."""
        path = str((self.out / "log").resolve())
        for h in logging.getLogger("svolsdf").handlers:
            if isinstance(h, logging.FileHandler) and h.baseFilename == path:
                rec = log.makeRecord(log.name, level, __file__, 0, msg, (),
                                     sys.exc_info() if exc_info else None)
                with contextlib.suppress(Exception):
                    h.handle(rec)

    def _run(self, t_all: float) -> dict:
        scene = self.load()
        self.keys = self._keys()
        save_config(self.cfg, self.out / "config.yaml")
        tmp = self.out / "views.json.tmp"
        tmp.write_text(json.dumps(
            {"inputs": self.views, "test": self.test_view_ids,
             "size": [scene.width, scene.height], "scene": str(self.cfg.scene.path)}, indent=1))
        os.replace(tmp, self.out / "views.json")
        threads = set_threads(self.cfg.threads)
        log.info("scene %s: inputs %s at %dx%d, mode %s, preset %s, %d torch thread(s)",
                 scene.path, self.views, scene.width, scene.height, self.cfg.train.mode,
                 self.cfg.preset, threads)
        mode = self.cfg.train.mode  # its value and the options it allows: validate_config
        # stage keys chain their inputs: a changed config reruns that stage and the later ones
        stages = []
        if mode in ("svolsdf", "mvs-only") or self.cfg.train.ablation:
            stages.append(("mvs1", self.stage_mvs1))
        if mode in ("svolsdf", "volsdf") and self.cfg.train.ablation != "soft-consistency-only":
            stages.append(("field", self.stage_field))
        stages += [("guide", self.stage_guide), ("mvs23", self.stage_mvs23),
                   ("unguided", self.stage_unguided), ("fusion", self.stage_fusion)]
        if self._has_field():
            stages.append(("mesh", self.stage_mesh))
        for name, stage in stages:
            self._stage = name
            stage()
        self._stage = "finish"
        self._time("total", t_all)
        summary = {"out": str(self.out), "points": str(self.out / "points.ply"),
                   "mesh": str(self.out / "mesh.ply") if self._has_field() else None,
                   "timing": self.timing}
        return summary

    def _has_field(self) -> bool:
        return self.cfg.train.mode in ("svolsdf", "volsdf") and \
            self.cfg.train.ablation != "soft-consistency-only"

    def _setup_log(self) -> logging.Handler | None:
        """Append this run's messages to OUT/log; returns the handler to remove afterwards."""
        root = logging.getLogger("svolsdf")
        if root.level == logging.NOTSET or root.level > logging.INFO:
            root.setLevel(logging.INFO)
        path = str((self.out / "log").resolve())
        if any(isinstance(h, logging.FileHandler) and h.baseFilename == path
               for h in root.handlers):
            return None
        h = logging.FileHandler(path)
        h.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        root.addHandler(h)
        return h

    # ------------------------------------------------------------------ stage 1
    def _backbone_kwargs(self) -> dict:
        m = self.cfg.mvs
        nd = tuple(int(x) for x in m.ndepths)
        common = {"inverse_depth": m.inverse_depth, "max_sources": m.max_sources}
        if m.backbone == "planesweep":
            return {"num_depths": nd, "width": m.width, "native_images": m.native_images,
                    **common, **({"scale": float(m.scale)} if m.scale is not None else {})}
        # casmvsnet and the depth + confidence adapters share these names
        from svolsdf.mvs.backbone import backbone_config_class

        kw = {"ndepths": nd, "width_mode": m.width, **common}
        if m.scale is not None:
            if not hasattr(backbone_config_class(m.backbone), "x2_mvsres"):
                raise InputError(f"mvs.scale: the {m.backbone} backbone runs at the working "
                                 f"size; leave mvs.scale unset (got {m.scale})")
            if float(m.scale) not in (1.0, 2.0):
                raise InputError(f"mvs.scale: {m.backbone} runs at 1 or 2 x the working size "
                                 f"(x2_mvsres), got {m.scale}")
            kw["x2_mvsres"] = float(m.scale) == 2.0
        if hasattr(backbone_config_class(m.backbone), "native_images"):
            kw["native_images"] = m.native_images
        if hasattr(backbone_config_class(m.backbone), "guide_init"):  # the adapters' option
            kw["guide_init"] = m.guide_network
        return kw

    def backbone(self):
        from svolsdf.mvs.backbone import get_backbone

        m = self.cfg.mvs
        return get_backbone(m.backbone, weights=m.weights, device=self.device,
                            **self._backbone_kwargs())

    def stage_mvs1(self) -> list[ProbabilityVolume]:
        d = self.out / "mvs" / "stage1"
        files = [d / f"{v}.npz" for v in self.views]
        if self._done("mvs1") and all(f.is_file() for f in files):
            vols = self._reuse("mvs1", lambda: [ProbabilityVolume.load(f) for f in files])
            if vols is not None:
                self._volumes1 = vols
                return vols
        t0 = time.perf_counter()
        from svolsdf.mvs.cascade import run_cascade

        res = run_cascade(self.backbone(), self.load(), stages=(1,))
        d.mkdir(parents=True, exist_ok=True)
        for v in res[1]:
            v.save(d / f"{v.view_id}.npz")
        self._volumes1 = [v.to("cpu") for v in res[1]]  # as when read back from the files
        self._mark("mvs1", self.keys["mvs1"])
        self._time("mvs1", t0)
        return self._volumes1

    def regressed_volumes1(self) -> list[ProbabilityVolume] | None:
        """The stage-1 volumes with depth = sum_k P_k d_k, the regression of METHOD.md 2.4.

        The field stage (box, SDF initialisation, the ablations' MVS depth) uses this depth
        whatever estimate the backbone stores: the plane sweep stores the main-mode depth
        (`PlaneSweepConfig.depth_radius`), which centres its own next stage better, while the
        smoother full expectation initialises the SDF grid better (synthetic benchmark scene,
        points Chamfer 2.12 vs 2.34 mm; benchmarks/results/fast_preset.md).
        """
        if self._volumes1 is None:
            return None
        if self._reg1 is None or self._reg1[0] is not self._volumes1:
            from svolsdf.mvs.backbone import expected_depth

            self._reg1 = (self._volumes1, [
                replace(v, depth=expected_depth(v.prob.float(), v.depths.float())
                                    .to(v.depth.dtype)) for v in self._volumes1])
        return self._reg1[1]

    # ------------------------------------------------------------------ field
    def field_bounds(self) -> torch.Tensor:
        """(2, 3) unit-frame box of the object: from stage-1 MVS depth where available (masked,
        percentiles, padded), else the intersection of the views' frusta and depth ranges."""
        scene = self.load()
        norm = scene.normalization
        pts = []
        if self._volumes1 is not None and self.cfg.train.mode != "volsdf":
            for vol in self.regressed_volumes1():
                cam = vol.cameras
                H, W = vol.depth.shape
                uv = cam.pixel_grid(dtype=torch.float64).reshape(1, -1, 2)
                conf = vol.confidence.reshape(-1)
                keep = conf >= torch.quantile(conf.float(), 0.5)
                if scene.masks is not None:
                    i = scene.index(vol.view_id)
                    m = F.interpolate(scene.masks[i:i + 1], size=(H, W), mode="bilinear")
                    keep &= m.reshape(-1) > 0.5
                X = cam.to(dtype=torch.float64).unproject(uv, vol.depth.double().reshape(1, -1))[0]
                pts.append(norm.to_unit(X[keep]))
        if pts and sum(len(p) for p in pts) > 100:
            P = torch.cat(pts).float()
            lo = torch.quantile(P[torch.randperm(len(P))[:200000]], 0.01, dim=0)
            hi = torch.quantile(P[torch.randperm(len(P))[:200000]], 0.99, dim=0)
        else:
            lo, hi = self._frusta_box()
        pad = 0.15 * (hi - lo).max()
        lo, hi = (lo - pad).clamp(-2.5, 2.5), (hi + pad).clamp(-2.5, 2.5)
        return torch.stack([lo, hi]).float()

    def _frusta_box(self) -> tuple[torch.Tensor, torch.Tensor]:
        scene = self.load()
        cams = scene.cameras_unit
        n = 64
        g = torch.linspace(-2.0, 2.0, n, dtype=torch.float64)
        X = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
        uv, z = cams.project(X)
        nf = scene.depth_range / scene.normalization.scale
        ok = (z > nf[:, None, 0]) & (z < nf[:, None, 1]) & (uv[..., 0] >= 0) \
            & (uv[..., 0] <= cams.width - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= cams.height - 1)
        inside = ok.all(0)
        if inside.sum() < 8:
            return torch.full((3,), -1.0), torch.full((3,), 1.0)
        P = X[inside].float()
        return P.min(0).values, P.max(0).values

    def build_model(self):
        """The configured `SurfaceModel` (grid field for fast, VolSDF MLP for paper)."""
        f = self.cfg.field
        if f.kind == "grid":
            from svolsdf.field.grid import GridFieldConfig, GridSDFField

            if self._grid_from_sphere():
                # VolSDF's start (METHOD.md 5.2): a sphere at the origin in the box of the
                # bounding sphere; nothing from MVS
                bounds = torch.tensor([[-1.0] * 3, [1.0] * 3])
                res, radius, centre = f.sphere_start_resolution, f.sphere_radius, (0.0,) * 3
            else:
                bounds = self.field_bounds()
                ext = (bounds[1] - bounds[0]).max()
                res, radius = f.grid_start_resolution, float(0.35 * ext)
                centre = tuple(((bounds[0] + bounds[1]) / 2).tolist())
            gcfg = GridFieldConfig(resolution=res, init_radius=radius, init_centre=centre,
                                   # METHOD.md 5.5: no sphere clamp under a background model
                                   sphere_clamp_scale=None if f.background else 20.0)
            model = GridSDFField(bounds, gcfg)
        elif f.kind == "mlp":
            from svolsdf.field.volsdf import VolSDFField, VolSDFFieldConfig

            model = VolSDFField(VolSDFFieldConfig(n_layers=f.mlp_depth, d_hidden=f.mlp_width,
                                                  render_hidden=f.mlp_width,
                                                  sphere_clamp=not f.background))
        else:
            raise InputError(f"unknown field kind {f.kind!r} (grid or mlp)")
        if f.background:
            self._attach_background(model)
        if self.cfg.train.beta_min > 0 and hasattr(model, "laplace"):
            model.laplace.beta_min = float(self.cfg.train.beta_min)  # METHOD.md 5.4's floor
        return model

    def _attach_background(self, model) -> None:
        """``model.background``: the NeRF++ inverted-sphere background (METHOD.md 5.5).

        A submodule of the field, so it moves with ``model.to(device)``, is saved in its
        state_dict (keys ``background.net.*``, ``background.colour_net.*``), trained by the
        Trainer at the network rate ``train.lr`` and passed to every ``render_rays`` call. The
        paper's network sizes with the MLP field; a smaller MLP with the fast grid field.
        """
        from svolsdf.field.background import BackgroundConfig, NeRFPlusPlusBackground

        bcfg = BackgroundConfig(radius=float(model.radius))
        if self.cfg.field.kind == "grid":
            bcfg = BackgroundConfig(radius=float(model.radius), n_layers=4, d_hidden=64,
                                    skip_in=(), feature_dim=32, colour_hidden=32)
        model.background = NeRFPlusPlusBackground(bcfg)

    def _grid_from_sphere(self) -> bool:
        """The grid field starts from VolSDF's sphere, not from the stage-1 MVS surface."""
        f = self.cfg.field
        return f.kind == "grid" and not (self.cfg.train.mode == "svolsdf" and f.init == "mvs"
                                         and self.cfg.train.ablation != "soft-consistency-only")

    def _grid_schedule(self) -> list[tuple[int, int]]:
        f = self.cfg.field
        steps = self.cfg.train.steps
        if f.kind == "grid" and self._grid_from_sphere():
            # doublings from sphere_start_resolution, evenly spaced, the last at 3/4 of the steps
            levels, r = [], f.sphere_start_resolution
            while r < f.grid_resolution:
                r = min(2 * r, f.grid_resolution)
                levels.append(r)
            n = len(levels)
            return [(int(steps * 0.75 * (i + 1) / n), r) for i, r in enumerate(levels)]
        if f.kind != "grid" or f.grid_resolution <= f.grid_start_resolution:
            return []
        r0, r1 = f.grid_start_resolution, f.grid_resolution
        mid = int(round((r0 * r1) ** 0.5))
        return [(int(steps * 0.25), mid), (int(steps * 0.5), r1)]

    def make_sampler(self, prior, training: bool = True):
        from svolsdf.render.guided import GuidedSamplerConfig, MVSGuidedSampler
        from svolsdf.render.samplers import ErrorBoundSampler

        t = self.cfg.train
        if t.sampler == "error_bounded":
            return ErrorBoundSampler()
        if t.sampler == "mvs":
            if training:
                gc = GuidedSamplerConfig(n_uniform=t.samples_uniform, n_fine=t.samples_fine)
            else:
                # rendering: a converged field needs fewer probes
                # (benchmarks/results/render_speed.md)
                gc = GuidedSamplerConfig(n_coarse=64, n_uniform=16, n_fine=32)
            return MVSGuidedSampler(prior if training else None, gc)
        raise InputError(f"unknown sampler {t.sampler!r} (mvs or error_bounded)")

    def unit_near_far(self) -> torch.Tensor:
        """(V, 2) unit-frame z-depth range of the input views, padded by 10% (rays are clipped
        to it in training, guide rendering and novel views)."""
        scene = self.load()
        nf = (scene.depth_range / scene.normalization.scale).float()
        return torch.stack([nf[:, 0] * 0.9, nf[:, 1] * 1.1], -1)

    def train_data(self):
        from svolsdf.optimize.trainer import TrainData

        scene = self.load()
        mvs_depth = None
        if self.cfg.train.ablation in ("mse", "no-prob-volume"):
            mvs_depth = self._filtered_stage1_depth() / scene.normalization.scale
        focus = None
        if self.cfg.train.object_ray_fraction > 0 and scene.masks is not None \
                and self.cfg.output.use_masks:
            from svolsdf.fusion.filter import dilate_mask

            r = self.cfg.train.object_ray_dilation
            focus = torch.stack([dilate_mask(m[0], r) for m in scene.masks])
        return TrainData(scene.images, scene.cameras_unit, self.unit_near_far(), mvs_depth,
                         focus)

    def _filtered_stage1_depth(self) -> torch.Tensor:
        """(V, H, W) stage-1 MVS depth (world), geometrically filtered, 0 where rejected, at the
        working size (for the "mse" and "no-prob-volume" ablations)."""
        from svolsdf.field.init import consistent_depths

        scene = self.load()
        depths, _ = consistent_depths(self.regressed_volumes1())  # >= 1 consistent source (6.3)
        return torch.stack([F.interpolate(d[None, None], size=(scene.height, scene.width),
                                          mode="nearest")[0, 0] for d in depths])

    def stage_field(self):
        """The S-VolSDF optimization (OUT/field/model.pt), resumed from OUT/field/checkpoint.pt
        after an interrupt; an unreadable model or checkpoint is discarded (with a warning) and
        the stage runs again."""
        fdir = self.out / "field"
        final = fdir / "model.pt"
        torch.manual_seed(self.cfg.train.seed)  # the box (quantiles of a random subset) too
        model = self.build_model()
        if self._done("field") and final.is_file():
            if self._reuse("field", lambda: self._load_model(model, final) or True, final):
                self._model = model.to(self.device)
                return self._model
            torch.manual_seed(self.cfg.train.seed)  # a fresh model: the load may have filled
            model = self.build_model()  # part of it
        t0 = time.perf_counter()
        tcfg = self.cfg.train
        trainer = self._field_trainer(model)
        if self._state().get("field_partial") == self.keys["field"]:
            ckpt = trainer.checkpoint_path()
            if not self._reuse("field", lambda: trainer.load_checkpoint() or True, ckpt):
                torch.manual_seed(tcfg.seed)  # start again, exactly as a fresh run
                model = self.build_model()
                trainer = self._field_trainer(model)
        else:
            self._mark("field_partial", self.keys["field"])
        self._trainer = trainer  # its step, for the message of an interrupt
        trainer.fit(progress=self.progress)
        self._trainer = None
        fdir.mkdir(parents=True, exist_ok=True)
        tmp = final.with_suffix(".tmp")
        torch.save({"model_state_dict": model.state_dict(),
                    "grid_resolution": getattr(model, "resolution", None),
                    "bounds": getattr(model, "bounds", None)}, tmp)
        os.replace(tmp, final)
        self._model = model
        self._mark("field", self.keys["field"])
        hist = trainer.history
        self._time("field", t0, steps=tcfg.steps,
                   steps_per_s=round(hist[-1]["steps_per_s"], 3) if hist else None)
        return model

    def _field_trainer(self, model):
        """The `Trainer` of the field stage for a freshly built ``model`` (its grid initialised
        from the stage-1 MVS depth where configured)."""
        from svolsdf.optimize.trainer import Trainer
        from svolsdf.prior.consistency import MVSPrior

        tcfg = self.cfg.train
        torch.manual_seed(tcfg.seed)
        prior = None
        if tcfg.mode == "svolsdf" and self._volumes1 is not None:
            prior = MVSPrior(self._volumes1, self.load().normalization, device=self.device)
            if self.cfg.field.kind == "grid" and self.cfg.field.init == "mvs":
                from svolsdf.field.init import init_grid_from_mvs

                scene = self.load()
                init_grid_from_mvs(model, self.regressed_volumes1(), scene.normalization,
                                   scene.masks if self.cfg.output.use_masks else None,
                                   unverified_weight=self.cfg.field.init_unverified_weight)
        return Trainer(model, self.train_data(), tcfg, prior=prior,
                       sampler=self.make_sampler(prior), out_dir=self.out / "field",
                       device=self.device, grid_schedule=self._grid_schedule())

    def _load_model(self, model, path: Path) -> None:
        """Load a saved field into ``model``.

        Raises:
            InputError: the file is unreadable (truncated, not a field file).
            RuntimeError: it holds another field than ``model`` (torch's message).
        """
        try:
            state = torch.load(path, map_location="cpu", weights_only=False)
            sd = state["model_state_dict"]
        except Exception as e:  # zip, pickle, EOF or key errors of a corrupt file
            raise InputError(f"{path}: not a readable field file ({_one_line(e)})") from None
        # a grid field takes the stored box and grid shapes (GridSDFField._load_from_state_dict)
        model.load_state_dict(sd)

    def model(self):
        if self._model is None:
            self.stage_field()
        return self._model

    # ------------------------------------------------------------------ rendering
    @torch.no_grad()
    def render_views(self, cameras_unit, near_far=None, chunk: int = 4096, keys=("depth",
                     "opacity", "rgb", "normals"),
                     pixels: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Render every camera of ``cameras_unit`` with the field (eval-mode sampler).

        ``chunk`` rays at a time: 4096 rendered the fast field ~10 % faster than 2048 or 8192
        on two cores (benchmarks/results/train_step_speed.md, session-13 notes).

        Args:
            pixels: optional (V, H, W) bool; only these pixels are rendered, the others get 0
                in every map (depth, opacity, colour and normal).

        Returns:
            dict of (V, H, W, ...) tensors: depth (unit-frame z-depth), opacity, rgb, normals.
        """
        from svolsdf.render.rays import rays_from_cameras
        from svolsdf.render.volume import render_rays

        model = self.model()
        model.eval()
        background = getattr(model, "background", None)
        sampler = self.make_sampler(None, training=False)
        cams = cameras_unit.to(self.device, dtype=torch.float32)
        H, W = cams.height, cams.width
        res = {k: [] for k in keys}
        for t in range(len(cams)):
            rays = rays_from_cameras(cams, t, radius=float(getattr(model, "radius", 3.0)))
            if near_far is not None:
                rays.near = torch.maximum(rays.near, near_far[t, 0] / rays.cos)
                # with a background the foreground ends at the sphere (METHOD.md 5.5)
                far = rays.far if background is not None else torch.minimum(
                    rays.far, near_far[t, 1] / rays.cos)
                rays.far = torch.maximum(far, rays.near + 1e-3)
            sel = None  # (R,) indices of the rendered pixels, on the CPU
            if pixels is not None:
                sel = pixels[t].reshape(-1).nonzero()[:, 0].cpu()
                rays = rays[sel.to(self.device)]
            parts = {k: [] for k in keys}
            for i in range(0, len(rays), chunk):
                rb = rays[i:i + chunk]
                s = sampler(model, rb, training=False)
                o = render_rays(model, rb, s.z, background=background, create_graph=False,
                                colour_min_weight=1e-4)
                for k in keys:
                    parts[k].append(getattr(o, k).detach().cpu())
            for k in keys:
                v = torch.cat(parts[k])
                if sel is not None:
                    full = v.new_zeros((H * W, *v.shape[1:]))
                    full[sel] = v
                    v = full
                res[k].append(v.reshape(H, W, *v.shape[1:]))
        return {k: torch.stack(v) for k, v in res.items()}

    # ------------------------------------------------------------------ guide depth
    def stage_guide(self) -> dict[int, torch.Tensor] | None:
        """World z-depth maps that replace the stage-1 depth (METHOD.md 6.1), or None."""
        if self.cfg.train.mode == "mvs-only":
            return None
        gdir = self.out / "field" / "render_depth"
        files = {v: gdir / f"{v}.npy" for v in self.views}
        if self._done("guide") and all(f.is_file() for f in files.values()):
            maps = self._reuse("guide", lambda: _load_maps(files))
            if maps is not None:
                return maps
        t0 = time.perf_counter()
        if self.cfg.train.ablation == "soft-consistency-only":
            guide = self._consistency_depth()
        else:
            guide = self._rendered_guide(previews=True)
        for v, d in guide.items():
            _save_npy(files[v], d.numpy().astype(np.float32))
        self._mark("guide", self.keys["guide"])
        psnr = getattr(self, "field_psnr", None)
        self._time("guide", t0, **({"field_psnr": psnr} if psnr is not None else {}))
        return guide

    def _rendered_guide(self, previews: bool = False) -> dict[int, torch.Tensor]:
        """The field's rendered z-depth (world) of each input view, with METHOD.md 6.1's rule
        for pixels of accumulated weight < 0.2."""
        scene = self.load()
        s = scene.normalization.scale
        pixels = self._guide_pixels()
        r = self.render_views(scene.cameras_unit, self.unit_near_far().to(self.device),
                              pixels=pixels)
        if previews:
            self._report_field_psnr(r["rgb"], pixels)
        guide = {}
        for i, v in enumerate(self.views):
            d = r["depth"][i] * s
            low = r["opacity"][i] < 0.2
            if self.cfg.output.low_weight_rule == "max":
                # METHOD.md 6.1: pixels with sum w < 0.2 get the map's maximum depth
                d = torch.where(low, d[~low].max() if (~low).any() else d.max(), d)
            elif self.cfg.output.low_weight_rule == "mvs" and self._volumes1 is not None:
                m = self.regressed_volumes1()[i].depth[None, None]
                m = F.interpolate(m, size=d.shape, mode="bilinear")[0, 0]
                d = torch.where(low, m, d)
            guide[v] = d.float()
            if previews:
                self._render_previews(v, r, i)
        return guide

    def _report_field_psnr(self, rgb: torch.Tensor, pixels: torch.Tensor | None) -> None:
        """Log the field's PSNR on its own input views and keep it in timing.json (issue 28).

        A field that only copies MVS scores well on the points and badly here; a field that
        explains the photos scores > 20 dB. Masked as the paper's PSNR (METHOD.md 8.3): inside the
        object masks when the scene has them (rendered pixels only), else over every pixel.

        Args:
            rgb: (V, H, W, 3) rendered colours of the input views (0 where not rendered).
            pixels: (V, H, W) bool rendered pixels, or None (all).
        """
        from svolsdf.evaluate.images import masked_psnr

        scene = self.load()
        vals = {}
        for i, v in enumerate(self.views):
            m = None
            if scene.masks is not None and self.cfg.output.use_masks:
                m = scene.masks[i, 0] > 0.5
            if pixels is not None:
                m = pixels[i] if m is None else m & pixels[i].to(m.device)
            vals[v] = round(float(masked_psnr(rgb[i].permute(2, 0, 1).clamp(0, 1),
                                              scene.images[i].cpu(), m)), 2)
        mean = round(sum(vals.values()) / len(vals), 2)
        where = "inside the object masks" if scene.masks is not None and \
            self.cfg.output.use_masks else "whole images"
        log.info("field: PSNR on the input views (%s): %s; mean %.2f dB", where,
                 ", ".join(f"{v}: {p:.2f}" for v, p in vals.items()), mean)
        self.field_psnr = {"masked": scene.masks is not None and self.cfg.output.use_masks,
                           "per_view_db": {str(v): p for v, p in vals.items()}, "mean_db": mean}

    def _guide_pixels(self) -> torch.Tensor | None:
        """(V, H, W) bool: the pixels whose guide depth is rendered, the object masks dilated by
        ``output.guide_mask_dilation`` px (None: every pixel, as released; also without masks)."""
        r = self.cfg.output.guide_mask_dilation
        scene = self.load()
        if r is None or scene.masks is None or not self.cfg.output.use_masks:
            return None
        from svolsdf.fusion.filter import dilate_mask

        m = scene.masks[:, 0] > 0.5  # (V, H, W) at the working size, as the cameras
        # a view whose mask is empty is rendered whole (its guide then follows the rule alone)
        return torch.stack([dilate_mask(m[i], int(r)) if bool(m[i].any())
                            else torch.ones_like(m[i]) for i in range(len(m))])

    def _finer_stage_cascade(self, guide: dict[int, torch.Tensor]) -> dict:
        """The paper's optional optimization at the finer stages (METHOD.md 9.2.13; the released
        code forbids it): stage 2 runs centred on the rendered depth, the field is optimized
        further against the soft-consistency prior of the stage-2 volumes, its depth is rendered
        again, and stage 3 runs centred on that depth.

        Returns:
            {2: stage-2 volumes, 3: stage-3 volumes}.
        """
        from dataclasses import replace

        from svolsdf.mvs.cascade import run_cascade
        from svolsdf.optimize.trainer import Trainer
        from svolsdf.prior.consistency import MVSPrior

        bb = self.backbone()
        scene = self.load()
        res2 = run_cascade(bb, scene, guide_depth=guide, stages=(2,))
        model = self.model()
        t = self.cfg.train
        # continue at the end of the stage-1 schedule: fixed final beta, no warm-up
        t2 = replace(t, steps=max(1, t.steps // 5), anneal_rgb=0,
                     beta_start=t.beta_end if t.beta_start > 0 else 0.0)
        prior2 = MVSPrior(res2[2], scene.normalization, device=self.device)
        trainer = Trainer(model, self.train_data(), t2, prior=prior2,
                          sampler=self.make_sampler(prior2),
                          out_dir=self.out / "field" / "stage2", device=self.device)
        trainer.fit(progress=self.progress)
        log.info("finer-stage optimization: %d more steps against the stage-2 volumes", t2.steps)
        final = self.out / "field" / "stage2" / "model.pt"
        tmp = final.with_suffix(".tmp")
        torch.save({"model_state_dict": model.state_dict(),
                    "grid_resolution": getattr(model, "resolution", None)}, tmp)
        os.replace(tmp, final)
        guide2 = self._rendered_guide()
        for v, d in guide2.items():  # the refined surface, for fusion (output.fusion_surface)
            _save_npy(self.out / "field" / "stage2" / "render_depth" / f"{v}.npy",
                      d.numpy().astype(np.float32))
        res3 = run_cascade(bb, scene, guide_depth=guide2, stages=(3,),
                           prev={v.view_id: v for v in res2[2]})
        return {2: res2[2], 3: res3[3]}

    def _render_previews(self, v: int, r: dict, i: int) -> None:
        from svolsdf.io.images import write_image

        d = self.out / "field"
        write_image(d / "render_rgb" / f"{v}.png", r["rgb"][i].permute(2, 0, 1).clamp(0, 1))
        n = r["normals"][i]
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        write_image(self.out / "normals" / f"{v}.png",
                    ((n * 0.5 + 0.5) * r["opacity"][i][..., None].clamp(0, 1)).permute(2, 0, 1))

    def _consistency_depth(self) -> dict[int, torch.Tensor]:
        """Ablation "soft-consistency-only": the expected depth under the consistency-weighted
        stage-1 volume P_ref * sum P_src (METHOD.md 3, 9.2.3) at each input view's hypotheses."""
        from svolsdf.prior.consistency import MVSPrior

        scene = self.load()
        norm = scene.normalization
        prior = MVSPrior(self._volumes1, norm)
        out = {}
        for i, vol in enumerate(self._volumes1):
            D, H, W = vol.depths.shape
            cam = vol.cameras.to(dtype=torch.float64)
            uv = cam.pixel_grid(dtype=torch.float64).reshape(1, -1, 2)
            num = torch.zeros(H * W)
            den = torch.zeros(H * W)
            for k in range(D):
                X = cam.unproject(uv, vol.depths[k].double().reshape(1, -1))[0]
                pts = norm.to_unit(X).float()[:, None]
                p_ref, p_src, _ = prior.lookup(pts, torch.full((H * W,), i, dtype=torch.long))
                w = (p_ref * p_src)[:, 0]
                num += w * vol.depths[k].reshape(-1)
                den += w
            d = torch.where(den > 1e-6, num / den.clamp_min(1e-12), vol.depth.reshape(-1))
            out[vol.view_id] = d.reshape(H, W).float()
        return out

    # ------------------------------------------------------------------ stages 2-3
    def stage_mvs23(self) -> dict[int, torch.Tensor]:
        """Final per-view depth: MVS stage 3 (guided by the field when there is one); for the
        ``volsdf`` mode, the field's rendered depth itself."""
        ddir = self.out / "depth"
        files = {v: ddir / f"{v}.npy" for v in self.views}
        if self._done("mvs23") and all(f.is_file() for f in files.values()):
            maps = self._reuse("mvs23", lambda: _load_maps(files))
            if maps is not None:
                return maps
        t0 = time.perf_counter()
        from svolsdf.io.images import write_depth_preview

        guide = self.stage_guide()
        if self.cfg.train.mode == "volsdf":
            depths = guide
            for v, d in depths.items():
                _save_npy(files[v], d.numpy().astype(np.float32))
                write_depth_preview(ddir / f"{v}.png", d)
        else:
            from svolsdf.mvs.cascade import run_and_save_cascade, save_cascade

            def picture(d, p):
                write_depth_preview(p, torch.from_numpy(d))

            prev = {v.view_id: v for v in self._volumes1} if guide is None else None
            stages = (2, 3)
            if guide is None and self._volumes1 is None:
                stages = (1, 2, 3)
            earlier = {1: self._volumes1} if self._volumes1 is not None else None
            if self.cfg.output.finer_stage_optimization and guide is not None:
                res = self._finer_stage_cascade(guide)
                save_cascade({**res, **(earlier or {})}, self.out, picture=picture)
                depths = {v.view_id: v.depth.float() for v in res[max(res)]}
            else:  # one view at a time: only its finer volumes are in memory
                depths = run_and_save_cascade(self.backbone(), self.load(), self.out,
                                              stages=stages, guide_depth=guide, prev=prev,
                                              earlier=earlier, picture=picture)
        self._mark("mvs23", self.keys["mvs23"])
        self._time("mvs23", t0)
        return depths

    def _wants_network(self) -> bool:
        """`OutputConfig.fusion_network` applies: set, in svolsdf mode (which has a guide)."""
        return self.cfg.output.fusion_network is not None and self.cfg.train.mode == "svolsdf"

    def _network_backbone(self):
        """The `OutputConfig.fusion_network` backbone (its weights loaded and checked once per
        config; `run` asks for it first, the fusion stage reuses it)."""
        from svolsdf.mvs.backbone import get_backbone

        o = self.cfg.output
        key = (o.fusion_network, o.fusion_network_weights, self.cfg.mvs.max_sources)
        if self._net is None or self._net[0] != key:
            bb = get_backbone(o.fusion_network, weights=o.fusion_network_weights,
                              max_sources=self.cfg.mvs.max_sources, device=self.device)
            if not getattr(bb, "can_start_from_depth", False):
                raise InputError(f"output.fusion_network: the {o.fusion_network!r} backbone "
                                 "cannot start from a depth map (patchmatchnet can)")
            self._net = (key, bb)
        return self._net[1]

    def _network_depths(self, guide: dict[int, torch.Tensor]
                        ) -> tuple[dict[int, torch.Tensor], dict[int, torch.Tensor]]:
        """`OutputConfig.fusion_network`'s depth and confidence of every input view (H, W), the
        network started from ``guide`` (world z-depth); also written to
        OUT/network/{depth,confidence}/<view>.npy."""
        from svolsdf.io.images import write_depth_preview

        bb = self._network_backbone()
        scene = self.load()
        depth, conf = {}, {}
        for v in self.views:
            depth[v], conf[v] = bb.prediction(scene, v, guide=guide[v])
            for sub, m in (("depth", depth[v]), ("confidence", conf[v])):
                _save_npy(self.out / "network" / sub / f"{v}.npy", m.numpy().astype(np.float32))
            write_depth_preview(self.out / "network" / "depth" / f"{v}.png", depth[v])
        return depth, conf

    def _wants_unguided(self) -> bool:
        """`OutputConfig.fusion_unguided` applies: svolsdf mode, whose stages 2-3 are guided."""
        return self.cfg.output.fusion_unguided and self.cfg.train.mode == "svolsdf"

    def stage_unguided(self) -> dict[int, torch.Tensor] | None:
        """MVS stages 2-3 centred on the stage-1 depth, the backbone alone's cascade
        (`OutputConfig.fusion_unguided`): OUT/unguided/{depth,confidence}/<view>.npy, confidence
        the product over stages 1-3 (METHOD.md 6.2). None when the option does not apply."""
        if not self._wants_unguided():
            return None
        udir = self.out / "unguided"
        files = {v: udir / "depth" / f"{v}.npy" for v in self.views}
        if self._done("unguided") and all(f.is_file() for f in files.values()):
            maps = self._reuse("unguided", lambda: _load_maps(files))
            if maps is not None:
                return maps
        t0 = time.perf_counter()
        from svolsdf.mvs.cascade import run_and_save_cascade

        vols1 = self._volumes1 if self._volumes1 is not None else self.stage_mvs1()
        # depth, confidence over stages 1-3, one view at a time
        depths = run_and_save_cascade(self.backbone(), self.load(), udir, stages=(2, 3),
                                      prev={v.view_id: v for v in vols1}, earlier={1: vols1},
                                      volumes=False)
        self._mark("unguided", self.keys["unguided"])
        self._time("unguided", t0)
        return depths

    # ------------------------------------------------------------------ fusion
    def stage_fusion(self) -> Path:
        path = self.out / "points.ply"
        if self._done("fusion") and path.is_file():
            return path
        t0 = time.perf_counter()
        from svolsdf.fusion.filter import FusionConfig, fuse_depth_maps
        from svolsdf.io.ply import write_points_ply

        scene = self.load()
        o = self.cfg.output
        fcfg = FusionConfig(dist_thresh=o.fusion_dist, rel_thresh=o.fusion_rel,
                            min_consistent=o.fusion_views, conf_thresh=o.fusion_conf,
                            use_masks=o.use_masks, surface_rel_thresh=o.fusion_surface)
        if self.cfg.train.mode == "svolsdf":  # OUT/depth is the field-guided depth
            fcfg.primary_mask_dilation = o.fusion_guided_dilation
            fcfg.alt_mask_dilation = o.fusion_unguided_dilation
        sdir = self.out / "field" / "render_depth"
        if self.cfg.output.finer_stage_optimization:
            sdir = self.out / "field" / "stage2" / "render_depth"  # the refined surface
        # the rendered guide is the surface (the soft-consistency ablation's guide is not)
        use_surface = (o.fusion_surface > 0 and self.cfg.train.ablation != "soft-consistency-only"
                       and all((sdir / f"{v}.npy").is_file() for v in self.views))
        cams = {v: scene.cameras[[i]] for i, v in enumerate(self.views)}
        images = {v: scene.images[i] for i, v in enumerate(self.views)}
        masks = None
        if scene.masks is not None and o.use_masks:
            masks = {v: scene.masks[i, 0] for i, v in enumerate(self.views)}

        def load(d: Path, sub: str) -> dict[int, torch.Tensor] | None:
            files = {v: d / sub / f"{v}.npy" for v in self.views}
            if not all(f.is_file() for f in files.values()):
                return None
            return {v: torch.from_numpy(np.load(f)) for v, f in files.items()}

        depths = load(self.out, "depth")
        confs = load(self.out, "confidence") if self.cfg.train.mode != "volsdf" else None
        alt = alt_confs = None
        if self._wants_unguided():  # the unguided stages 2-3 as each view's second hypothesis
            alt, alt_confs = load(self.out / "unguided", "depth"), \
                load(self.out / "unguided", "confidence")
            if confs is None:
                alt_confs = None
        surface = None
        if use_surface:  # fuse_depth_maps resizes it to each hypothesis' size
            surface = {v: torch.from_numpy(np.load(sdir / f"{v}.npy")).float()
                       for v in self.views}
        net = net_confs = None
        if self._wants_network():  # the learned network, started from the guide
            t1 = time.perf_counter()
            d, c = self._network_depths(self.stage_guide())
            net, net_confs = {"network": d}, ({"network": c} if confs is not None else None)
            log.info("fusion network %s: %d view(s) in %.1f s", o.fusion_network,
                     len(self.views), time.perf_counter() - t1)
        fused = fuse_depth_maps(depths, cams, images, confs, masks, fcfg, surface,
                                alt_depths=alt, alt_confidences=alt_confs,
                                extra_depths=net, extra_confidences=net_confs,
                                device=self.device)
        extra = {}
        if alt is not None or net is not None:
            sets = {"guided": "", **({"unguided": ":alt"} if alt is not None else {}),
                    **({"network": ":network"} if net is not None else {})}
            extra["points_per_set"] = {
                name: sum(fused.stats[f"{v}{sfx}" if sfx else v]["points"] for v in self.views)
                for name, sfx in sets.items()}
        pts = fused.points.numpy()
        cols = None if fused.colors is None else fused.colors.numpy()
        write_points_ply(path, pts, cols)
        self._mark("fusion", self.keys["fusion"])
        self._time("fusion", t0, points=int(len(pts)), **extra)
        log.info("fused %d points -> %s %s", len(pts), path, extra.get("points_per_set", ""))
        return path

    # ------------------------------------------------------------------ mesh
    def _mesh_cull_depths(self, refined: Path | None) -> torch.Tensor | None:
        """(V, H, W) rendered depth of the input views (the refined field's with
        ``refined``), for `cull_unseen`; None when it is missing or is not the surface (the
        soft-consistency ablation's guide)."""
        if self.cfg.train.ablation == "soft-consistency-only":
            return None
        sdir = self.out / "field" / ("stage2/render_depth" if refined is not None
                                     and refined.is_file() else "render_depth")
        files = [sdir / f"{v}.npy" for v in self.views]
        if not all(f.is_file() for f in files):
            return None
        maps = [torch.from_numpy(np.load(f)).float() for f in files]
        if len({tuple(m.shape) for m in maps}) != 1:
            return None
        return torch.stack(maps)

    def _wants_mesh_fit(self) -> bool:
        """`OutputConfig.mesh_fit_points` applies: set, svolsdf mode (its points come from the
        finer MVS stages), a grid field."""
        return (self.cfg.output.mesh_fit_points > 0 and self.cfg.output.mesh_method == "field"
                and self.cfg.train.mode == "svolsdf"
                and self.cfg.train.ablation is None and self.cfg.field.kind == "grid")

    def _surface_fitted_to_points(self, model):
        """A copy of ``model`` whose SDF grid is refined to pass through OUT/points.ply
        (`OutputConfig.mesh_fit_points`); saved as OUT/field/surface.pt."""
        import copy

        from svolsdf.field.fit import fit_sdf_to_points
        from svolsdf.io.ply import read_ply

        scene = self.load()
        pts = read_ply(self.stage_fusion())["points"]
        unit = scene.normalization.to_unit(torch.from_numpy(pts).double()).float()
        fitted = copy.deepcopy(model)
        fit_sdf_to_points(fitted, unit.to(self.device), steps=self.cfg.output.mesh_fit_points,
                          seed=self.cfg.train.seed)
        path = self.out / "field" / "surface.pt"
        tmp = path.with_suffix(".tmp")
        torch.save({"model_state_dict": fitted.state_dict(),
                    "grid_resolution": getattr(fitted, "resolution", None),
                    "bounds": getattr(fitted, "bounds", None)}, tmp)
        os.replace(tmp, path)
        return fitted

    def stage_mesh(self) -> Path:
        o = self.cfg.output
        path = self.out / ("mesh.obj" if o.mesh_format == "obj" else "mesh.ply")
        if self._done("mesh") and path.is_file():
            return path
        t0 = time.perf_counter()
        from svolsdf.fusion.mesh import (
            cull_by_frusta,
            cull_by_masks,
            cull_unseen,
            extract_mesh,
            largest_component,
            mesh_vertex_depths,
            to_world,
        )

        model = self.model()
        refined = self.out / "field" / "stage2" / "model.pt"
        if o.finer_stage_optimization and refined.is_file():
            self._load_model(model, refined)  # the field after the finer-stage optimization
        if self._wants_poisson():
            return self._poisson_mesh(path, model, t0)
        if self._wants_mesh_fit():
            model = self._surface_fitted_to_points(model)
        model.eval()
        b = getattr(model, "bounds", None)
        bounds = b.detach().cpu() if isinstance(b, torch.Tensor) else self.field_bounds()
        dev = self.device

        def sdf_fn(x):
            return model.sdf(x.to(dev)).cpu()

        if o.mesh_watertight:
            # a surface that leaves the field's box is closed by a cap on the box's faces: the
            # grid reaches two mesh cells beyond the box, where everything counts as outside
            lo, hi = bounds[0].clone(), bounds[1].clone()
            pad = 2 * float((hi - lo).max()) / o.mesh_resolution
            field_sdf = sdf_fn

            def sdf_fn(x):  # noqa: F811
                out = ((x < lo) | (x > hi)).any(-1)
                return torch.where(out, torch.full_like(x[:, 0], pad), field_sdf(x))

            bounds = torch.stack([lo - pad, hi + pad])
        v, f = extract_mesh(sdf_fn, bounds, resolution=o.mesh_resolution, coarse_to_fine=True,
                            progress=self.progress)
        scene = self.load()
        vw = to_world(v, scene.normalization)
        # keep what the input views can judge: faces inside some view's frustum, and, with
        # masks, inside the dilated object mask of every view that sees them (the mesh culling
        # of the DTU evaluations, METHOD.md 8.3)
        if o.mesh_watertight:
            vw, f, idx = largest_component(vw, f, return_index=True)
            return self._save_mesh(path, model, v[idx], vw, f, t0)
        vw, f, idx = cull_by_frusta(vw, f, scene.cameras)
        v = v[idx]
        if scene.masks is not None and o.use_masks:
            dil = max(2, round(12 * scene.width / 1600))  # METHOD.md 6.3's 12 px at 1600 wide
            vw, f, idx = cull_by_masks(vw, f, scene.cameras, scene.masks, dilation=dil)
            v = v[idx]
        vw, f, idx = largest_component(vw, f, return_index=True)
        v = v[idx]
        # after the largest component: culling splits the surface where no view looked, and
        # the parts it leaves are all observed (benchmarks/results/fast_preset.md, session 8)
        if o.mesh_cull_unseen:
            if self._wants_mesh_fit():
                # the fitted surface moved away from the rendered depth: the views' depth of
                # this mesh itself decides what they see
                depths = mesh_vertex_depths(vw, scene.cameras)
            else:
                depths = self._mesh_cull_depths(refined if o.finer_stage_optimization
                                                else None)
            if depths is None:
                log.warning("mesh: no rendered depth of the input views; faces hidden from "
                            "every view are kept")
            else:
                vw2, f2, idx = cull_unseen(vw, f, scene.cameras, depths, o.mesh_cull_tol)
                if len(f2):
                    vw, f, v = vw2, f2, v[idx]
                else:
                    log.warning("mesh: no face is visible in the rendered depth; visibility "
                                "culling skipped")
        return self._save_mesh(path, model, v, vw, f, t0)

    def _wants_poisson(self) -> bool:
        """`OutputConfig.mesh_method` = "poisson" applies: set and no watertight mesh (a Poisson
        surface opens where it meets its octree's box; the watertight mesh is the field's)."""
        o = self.cfg.output
        return o.mesh_method == "poisson" and not o.mesh_watertight

    def _poisson_mesh(self, path: Path, model, t0: float) -> Path:
        """`OutputConfig.mesh_method` = "poisson": the screened Poisson surface of
        OUT/points.ply, normals oriented by the input cameras and, where they straddle a
        point's tangent plane, by the field's gradient; culled like the field's mesh, with the
        mesh's own depth deciding what the views see; vertex colours from the points."""
        from svolsdf.fusion.mesh import (
            cull_by_frusta,
            cull_by_masks,
            cull_unseen,
            largest_component,
            mesh_vertex_depths,
            save_mesh,
        )
        from svolsdf.fusion.poisson import estimate_normals, orient_normals, poisson_surface
        from svolsdf.io.ply import read_ply

        o = self.cfg.output
        scene = self.load()
        d = read_ply(self.stage_fusion())
        pts, cols = d["points"], d["colors"]
        if len(pts) < 100:
            raise InputError(f"{self.out / 'points.ply'}: {len(pts)} fused points, too few for "
                             "a Poisson mesh (output.mesh_method = poisson); use "
                             "output.mesh_method = field")
        threads = max(1, torch.get_num_threads())
        normals = estimate_normals(pts, workers=threads)
        unit = scene.normalization.to_unit(torch.from_numpy(pts)).float()
        grads = []
        for x in unit.split(65536):  # the field's outward direction at each point
            x = x.to(self.device).requires_grad_(True)
            (g,) = torch.autograd.grad(model.sdf(x).sum(), x)
            grads.append(g.detach().cpu())
        normals = orient_normals(pts, normals, scene.cameras.centers.double().numpy(),
                                 guide=torch.cat(grads).double().numpy())
        v, f, c = poisson_surface(pts, normals, cols, depth=o.poisson_depth,
                                  trim=o.poisson_trim, threads=threads)
        vw, f = torch.from_numpy(v), torch.from_numpy(f)
        c = None if c is None else torch.from_numpy(c)

        def keep(idx):
            return None if c is None else c[idx]

        vw, f, idx = cull_by_frusta(vw, f, scene.cameras)
        c = keep(idx)
        if scene.masks is not None and o.use_masks:
            dil = max(2, round(12 * scene.width / 1600))  # as the field's mesh
            vw, f, idx = cull_by_masks(vw, f, scene.cameras, scene.masks, dilation=dil)
            c = keep(idx)
        vw, f, idx = largest_component(vw, f, return_index=True)
        c = keep(idx)
        if o.mesh_cull_unseen:
            vw2, f2, idx = cull_unseen(vw, f, scene.cameras, mesh_vertex_depths(vw, scene.cameras),
                                       o.mesh_cull_tol)
            if len(f2):
                vw, f, c = vw2, f2, keep(idx)
        save_mesh(path, vw, f, c, fmt=o.mesh_format)
        self._mark("mesh", self.keys["mesh"])
        self._time("mesh", t0, vertices=int(len(vw)), faces=int(len(f)), method="poisson",
                   points=int(len(pts)))
        return path

    def _save_mesh(self, path: Path, model, v: torch.Tensor, vw: torch.Tensor, f: torch.Tensor,
                   t0: float) -> Path:
        """Colour the mesh from the field (unit-frame vertices ``v``), write it (world vertices
        ``vw``, faces ``f``) and mark the mesh stage done."""
        from svolsdf.fusion.mesh import colors_from_fn, model_colour_fn, save_mesh, vertex_normals

        o = self.cfg.output
        dev = self.device
        cols = None
        try:
            cols = colors_from_fn(v, vertex_normals(v, f), model_colour_fn(model), device=dev)
        except Exception as e:  # colours are a convenience
            log.warning("mesh colours failed: %s", e)
        save_mesh(path, vw, f, cols, fmt=o.mesh_format)
        self._mark("mesh", self.keys["mesh"])
        self._time("mesh", t0, vertices=int(len(vw)), faces=int(len(f)))
        return path
