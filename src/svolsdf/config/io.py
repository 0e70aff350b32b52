"""Configs to and from YAML and the command line: load, save, dotted overrides (``--set``), and
the commented YAML of `svolsdf config`.

An option has one name from the YAML file to the code: each component reads its own section
under the section's names (``mvs.crop_to_masks`` is the plane sweep's ``crop_to_masks``,
``fusion.guided_dilation`` the fusion filter's ``guided_dilation``; tests/test_option_names.py
checks every hand-off). `RENAMED` is the one table of older names, and its purpose is reading
old YAML files: config files, the config.yaml of run folders written before the component
sections, and ``--set`` given an old name, all read as the new names with one deprecation line.
No component uses the old names; `legacy_layout` lays a config out under them only for the
earlier stage-key formula, by which the runner recognises the run folders written before the
renaming (`svolsdf.pipeline.legacy_keys`).
"""

from __future__ import annotations

import dataclasses
import difflib
import logging
import os
import textwrap
from collections.abc import Mapping
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

import yaml

from svolsdf.config.presets import PRESETS, follow_backbone, preset
from svolsdf.config.schema import Config
from svolsdf.config.validate import _short, validate_config
from svolsdf.errors import InputError

__all__ = ["load_config", "save_config", "config_from_dict", "apply_overrides", "parse_set",
           "option_docs", "config_yaml", "known_keys", "RENAMED", "legacy_layout"]

log = logging.getLogger("svolsdf.config")

#: option names of the flat ``output`` section, before the component sections -> their names
#: now: for reading old YAML files only (the module's docstring). Config files, run folders'
#: config.yaml and ``--set`` still take the old names: `config_from_dict` and `apply_overrides`
#: read them as the new ones and say so in one deprecation line; `legacy_layout` gives them to
#: the earlier stage-key formula, which recognises run folders made before the change, so they
#: keep their finished stages.
RENAMED: dict[str, str] = {
    "output.mesh_method": "mesh.method",
    "output.mesh_resolution": "mesh.resolution",
    "output.mesh_format": "mesh.format",
    "output.mesh_cull_unseen": "mesh.cull_unseen",
    "output.mesh_cull_tol": "mesh.cull_tol",
    "output.mesh_watertight": "mesh.watertight",
    "output.mesh_fit_points": "mesh.fit_points",
    "output.mesh_free_space": "mesh.free_space",
    "output.mesh_free_space_steps": "mesh.free_space_steps",
    "output.mesh_support": "mesh.support",
    "output.poisson_depth": "mesh.poisson.depth",
    "output.poisson_trim": "mesh.poisson.trim",
    "output.tsdf_resolution": "mesh.tsdf.resolution",
    "output.tsdf_truncation_steps": "mesh.tsdf.truncation_steps",
    "output.fusion_dist": "fusion.dist",
    "output.fusion_rel": "fusion.rel",
    "output.fusion_views": "fusion.min_views",
    "output.fusion_conf": "fusion.conf",
    "output.fusion_surface": "fusion.surface",
    "output.fusion_guided_dilation": "fusion.guided_dilation",
    "output.fusion_unguided_dilation": "fusion.unguided_dilation",
    "output.fusion_unguided": "fusion.unguided",
    "output.fusion_network": "fusion.network",
    "output.fusion_network_weights": "fusion.network_weights",
    "output.use_masks": "scene.use_masks",
    "output.guide_mask_dilation": "guide.mask_dilation",
    "output.low_weight_rule": "guide.low_weight_rule",
    "output.finer_stage_optimization": "mvs.finer_stage_optimization",
}


_OUTPUT_GONE = ("the output section's options are now in the sections guide, fusion and mesh, "
                "and scene.use_masks, mvs.finer_stage_optimization; `svolsdf config` lists them")


def _deprecated(where: str, old: list[str]) -> None:
    """The one deprecation line for the old option names ``old`` read from ``where``."""
    if old:
        pairs = ", ".join(f"{k} -> {RENAMED[k]}" for k in old[:3])
        more = f" and {len(old) - 3} more" if len(old) > 3 else ""
        log.warning("%s: old option names read as the new ones (%s%s); they are deprecated: "
                    "`svolsdf config` prints the current names", where, pairs, more)


def _dotted(data: dict, prefix: str = "") -> dict[str, Any]:
    """A nested dict as {dotted key: value} (mappings flattened)."""
    out: dict[str, Any] = {}
    for k, v in data.items():
        if isinstance(v, dict):
            out.update(_dotted(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _upgrade(data: dict, where: str) -> dict:
    """``data`` (a nested config dict) with the old option names of `RENAMED` moved to their new
    places (one deprecation line when there were any).

    Raises:
        InputError: an option given under both its old and its new name.
    """
    old = data.get("output")
    if "output" in data and (old is None or old == {}):  # an empty old section: nothing to move
        return {k: v for k, v in data.items() if k != "output"}
    if not isinstance(old, dict):
        return data
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in data.items()}
    section = data.pop("output")
    moved = []
    for k, v in section.items():
        new = RENAMED.get(f"output.{k}")
        if new is None:
            raise InputError(f"{where}: unknown key 'output.{k}' ({_OUTPUT_GONE})")
        node = data
        *parents, leaf = new.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise InputError(f"{where}: {part} must be a mapping")
        if leaf in node:
            raise InputError(f"{where}: option {new} given twice, also as output.{k} (its "
                             f"old name): keep {new}")
        node[leaf] = v
        moved.append(f"output.{k}")
    _deprecated(where, moved)
    return data


def legacy_layout(cfg: Config) -> dict:
    """``cfg`` as a nested dict in the layout before the component sections: the renamed options
    of `RENAMED` under their old ``output.*`` names (in their old order), the rest as
    `dataclasses.asdict`. The earlier stage-key formula hashes this, so the run folders it marked
    before the renaming are recognised (`svolsdf.pipeline.legacy_keys.legacy_stage_keys`)."""
    c = asdict(cfg)
    flat = _dotted(c)
    for section in ("guide", "fusion", "mesh"):
        c.pop(section)
    c["output"] = {}
    for old, new in RENAMED.items():
        *parents, leaf = new.split(".")
        if parents[0] in ("scene", "mvs"):
            c[parents[0]].pop(leaf)
        c["output"][old.split(".", 1)[1]] = flat[new]
    return c


def _from_dict(cls, data: dict, where: str, prefix: str = ""):
    obj = cls()
    names = {f.name: f for f in fields(cls)}
    for k, v in data.items():
        if k not in names:
            gone = f"; {_OUTPUT_GONE}" if prefix + str(k) == "output" else ""
            raise InputError(f"{where}: unknown key {prefix + str(k)!r} (known in "
                             f"{prefix.rstrip('.') or 'the top level'}: {', '.join(names)}"
                             f"{gone})")
        cur = getattr(obj, k)
        if dataclasses.is_dataclass(cur):
            if not isinstance(v, dict):
                raise InputError(f"{where}: {prefix}{k} = {_short(v)}: expected a mapping of "
                                 f"{', '.join(f.name for f in fields(cur))}")
            setattr(obj, k, _from_dict(type(cur), v, where, f"{prefix}{k}."))
        else:
            setattr(obj, k, v)
    return obj


def config_from_dict(data: dict, where: str = "config") -> Config:
    """A validated `Config` from a nested dict: the keys it gives over its preset's values.

    Raises:
        InputError: an unknown key or a value `validate_config` rejects, named with ``where``.
    """
    name = data.get("preset", "fast")
    if not isinstance(name, str) or name not in PRESETS:
        raise InputError(f"{where}: preset = {_short(name)}: expected one of "
                         f"{', '.join(repr(p) for p in PRESETS)}")
    merged = _merge(asdict(preset(name)), _upgrade(data, where))
    return validate_config(_from_dict(Config, merged, where), where)


def _merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def load_config(path: str | Path) -> Config:
    """Read a YAML config (as written by `save_config`)."""
    from svolsdf.io.paths import input_file

    path = input_file(path, "config file")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise InputError(f"{path}: not valid YAML ({e.__class__.__name__})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read the config file ({e})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping at the top level")
    return config_from_dict(data, where=str(path))


def save_config(cfg: Config, path: str | Path) -> None:
    """Write ``cfg`` as YAML atomically; the paper and released presets' file starts with a
    comment naming the MVS backbone and whether it is the paper's (`backbone_provenance`)."""

    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    head = ""
    if cfg.preset in ("paper", "released"):  # which MVS backbone ran, and whether the paper's
        from svolsdf.config.presets import backbone_provenance

        head = f"# {cfg.preset} preset: {backbone_provenance(cfg)['note']}\n"
    tmp.write_text(head + yaml.safe_dump(asdict(cfg), sort_keys=False))
    os.replace(tmp, path)


def known_keys(cfg: Any, prefix: str = "") -> list[str]:
    """Every dotted option key of ``cfg`` (``train.steps``, ``mesh.poisson.depth``, ...)."""
    out = []
    for f in fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            out += known_keys(v, f"{prefix}{f.name}.")
        else:
            out.append(prefix + f.name)
    return out


def _unknown_key(cfg: Config, key: str, label: str | None = None) -> InputError:
    near = difflib.get_close_matches(key, known_keys(cfg), n=3, cutoff=0.6)
    hint = (f"; did you mean {' or '.join(near)}?" if near
            else f"; {_OUTPUT_GONE}" if key.startswith("output.")
            else "; `svolsdf config` lists every option")
    return InputError(f"{label + ': ' if label else ''}unknown option {key!r}{hint}")


def apply_overrides(cfg: Config, overrides: dict[str, Any],
                    labels: Mapping[str, str] | None = None, skip_none: bool = True) -> Config:
    """Set dotted keys (``{"train.steps": 100}``), then validate.

    A changed ``mvs.backbone`` without ``mvs.scale`` takes the preset's scale for it
    (`svolsdf.config.presets.follow_backbone`: ``--preset draft --backbone casmvsnet`` runs
    CasMVSNet at its own size, not at the plane sweep's 1.5).

    Args:
        labels: dotted key -> the option that gave it, for the messages of `validate_config`.
        skip_none: None values mean "not given" and are skipped (command-line flags); False sets
            them (``--set mvs.weights=null``).

    Raises:
        InputError: an unknown key (with the nearest known ones), or a value `validate_config`
            rejects.
    """
    labels = dict(labels or {})
    old = [k for k in overrides if k in RENAMED]
    if old:
        overrides = {RENAMED.get(k, k): v for k, v in overrides.items()}
        for k in old:
            if k in labels:
                labels[RENAMED[k]] = labels.pop(k)
        _deprecated(", ".join(sorted({labels.get(RENAMED[k], "--set") for k in old})), old)
    backbone = getattr(getattr(cfg, "mvs", None), "backbone", None)
    for key, value in overrides.items():
        if value is None and skip_none:
            continue
        obj = cfg
        parts = key.split(".")
        for p in parts[:-1]:
            obj = getattr(obj, p, None)
            if not dataclasses.is_dataclass(obj):
                raise _unknown_key(cfg, key, labels.get(key))
        if dataclasses.is_dataclass(getattr(obj, parts[-1], None)) or \
                parts[-1] not in {f.name for f in fields(obj)}:
            raise _unknown_key(cfg, key, labels.get(key))
        setattr(obj, parts[-1], value)
    set_keys = {k for k, v in overrides.items() if v is not None or not skip_none}
    if "mvs.backbone" in set_keys and "mvs.scale" not in set_keys:
        follow_backbone(cfg, backbone)  # the preset's scale for the new backbone
    given = {k: v for k, v in labels.items() if k in set_keys}
    return validate_config(cfg, labels=given)


def parse_set(items: list[str] | None) -> dict[str, Any]:
    """``["train.steps=200", "output.mesh_method=poisson"]`` -> dotted key -> value.

    Values are read as YAML (``200`` an int, ``null`` None, ``[25, 22, 28]`` a list, ``true`` a
    bool, anything else a string); `apply_overrides` then checks keys and values.

    Raises:
        InputError: an item without ``=`` or with an empty key, naming it.
    """
    out: dict[str, Any] = {}
    for item in items or []:
        key, eq, text = str(item).partition("=")
        key = key.strip()
        if not eq or not key:
            raise InputError(f"--set {item!r}: expected section.option=value, e.g. "
                             "--set train.steps=200")
        try:
            value = yaml.safe_load(text) if text.strip() else None
        except yaml.YAMLError:
            value = text
        out[key] = value
    return out


def option_docs() -> dict[str, str]:
    """Dotted option key -> its docstring (the string under each field in
    `svolsdf.config.schema`), one paragraph with single spaces."""
    import ast
    import inspect

    from svolsdf.config import schema

    tree = ast.parse(inspect.getsource(schema))
    by_class: dict[str, dict[str, str]] = {}
    for node in tree.body:
        if not isinstance(node, ast.ClassDef):
            continue
        docs = by_class.setdefault(node.name, {})
        for a, b in zip(node.body, node.body[1:], strict=False):
            if isinstance(a, ast.AnnAssign) and isinstance(a.target, ast.Name) and \
                    isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant) and \
                    isinstance(b.value.value, str):
                docs[a.target.id] = " ".join(b.value.value.split())
    out: dict[str, str] = {}

    def walk(cls: Any, prefix: str) -> None:
        for f in fields(cls):
            out[prefix + f.name] = by_class.get(cls.__name__, {}).get(f.name, "")
            sub = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
            if dataclasses.is_dataclass(sub):
                walk(type(sub), f"{prefix}{f.name}.")

    walk(Config, "")
    return out


def config_yaml(cfg: Config, width: int = 96) -> str:
    """``cfg`` as YAML (as `save_config` writes it) with each option's docstring as a comment
    above it; loading the text gives ``cfg`` back."""
    docs = option_docs()
    lines: list[str] = []

    def comment(text: str, indent: str) -> None:
        for ln in textwrap.wrap(text, width - len(indent) - 2) if text else []:
            lines.append(f"{indent}# {ln}")

    def section(data: dict, prefix: str, indent: str) -> None:
        for key, value in data.items():
            comment(docs.get(prefix + key, ""), indent)
            if isinstance(value, dict):
                lines.append(f"{indent}{key}:")
                section(value, f"{prefix}{key}.", indent + "  ")
            else:
                lines.append(indent + _yaml_item(key, value))

    section(asdict(cfg), "", "")
    return "\n".join(lines) + "\n"


def _yaml_item(key: str, value: Any) -> str:
    text = yaml.safe_dump({key: value}, default_flow_style=True, sort_keys=False, width=10**6)
    return text.strip().removeprefix("{").removesuffix("}")
