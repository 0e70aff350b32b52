"""The run folder below every command: `RunFolder` reads it (the paths of its files, views.json,
timing.json, metrics.json, which outputs it holds); the lock, atomic writes with unique temporary
names and the record of which config made each output (its provenance) are shared by every
command that writes one.

The pipeline's `svolsdf.pipeline.RunDir` is a `RunFolder` with the writing side (stage state,
views.json, timing.json, OUT/log); the commands over finished runs (evaluate, report, render,
benchmark, mvs) read through `RunFolder`. Its config.yaml is read by the config package's loader,
which sits above this module: ``svolsdf.config.load_config(RunFolder(out).config_file)``. Two
commands never write one folder at once, a full disk never leaves a half file under a final name,
and scores are never given to outputs that another config made. docs/run-folder.md explains the
choices.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import logging
import os
import re
import secrets
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from svolsdf.errors import InputError

__all__ = ["LOCK_NAME", "MVS_NAMES", "MVS_STATE", "OUTPUT_STAGES", "RUN_NAMES", "RunFolder",
           "RunViews", "atomic_write", "config_digest", "file_record", "folder_lock",
           "foreign_names", "lock_holder", "mesh_source", "output_provenance", "read_stage_state",
           "refuse_in_progress", "unique_temp"]

log = logging.getLogger(__name__)

LOCK_NAME = ".svolsdf.lock"
"""The lock file of a run folder."""

RUN_NAMES = frozenset({
    "config.yaml", "views.json", "stages.json", "timing.json", "log", LOCK_NAME,
    "mvs", "depth", "confidence", "field", "normals", "unguided", "network",
    "points.ply", "mesh.ply", "mesh.obj", "renders", "renders_ibr", "metrics.json", "report.html",
    "demo_metrics.json", "benchmark_row.json", "run.json", "export"})
"""The names at the top of a run folder of ``svolsdf reconstruct`` (the layout of `RunFolder`,
with what evaluate, report, render, export, demo and a benchmark job add): a folder that holds
others is no run."""

MVS_NAMES = frozenset({"mvs", "depth", "confidence", "points.ply", "mvs.json", LOCK_NAME})
"""The names at the top of an output folder of ``svolsdf mvs`` (`svolsdf.commands.mvs`)."""

MVS_STATE = "mvs/stages.json"
"""Where an output folder of ``svolsdf mvs`` records its finished stages (a stages.json at the
top names a run of ``svolsdf reconstruct``)."""

#: files a desktop leaves in any folder it shows: not the user's data
_SYSTEM_FILES = frozenset({".DS_Store", "Thumbs.db", "desktop.ini"})
#: a temporary of `unique_temp` (``.NAME.<pid>.<random>.tmp<suffix>``) that a killed write left
_TEMPORARY = re.compile(r"\..+\.\d+\.[0-9a-f]{8}\.tmp.*")

OUTPUT_STAGES = {"points.ply": "fusion", "mesh.ply": "mesh", "mesh.obj": "mesh",
                 "renders": "render"}
"""The outputs that evaluate and report read, and the record (a stage of OUT/stages.json, or
``render``) that names the config which made each."""


# --------------------------------------------------------------------------- reading
@dataclass(frozen=True)
class RunViews:
    """OUT/views.json: the views a run used."""

    inputs: list[int]
    """The input view ids."""
    test: list[int]
    """The held-out test view ids (the scene's views that are not inputs)."""
    size: tuple[int, int] | None
    """The working size (W, H), None when the file does not say."""
    scene: str | None
    """The scene folder, None when the file does not say."""


class RunFolder:
    """A run folder, read: every path of a run and what its bookkeeping files hold. It writes
    nothing (`svolsdf.pipeline.RunDir` adds the writing side).

    Layout (docs/architecture.md "Data flow"; `svolsdf.pipeline` writes it):

    - ``config.yaml``, ``views.json`` (inputs, test views, working size, scene), ``stages.json``
      (stage -> key of the config it finished under; "provenance": stage -> the key of its
      inputs and the digest of the config.yaml it finished or was last reused under;
      "manifest": the input files, `svolsdf.pipeline.keys.input_manifest`; "outputs": stage ->
      {file: `file_record`} of the files it wrote when it finished), ``timing.json``,
      ``log``, ``.svolsdf.lock`` (`folder_lock`: every command that writes here);
    - ``mvs/stage1/<id>.npz`` (stages 2-3 too with ``mvs.save_volumes``), ``depth/<id>.npy``
      (+ .png), ``confidence/<id>.npy``;
    - ``field/model.pt`` (+ checkpoints), ``field/render_depth/<id>.npy``, ``field/render_rgb/``,
      ``normals/``, ``field/stage2/`` (the finer-stage optimization), ``field/surface.pt``;
    - ``unguided/{depth,confidence}/<id>.npy``, ``network/{depth,confidence}/<id>.npy``;
    - ``points.ply``, ``mesh.ply`` (or ``mesh.obj``);
    - after ``svolsdf render``: ``renders/<id>.png``, ``renders_ibr/<id>.png``; after
      ``svolsdf evaluate``: ``metrics.json`` and ``report.html``.

    Args:
        root: the folder (need not exist).
    """

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.root)!r})"

    # ------------------------------------------------------------------ paths
    @property
    def config_file(self) -> Path:
        """The run's config (load it with `svolsdf.config.load_config`)."""
        return self.root / "config.yaml"

    @property
    def views_file(self) -> Path:
        return self.root / "views.json"

    @property
    def stages_file(self) -> Path:
        return self.root / "stages.json"

    @property
    def timing_file(self) -> Path:
        return self.root / "timing.json"

    @property
    def metrics_file(self) -> Path:
        return self.root / "metrics.json"

    @property
    def report_file(self) -> Path:
        return self.root / "report.html"

    @property
    def log_file(self) -> Path:
        return self.root / "log"

    @property
    def run_file(self) -> Path:
        """run.json: the command, version, device and date of the last finished run."""
        return self.root / "run.json"

    @property
    def points(self) -> Path:
        return self.root / "points.ply"

    def mesh(self, fmt: str = "ply") -> Path:
        """OUT/mesh.ply, or OUT/mesh.obj for ``fmt`` "obj"."""
        return self.root / ("mesh.obj" if fmt == "obj" else "mesh.ply")

    @property
    def field_dir(self) -> Path:
        return self.root / "field"

    @property
    def model(self) -> Path:
        """The fitted field (OUT/field/model.pt)."""
        return self.field_dir / "model.pt"

    @property
    def refined_model(self) -> Path:
        """The field after the finer-stage optimization (OUT/field/stage2/model.pt)."""
        return self.field_dir / "stage2" / "model.pt"

    @property
    def surface_model(self) -> Path:
        """The field refined through the fused points (OUT/field/surface.pt)."""
        return self.field_dir / "surface.pt"

    def render_depth_dir(self, refined: bool = False) -> Path:
        """The field's rendered depth of the input views (the refined field's with
        ``refined``)."""
        return self.field_dir / ("stage2/render_depth" if refined else "render_depth")

    def stage1_file(self, view: int) -> Path:
        return self.root / "mvs" / "stage1" / f"{view}.npz"

    @property
    def depth_dir(self) -> Path:
        return self.root / "depth"

    @property
    def normals_dir(self) -> Path:
        return self.root / "normals"

    @property
    def unguided_dir(self) -> Path:
        return self.root / "unguided"

    @property
    def network_dir(self) -> Path:
        return self.root / "network"

    def renders_dir(self, ibr: bool = False) -> Path:
        """OUT/renders (volume rendering), or OUT/renders_ibr with ``ibr``."""
        return self.root / ("renders_ibr" if ibr else "renders")

    def view_files(self, folder: Path, views: Sequence[int], suffix: str = ".npy"
                   ) -> dict[int, Path]:
        """{view: folder/<view><suffix>}."""
        return {v: folder / f"{v}{suffix}" for v in views}

    def stage_outputs(self, stage: str, views: Sequence[int]) -> list[Path]:
        """The files of this folder that ``stage`` of `svolsdf.pipeline` writes for the input
        ``views`` and that exist (what its finished marker records, `file_record`): mvs1 the
        stage-1 volumes, field model.pt, guide the rendered depth, mvs23 the final depth and
        confidence (and the stage-2/3 volumes of ``mvs.save_volumes``), unguided its depth and
        confidence, fusion points.ply; [] for another name (the mesh stage names its file)."""
        per_view = {"mvs1": ["mvs/stage1/{}.npz"], "guide": ["field/render_depth/{}.npy"],
                    "mvs23": ["depth/{}.npy", "confidence/{}.npy", "mvs/stage2/{}.npz",
                              "mvs/stage3/{}.npz"],
                    "unguided": ["unguided/depth/{}.npy", "unguided/confidence/{}.npy"]}
        whole = {"field": [self.model], "fusion": [self.points]}
        files = whole.get(stage) or [self.root / f.format(v) for f in per_view.get(stage, [])
                                     for v in views]
        return [f for f in files if f.is_file()]

    # ------------------------------------------------------------------ what it holds
    def is_run(self) -> bool:
        """A reconstruct wrote config.yaml and views.json here."""
        return self.config_file.is_file() and self.views_file.is_file()

    def missing_run_files(self) -> str | None:
        """What a run folder lacks here ("config.yaml and views.json", ...), None for a run."""
        missing = [p.name for p in (self.config_file, self.views_file) if not p.is_file()]
        return " and ".join(missing) or None

    def render_files(self, ibr: bool = False, views: Sequence[int] | None = None
                     ) -> dict[int, Path]:
        """{view id: OUT/renders/<id>.png} (OUT/renders_ibr with ``ibr``) sorted by id, only
        ``views`` when given; {} without the folder."""
        folder = self.renders_dir(ibr)
        if not folder.is_dir():
            return {}
        files = {int(p.stem): p for p in folder.glob("*.png") if re.fullmatch(r"\d+", p.stem)}
        if views is not None:
            files = {v: files[v] for v in views if v in files}
        return dict(sorted(files.items()))

    def outputs(self) -> list[str]:
        """The outputs evaluate and report read that the folder holds, of points.ply,
        mesh.ply, renders and renders_ibr (a folder counts with a <view id>.png in it)."""
        return [n for n in ("points.ply", "mesh.ply") if (self.root / n).is_file()] + [
            n for n, ibr in (("renders", False), ("renders_ibr", True)) if self.render_files(ibr)]

    def views(self) -> RunViews | None:
        """OUT/views.json; None when the file is missing or unreadable (a warning says so)."""
        p = self.views_file
        if not p.is_file():
            return None
        try:
            d = json.loads(p.read_text())
            size = d.get("size")
            return RunViews(inputs=[int(v) for v in d.get("inputs") or []],
                            test=[int(v) for v in d.get("test") or []],
                            size=(int(size[0]), int(size[1])) if size else None,
                            scene=str(d["scene"]) if d.get("scene") else None)
        except (OSError, ValueError, TypeError, AttributeError, IndexError, KeyError):
            log.warning("%s is unreadable (expected a JSON object with lists 'inputs' and "
                        "'test'); its views are not used", p)
            return None

    def timing(self) -> dict | None:
        """OUT/timing.json ({stage: {...}}): {} when the file is missing, None when it is
        unreadable."""
        return _json_object(self.timing_file, missing={})

    def run_info(self) -> dict:
        """OUT/run.json ({command, version, device, torch, date}, the last finished run's); {}
        when the file is missing or unreadable."""
        return _json_object(self.run_file, missing={}) or {}

    def metrics(self) -> dict | None:
        """OUT/metrics.json (`svolsdf evaluate`); None when the file is missing.

        Raises:
            InputError: the file is not a JSON object, naming it.
        """
        p = self.metrics_file
        if not p.is_file():
            return None
        m = _json_object(p)
        if m is None:
            raise InputError(f"{p}: not valid JSON (a JSON object); run svolsdf evaluate "
                             f"{self.root} to write it again")
        return m

    def stage_state(self) -> dict:
        """OUT/stages.json as a dict ({} when missing or unreadable, `read_stage_state`)."""
        return read_stage_state(self.root)

    def changed_output(self, stage: str) -> str | None:
        """How a file that ``stage`` recorded when it finished (`svolsdf.pipeline.RunDir.mark`)
        differs from it now: missing,
        of another size, or of another content (a truncated or replaced file); None when all
        match or none is recorded (a folder made before the record)."""
        rec = (_json_object(self.stages_file) or {}).get("outputs")
        rec = rec.get(stage) if isinstance(rec, dict) else None
        for name, was in (rec.items() if isinstance(rec, dict) else ()):
            f = self.root / name
            if not f.is_file():
                return f"{f} is missing"
            now = file_record(f)
            if isinstance(was, dict) and was.get("size") not in (None, now["size"]):
                return f"{f} has {now['size']} bytes, {was['size']} when the stage finished"
            if isinstance(was, dict) and was.get("blake2b") not in (None, now["blake2b"]):
                return f"{f} changed since the stage finished (another blake2b digest)"
        return None

    def output_provenance(self, outputs: list[str]) -> dict[str, str]:
        """Whether config.yaml made each of ``outputs`` (`output_provenance`)."""
        return output_provenance(self.root, outputs)

    def mesh_source(self) -> str | None:
        """Which surface OUT/mesh.ply is, from timing.json (`mesh_source`)."""
        return mesh_source(self.timing())


def foreign_names(folder: str | Path, names: frozenset[str]) -> list[str]:
    """The entries of ``folder`` that a command writing ``names`` (`RUN_NAMES`, `MVS_NAMES`) did
    not write, sorted; a killed write's temporary and a desktop's index files do not count.

    Args:
        folder: an existing folder.
        names: the names the command writes at the folder's top.
    """
    return sorted(p.name for p in Path(folder).iterdir()
                  if p.name not in names and p.name not in _SYSTEM_FILES
                  and not _TEMPORARY.fullmatch(p.name))


def _json_object(path: Path, missing: dict | None = None) -> dict | None:
    """The JSON object in ``path``; ``missing`` when there is no file, None when it is not a
    JSON object."""
    if not path.is_file():
        return missing
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    return d if isinstance(d, dict) else None


def mesh_source(timing: dict | None) -> str | None:
    """Which surface OUT/mesh.ply is: "field", "poisson", "tsdf", or "field (poisson failed:
    REASON)" when the method asked for gave no mesh and the field's zero level replaced it;
    None when the run made no mesh (or its timing.json does not say).

    Args:
        timing: the parsed OUT/timing.json ({stage: {...}}), or None.
    """
    m = (timing or {}).get("mesh")
    if not isinstance(m, dict):
        return None
    if m.get("mesh_source"):
        return str(m["mesh_source"])
    # run folders written before mesh_source existed
    if m.get("poisson_failed"):
        return f"field (poisson failed: {m['poisson_failed']})"
    return str(m.get("method") or "field")


# --------------------------------------------------------------------------- lock
def lock_holder(folder: str | Path) -> str | None:
    """Who holds FOLDER's lock (`folder_lock`) now, as it wrote itself there
    (``"svolsdf reconstruct, pid 123"``); None when no process holds it (or there is no lock
    file, or no ``fcntl``). A reader asks before it judges the folder's files: a run in progress
    has written its new config.yaml but not yet the outputs that go with it.

    Args:
        folder: a folder.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        return None
    try:
        f = open(Path(folder) / LOCK_NAME)  # noqa: SIM115 - closed below
    except OSError:
        return None
    with f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            return " ".join(f.read().split()) or "pid ?"
        fcntl.flock(f.fileno(), fcntl.LOCK_UN)
    return None


def refuse_in_progress(folder: str | Path) -> None:
    """Refuse a run folder that another command is writing now (`lock_holder`), before its files
    are judged: what it holds is not yet the run's.

    Raises:
        InputError: naming the holder (command and pid) and the lock file.
    """
    holder = lock_holder(folder)
    if holder is not None:
        raise InputError(_held(Path(folder), holder, "wait for it to finish, then run this "
                                                     "again"))


def _held(folder: Path, holder: str, way: str) -> str:
    """The one line of a folder whose lock ``holder`` holds."""
    return (f"{folder}: another svolsdf run ({holder}) is writing this folder, in progress "
            f"(it holds {folder / LOCK_NAME}); {way}")


@contextlib.contextmanager
def folder_lock(folder: str | Path, command: str) -> Iterator[None]:
    """Hold an exclusive lock on FOLDER/.svolsdf.lock while ``command`` writes the folder.

    The lock is an advisory ``flock`` that the operating system drops when the process ends, so a
    killed command never leaves a stale lock behind. Where ``fcntl`` does not exist (Windows)
    folders are not locked. One process taking the lock twice (through two open files) is
    refused too, so callers take it once, at their entry point.

    Args:
        folder: an existing folder.
        command: what writes (``svolsdf evaluate``), named to whoever finds the folder locked.

    Raises:
        InputError: another process holds the folder; the message names the folder, the command
            and its pid.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    folder = Path(folder)
    f = open(folder / LOCK_NAME, "a+")  # noqa: SIM115 - held for the whole command
    try:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.seek(0)
            holder = " ".join(f.read().split()) or "pid ?"
            raise InputError(_held(folder, holder, "wait for it or choose another output "
                                                   "folder")) from None
        f.seek(0)
        f.truncate()
        f.write(f"{command}, pid {os.getpid()}")
        f.flush()
        yield
    finally:
        f.close()


# --------------------------------------------------------------------------- atomic writes
def unique_temp(path: str | Path, suffix: str = "") -> Path:
    """Create an empty file with a name no other writer uses, beside ``path``
    (``.NAME.<pid>.<random>.tmp<suffix>``), with the permissions a new file gets (the umask's,
    not mkstemp's owner-only)."""
    path = Path(path)
    while True:
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp{suffix}")
        try:
            os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
            return tmp
        except FileExistsError:  # pragma: no cover - 32 random bits
            continue


def atomic_write(path: str | Path, write: Callable[[Path], None], suffix: str = "") -> Path:
    """Write ``path`` through a uniquely named temporary file beside it, then rename it.

    A failure (a full disk, a killed process aside) removes the temporary file and leaves the
    previous ``path`` as it was; two writers of one file never share a temporary name.

    Args:
        path: the target; its folder is created.
        write: called with the temporary path; writes the whole file there.
        suffix: the temporary file's suffix, for writers that add or need one (np.save: .npy).

    Raises:
        InputError: the file cannot be written (no space left, read-only, ...); the message
            names ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        tmp = unique_temp(path, suffix)
    except OSError as e:
        raise InputError(f"{path}: cannot write it ({e.strerror or e})") from None
    try:
        write(tmp)
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        if e.errno == errno.ENOSPC:
            raise InputError(f"{path}: cannot write it, the disk is full; free some space and "
                             "rerun (finished files are kept)") from None
        raise InputError(f"{path}: cannot write it ({e.strerror or e})") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


# --------------------------------------------------------------------------- provenance
def file_record(path: str | Path) -> dict:
    """{"size": bytes, "blake2b": 32-hex digest of the content} of a file, as a stage's finished
    marker records each file it wrote, so that a rerun notices a truncated or replaced output
    (docs/run-folder.md "Finished outputs are checked")."""
    h = hashlib.blake2b(digest_size=16)
    size = 0
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
            size += len(chunk)
    return {"size": size, "blake2b": h.hexdigest()}


def config_digest(path: str | Path) -> str | None:
    """12-hex digest of a config.yaml's values (comments and layout do not count); None when the
    file is missing or is not YAML."""
    import yaml

    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, ValueError, yaml.YAMLError):
        return None
    text = json.dumps(data, sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def read_stage_state(folder: str | Path) -> dict:
    """FOLDER/stages.json as a dict ({} when missing or unreadable)."""
    try:
        st = json.loads((Path(folder) / "stages.json").read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return {}
    return st if isinstance(st, dict) else {}


def output_provenance(folder: str | Path, outputs: list[str]) -> dict[str, str]:
    """Whether each of ``outputs`` (names of `OUTPUT_STAGES`, or stages such as "field") was
    made under FOLDER/config.yaml.

    Returns:
        {output: "config.yaml" (made under it) | "unknown" (no record: a folder from before the
        record, or of svolsdf mvs) | "another config" (made by an earlier config: a rerun with
        new options stopped before it made this output again)}.
    """
    folder = Path(folder)
    prov = read_stage_state(folder).get("provenance")
    digest = config_digest(folder / "config.yaml")
    res = {}
    for name in outputs:
        rec = prov.get(OUTPUT_STAGES.get(name, name)) if isinstance(prov, dict) else None
        made = rec.get("config") if isinstance(rec, dict) else None
        if made is None or digest is None:
            res[name] = "unknown"
        else:
            res[name] = "config.yaml" if made == digest else "another config"
    return res
