"""Validation of a `Config` against its annotations, limits and enumerations: one place, run
when YAML is read, when options are applied and when a pipeline is built."""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
import re
import types
from collections.abc import Mapping
from dataclasses import fields
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints

from svolsdf.config.schema import Config
from svolsdf.errors import InputError

__all__ = ["available_memory", "check_memory", "memory_needs", "validate_config"]


class _Rejected(Exception):
    """A value does not fit its field; ``args[0]`` says what would. ``near``: the value has the
    right type but is out of range (a union then reports this member alone)."""

    def __init__(self, wanted: str, near: bool = False):
        super().__init__(wanted)
        self.near = near


def _range_text(lim: dict) -> str:
    lo, hi, gt = lim.get("min"), lim.get("max"), lim.get("gt")
    if lo is not None and hi is not None:
        return f" in [{lo}, {hi}]"
    if gt is not None:
        return f" > {gt}"
    if lo is not None:
        return f" >= {lo}"
    if hi is not None:
        return f" <= {hi}"
    return ""


def _check_range(x: float, lim: dict, what: str) -> None:
    lo, hi, gt = lim.get("min"), lim.get("max"), lim.get("gt")
    if (lo is not None and x < lo) or (hi is not None and x > hi) or (gt is not None and x <= gt):
        raise _Rejected(what + _range_text(lim), near=True)


def _check_value(value: Any, tp: Any, lim: dict) -> Any:
    """``value`` checked against the annotation ``tp`` and the field's limits, normalized (an int
    where a float is wanted becomes a float, a tuple a list, a path a string).

    Raises:
        _Rejected: with the description of what is allowed.
    """
    origin, args = get_origin(tp), get_args(tp)
    if origin is Union or origin is types.UnionType:
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        wanted = []
        for a in options:
            try:
                return _check_value(value, a, lim)
            except _Rejected as e:
                if e.near:
                    raise
                wanted.append(str(e))
        if type(None) in args:
            wanted.append("null")
        raise _Rejected(" or ".join(wanted))
    if origin is Literal:
        if isinstance(value, str) and value in args:
            return value
        raise _Rejected(("one of " if len(args) > 1 else "") + ", ".join(repr(a) for a in args))
    if tp is bool:
        # YAML's quoted 'no' is a (truthy) string: only real booleans are accepted
        if isinstance(value, bool):
            return value
        raise _Rejected("true or false")
    if tp is int:
        what = "an integer" + _range_text(lim)
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise _Rejected(what)
        value = int(value)  # numpy integers too
        _check_range(value, lim, "an integer")
        return value
    if tp is float:
        what = "a number" + _range_text(lim)
        if isinstance(value, str):
            # YAML 1.1 (PyYAML) reads 1e-3 as a string: a plain number in a string is accepted
            try:
                value = float(value)
            except ValueError:
                raise _Rejected(what) from None
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise _Rejected(what)
        value = float(value)
        if not math.isfinite(value):
            raise _Rejected("a finite number" + _range_text(lim))
        _check_range(value, lim, "a number")
        return value
    if tp is str:
        if isinstance(value, os.PathLike):
            value = os.fspath(value)
        choices = lim.get("choices")
        if choices is not None:
            allowed = list(choices())
            if value not in allowed:
                raise _Rejected("one of " + ", ".join(repr(a) for a in allowed))
        if not isinstance(value, str):
            raise _Rejected("a string")
        pattern = lim.get("pattern")
        if pattern is not None and re.fullmatch(pattern, value) is None:
            raise _Rejected(lim.get("wanted", f"a string matching {pattern}"))
        return value
    if origin in (list, tuple):
        item_tp = args[0] if args else Any
        n, n_min = lim.get("len"), lim.get("min_len")
        item_lim = {k: v for k, v in lim.items() if k in ("min", "max", "gt")}
        item_what = {int: "integers", float: "numbers", str: "strings"}.get(item_tp, "items")
        what = (f"a list of {n} " if n is not None else
                f"a list of at least {n_min} " if n_min is not None else "a list of ") + \
            item_what + _range_text(item_lim)
        if lim.get("unique"):
            what += ", each once"
        if not isinstance(value, (list, tuple)):
            raise _Rejected(what)
        if (n is not None and len(value) != n) or (n_min is not None and len(value) < n_min):
            raise _Rejected(what, near=True)
        try:
            out = [_check_value(v, item_tp, item_lim) for v in value]
        except _Rejected as e:
            raise _Rejected(what, near=e.near) from None
        if lim.get("unique"):
            seen = set()
            for v in out:
                if v in seen:
                    raise _Rejected(f"{what} ({v} is repeated)", near=True)
                seen.add(v)
        return out
    if tp is Any:
        return value
    raise TypeError(f"validate_config: no rule for the annotation {tp!r}")  # a new field's


def _short(value: Any) -> str:
    r = repr(value)
    return r if len(r) <= 60 else r[:57] + "..."


def _validate_dataclass(obj: Any, prefix: str, where: str | None,
                        labels: Mapping[str, str]) -> None:
    hints = get_type_hints(type(obj))
    for f in fields(obj):
        key = prefix + f.name
        value = getattr(obj, f.name)
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            if not isinstance(value, tp):
                raise InputError(f"{where + ': ' if where else ''}{key}: expected a mapping of "
                                 f"{', '.join(g.name for g in fields(tp))}")
            _validate_dataclass(value, key + ".", where, labels)
            continue
        try:
            setattr(obj, f.name, _check_value(value, tp, f.metadata.get("limits", {})))
        except _Rejected as e:
            name = f"{labels[key]} ({key})" if key in labels else key
            raise InputError(f"{where + ': ' if where else ''}{name} = {_short(value)}: "
                             f"expected {e}") from None


def validate_config(cfg: Config, where: str | None = None,
                    labels: Mapping[str, str] | None = None) -> Config:
    """Check every field of ``cfg`` against its type annotation and limits, in place.

    The one check of a run's configuration, made when it is built (from YAML, from command-line
    options or in code) and before any stage runs: types (a string where a number is wanted, a
    quoted 'no' where a boolean is), enumerations (``Literal``), ranges and list lengths
    (`_limited`), and the combinations of options that cannot run. Ints given for floats
    become floats, tuples lists.

    Args:
        cfg: the configuration; normalized in place and returned.
        where: what the values came from (a file name), to begin the message with.
        labels: dotted key -> the option that set it (``{"train.steps": "--steps"}``).

    Raises:
        InputError: naming the dotted key (and its option), the value and what is allowed.
    """
    if not isinstance(cfg, Config):
        raise InputError(f"{where or 'config'}: expected a Config, got {type(cfg).__name__}")
    labels = labels or {}
    _validate_dataclass(cfg, "", where, labels)
    _check_combinations(cfg, f"{where}: " if where else "", labels)
    check_memory(cfg, where=where, labels=labels)
    return cfg


#: the smallest working side a run accepts (`svolsdf.scene.checks.MIN_SIDE`): without
#: ``scene.image_size`` the memory estimate assumes images this small, so it is a lower bound
_MIN_SIDE = 16


def memory_needs(cfg: Config, size: tuple[int, int] | None = None, views: int | None = None
                 ) -> list[tuple[tuple[str, ...], float, str]]:
    """Lower bounds of the largest allocations the options ask for, in bytes.

    Each bound counts only what the run surely allocates, so that a run the machine can hold is
    never refused:

    - what the field kind declares (`svolsdf.field.kinds.FieldKind.memory`: the grid field's
      SDF grid, values and gradients), when the run fits a field;
    - the MVS probability volumes, float32 hypotheses and probabilities (D, H_k, W_k) per view
      (`svolsdf.mvs.volume.ProbabilityVolume`): stage 1 for every input view (kept in memory
      through the run), or one view of a finer stage, 2 x D_k x H_k x W_k x 4 bytes, the stage
      size at ``mvs.scale`` (at least 1) x the working size over 2^(3 - k).

    Args:
        cfg: the run's configuration.
        size: the working size (W, H); default ``scene.image_size``, else the smallest a run
            accepts (16 x 16).
        views: input views; default the number ``scene.views`` lists, else 2.

    Returns:
        [(the options that set the allocation, bytes, what it is)].
    """
    W, H = size or cfg.scene.image_size or (_MIN_SIDE, _MIN_SIDE)
    at = "the" if size or cfg.scene.image_size else "the smallest"
    n_views = views or (len(cfg.scene.views) if cfg.scene.views else 2)
    out = []
    if cfg.train.mode != "mvs-only":  # the field kind's own (`FieldKind.memory`)
        from svolsdf.field.kinds import get_field_kind

        memory = get_field_kind(cfg.field.kind).memory
        out.extend(memory(cfg.field) if memory is not None else [])
    if cfg.train.mode != "volsdf":
        scale = max(1.0, float(cfg.mvs.scale or 1.0))
        need, stage = 0.0, 1
        for k, d in enumerate(cfg.mvs.ndepths, start=1):
            s = 2 ** (len(cfg.mvs.ndepths) - k)
            hw = max(1, round(W * scale / s)) * max(1, round(H * scale / s))
            b = 2.0 * d * hw * 4 * (n_views if k == 1 else 1)
            if b > need:
                need, stage = b, k
        n = n_views if stage == 1 else 1
        out.append((("mvs.ndepths", *(("mvs.scale",) if cfg.mvs.scale is not None else ())), need,
                    f"the stage-{stage} MVS volume{'s' if n > 1 else ''} ({n} view"
                    f"{'s' if n > 1 else ''} at {at} working size {W}x{H})"))
    return out


def available_memory() -> int | None:
    """Bytes of memory the machine can give a new run now (psutil, else /proc/meminfo's
    MemAvailable, else the free physical pages); None when none of them answers."""
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except Exception:  # noqa: BLE001  (not installed, or no answer on this system)
        pass
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (OSError, ValueError, AttributeError):
        return None


def check_memory(cfg: Config, size: tuple[int, int] | None = None, views: int | None = None,
                 where: str | None = None, labels: Mapping[str, str] | None = None) -> None:
    """Refuse options whose allocations (`memory_needs`, lower bounds) exceed the memory the
    machine has available (`available_memory`; not checked when it cannot be read).

    Raises:
        InputError: naming the option (with the command-line option that set it), the memory
            it needs and the memory available.
    """
    have = available_memory()
    if have is None:
        return
    labels = labels or {}
    for keys, need, what in memory_needs(cfg, size, views):
        if need > have:
            shown = ", ".join(_option(cfg, k, labels) for k in keys)
            raise InputError(f"{where + ': ' if where else ''}{shown}: {what} would take at "
                             f"least {_gb(need)} of memory, but {_gb(have)} is available; "
                             "choose a smaller value")


def _option(cfg: Config, key: str, labels: Mapping[str, str]) -> str:
    """``key`` and its value as the user gave it (``--set key=value``, ``--flag value (key)``)."""
    section, name = key.split(".")
    value = _short(getattr(getattr(cfg, section), name))
    label = labels.get(key)
    if label is None:
        return f"{key} = {value}"
    return f"{label}={value}" if label == f"--set {key}" else f"{label} {value} ({key})"


def _gb(n: float) -> str:
    return f"{n / 2**30:.3g} GB" if n < 2**50 else f"{n / 2**50:.3g} PB"


def _check_combinations(cfg: Config, head: str, labels: Mapping[str, str]) -> None:
    """The pairs of options where one would silently disable or contradict the other.

    Raises:
        InputError: one line naming both options (with the command-line option that set each,
            from ``labels``) and what to do.
    """
    t, f = cfg.train, cfg.field

    def opt(key: str, value: Any) -> str:
        shown = value if isinstance(value, str) else _short(value)
        label = labels.get(key)
        if label is None:
            return f"{key} = {shown}"
        return f"{label}={shown}" if label == f"--set {key}" else f"{label} {shown} ({key})"

    def refuse(a: str, va: Any, b: str, vb: Any, why: str) -> None:
        raise InputError(f"{head}{opt(a, va)} with {opt(b, vb)}: {why}")

    if cfg.mvs.finer_stage_optimization and (t.mode != "svolsdf" or t.ablation is not None):
        which = ("train.mode", t.mode) if t.mode != "svolsdf" else ("train.ablation", t.ablation)
        refuse("mvs.finer_stage_optimization", True, *which,
               "the finer-stage optimization needs train.mode svolsdf without train.ablation "
               "(it optimizes the field against the stage-2 volumes)")
    if cfg.mvs.third_stage_optimization and not cfg.mvs.finer_stage_optimization:
        refuse("mvs.third_stage_optimization", True, "mvs.finer_stage_optimization", False,
               "the optimization after stage 3 follows the one after stage 2 (stages 1, 2, 3); "
               "set mvs.finer_stage_optimization=true too")
    # a baseline never sees MVS, or it would not be the baseline the paper compares with: the
    # ablations run stage-1 MVS, and the mvs rule reads its depth into the guide
    if t.ablation is not None and t.mode != "svolsdf":
        refuse("train.mode", t.mode, "train.ablation", t.ablation,
               "the ablations change S-VolSDF's prior; "
               + ("a VolSDF baseline must never see MVS" if t.mode == "volsdf"
                  else "mvs-only fits no field") + ": drop the ablation or use train.mode svolsdf")
    if t.mode == "volsdf" and cfg.guide.low_weight_rule == "mvs":
        refuse("train.mode", t.mode, "guide.low_weight_rule", cfg.guide.low_weight_rule,
               "the mvs rule fills the guide with stage-1 MVS depth, which a VolSDF baseline "
               "must never see: use guide.low_weight_rule=max")
    if cfg.fusion.network is not None and t.mode != "svolsdf":
        refuse("train.mode", t.mode, "fusion.network", cfg.fusion.network,
               "the fusion network starts from the field's guide in svolsdf mode only; "
               "leave fusion.network unset")
    if cfg.fusion.network_weights is not None and cfg.fusion.network is None:
        refuse("fusion.network_weights", cfg.fusion.network_weights,
               "fusion.network", None, "the weights are of the fusion network; set "
               "fusion.network too or leave the weights out")
    # what the mesh method declares (svolsdf.fusion.mesh_methods.MeshMethod), never its name
    from svolsdf.fusion.mesh_methods import get_mesh_method, registered_mesh_methods

    method = get_mesh_method(cfg.mesh.method)
    if t.mode == "mvs-only" and method.needs_field:
        # no mesh stage runs without a field (svolsdf.pipeline.options.has_field), so no
        # mesh.method makes a mesh in mvs-only: the way out must not promise one
        of_points = [n for n in registered_mesh_methods() if get_mesh_method(n).needs_points]
        refuse("train.mode", t.mode, "mesh.method", cfg.mesh.method,
               "mvs-only fits no field and makes no mesh of any method, only points.ply: for "
               "a mesh use train.mode svolsdf (or volsdf); for the points alone set "
               f"mesh.method to a method of the points ({', '.join(of_points)}), which "
               "mvs-only leaves unused")
    # a scale the backbone cannot run at would stop the run at the backbone's construction
    from svolsdf.config.presets import MVS_SCALE_BY_BACKBONE
    from svolsdf.mvs.backbone import backbone_scale_problem

    why = backbone_scale_problem(cfg.mvs.backbone, cfg.mvs.scale)
    if why is not None:
        whose = [b for b, v in MVS_SCALE_BY_BACKBONE.get(cfg.preset, {}).items()
                 if v == cfg.mvs.scale and b != cfg.mvs.backbone]
        refuse("mvs.scale", cfg.mvs.scale, "mvs.backbone", cfg.mvs.backbone,
               why + (f" ({cfg.mvs.scale:g} is the {cfg.preset} preset's scale for "
                      f"{whose[0]})" if whose and "mvs.scale" not in labels else "")
               + ": leave mvs.scale unset (--set mvs.scale=null) for the backbone's own size")
    if cfg.mesh.watertight and not method.closed:
        closed = [n for n in registered_mesh_methods() if get_mesh_method(n).closed]
        refuse("mesh.watertight", True, "mesh.method", cfg.mesh.method,
               f"the {cfg.mesh.method} method gives no closed surface (a mesh of the points "
               f"opens where no point is): use mesh.method={' or '.join(closed)} or drop "
               "mesh.watertight")
    if 0 < t.beta_start < t.beta_end:
        refuse("train.beta_start", t.beta_start, "train.beta_end", t.beta_end,
               "beta is annealed from beta_start down to beta_end (a sharper surface at the "
               "end): give beta_start >= beta_end, or 0 for a learned beta")
    # the field kind's own checks (svolsdf.field.kinds.FieldKind.check), told whether the field
    # starts from the MVS surface (svolsdf.field.kinds.starts_from_mvs: a kind that can, in
    # svolsdf mode with init mvs, not the soft-consistency ablation); then a kind that cannot
    # refuses init mvs where it would act (the MLP's check says so in its own words first)
    from svolsdf.field.kinds import get_field_kind, registered_field_kinds, starts_from_mvs

    kind = get_field_kind(f.kind)
    from_mvs = starts_from_mvs(f, t)
    refused = kind.check(f, t, not from_mvs) if kind.check is not None else None
    if refused is not None:
        refuse(*refused)
    if not kind.starts_from_mvs and f.init == "mvs" and t.mode == "svolsdf":
        starting = [n for n in registered_field_kinds() if get_field_kind(n).starts_from_mvs]
        refuse("field.kind", f.kind, "field.init", f.init,
               f"the {f.kind} field starts from VolSDF's sphere, not from the MVS surface "
               f"(only {', '.join(starting)} can): use field.init=sphere")
