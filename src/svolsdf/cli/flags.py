"""Command-line flags generated from the config schema (`svolsdf.config.schema`).

A flag that sets one config option is declared once, as ``flag -> dotted option`` in a table
such as `RECONSTRUCT_FLAGS`. Its type comes from the option's annotation, its help text from the
first sentence of the option's docstring (`svolsdf.config.option_docs`) with its choices
(`svolsdf.config.choices`: a ``Literal``'s or a registry's) appended when that sentence does not
name them all, and its default is None: the config's value stands unless the flag is given.
`with_flags` adds the table's flags to a command's signature for typer, and `flag_overrides`
turns the values typer passes back into the dotted overrides that `build_config` applies.

The other commands are configured by a dataclass of their own (`CalibrateConfig`,
`MVSJobConfig`, `SynthConfig`, `EvaluateConfig`): a table ``flag -> field`` such as
`CALIBRATE_FLAGS` declares their flags the same way (`with_dataclass_flags`, then
`dataclass_values`), each with the field's type, the first sentence of its docstring and its
default. A help text says what the option does for the user: references to the code and to
docs/ in parentheses are left out (`user_help`).
"""

from __future__ import annotations

import dataclasses
import inspect
import re
import types
from pathlib import Path
from typing import Annotated, Any, Literal, Union, get_args, get_origin, get_type_hints

import typer

from svolsdf.io.paths import user_path

#: `svolsdf reconstruct` flag -> the config option it sets (adding a flag is one line here)
RECONSTRUCT_FLAGS: dict[str, str] = {
    "--backbone": "mvs.backbone",
    "--weights": "mvs.weights",
    "--mvs-scale": "mvs.scale",
    "--mode": "train.mode",
    "--ablation": "train.ablation",
    "--steps": "train.steps",
    "--device": "device",
    "--threads": "threads",
    "--mesh-resolution": "mesh.resolution",
    "--seed": "train.seed",
    "--background": "field.background",
}

#: flags that take a file (a ``Path`` on the command line, a string in the config)
PATH_FLAGS = frozenset({"--weights"})

#: `svolsdf calibrate` flag -> the field of `svolsdf.calibrate.CalibrateConfig` it sets
CALIBRATE_FLAGS: dict[str, str] = {
    "--max-size": "max_size", "--matcher": "matcher", "--frames": "frames",
    "--max-features": "max_features", "--min-registered": "min_registered",
    "--threads": "threads", "--seed": "seed", "--progress": "progress",
}

#: `svolsdf mvs` flag -> the field of `svolsdf.commands.mvs.MVSJobConfig` it sets
MVS_FLAGS: dict[str, str] = {
    "--backbone": "backbone", "--weights": "weights", "--device": "device", "--fuse": "fuse",
}

#: `svolsdf synth` flag -> the field of `svolsdf.scene.synthetic.SynthConfig` it sets
SYNTH_FLAGS: dict[str, str] = {
    "--seed": "seed", "--views": "views", "--object": "object",
    "--texture-contrast": "texture_contrast", "--specular": "specular",
    "--shininess": "shininess", "--supersample": "supersample",
    "--distance": "distance", "--focal": "focal", "--intrinsics-jitter": "intrinsics_jitter",
    "--soft-shadows": "soft_shadows", "--gt-points": "gt_points",
}

#: `svolsdf render` flag -> the field of `svolsdf.ibr.IBRConfig` it sets
RENDER_IBR_FLAGS: dict[str, str] = {"--ibr-unseen": "unseen", "--ibr-holes": "hole_depth"}

#: `svolsdf evaluate` flag -> the field of `svolsdf.evaluate.scoring.EvaluateConfig` it sets
EVALUATE_FLAGS: dict[str, str] = {
    "--gt-points": "gt_points", "--dtu-gt": "dtu_gt", "--scan": "scan", "--scene": "scene",
    "--threshold": "threshold", "--max-dist": "max_dist", "--lpips-net": "lpips_net",
    "--lpips-weights": "lpips_weights", "--ssim-data-range": "ssim_data_range",
    "--masks": "masks", "--report": "report", "--protocol": "protocol", "--volsdf": "volsdf",
    "--eval-masks": "eval_masks",
}


def param_name(flag: str) -> str:
    """``--mesh-resolution`` -> ``mesh_resolution`` (the parameter typer passes it as)."""
    return flag.lstrip("-").replace("-", "_")


def _option_field(key: str) -> tuple[Any, dataclasses.Field]:
    """The type hint and dataclass field of the dotted option ``key``."""
    from svolsdf.config import Config

    cls: Any = Config
    *sections, name = key.split(".")
    for section in sections:
        cls = get_type_hints(cls)[section]
    if name not in get_type_hints(cls):
        raise KeyError(f"{key}: no such option")
    field = next(f for f in dataclasses.fields(cls) if f.name == name)
    return get_type_hints(cls)[name], field


def option_choices(key: str) -> tuple[str, ...]:
    """The values option ``key`` allows: its ``Literal``'s, else its registry's
    (`svolsdf.config.choices`); () for any."""
    from svolsdf.config import choices

    try:
        return choices(key)
    except KeyError:
        return ()


def flag_type(flag: str, key: str) -> type:
    """The flag's value type: the option's annotation without None (a ``Literal`` is a str)."""
    if flag in PATH_FLAGS:
        return Path
    return _value_type(flag, key, _option_field(key)[0])


def _value_type(flag: str, key: str, hint: Any) -> type:
    """A flag's value type from the annotation ``hint`` of the option or field ``key``."""
    args = get_args(hint) if get_origin(hint) in (Union, types.UnionType) else (hint,)
    args = tuple(a for a in args if a is not type(None))
    if len(args) != 1:
        raise TypeError(f"{flag}: option {key} has no single type ({hint})")
    tp = args[0]
    if get_origin(tp) is Literal:
        return str
    if tp not in (bool, int, float, str, Path):
        raise TypeError(f"{flag}: option {key} of type {tp} needs a hand-written flag")
    return tp


def first_sentence(doc: str) -> str:
    """A docstring's first sentence (up to the first '. ' outside parentheses), without the
    reStructuredText backticks."""
    text = doc.replace("``", "").replace("`", "").strip()
    depth = 0
    for i, c in enumerate(text):
        depth += (c == "(") - (c == ")")
        if c == "." and depth == 0 and (i + 1 == len(text) or text[i + 1].isspace()):
            return text[:i + 1]
    return text


#: a parenthesis that points at the code or the docs rather than at what the option does
_REFERENCE = re.compile(r"\s*\([^()]*(?:docs/|svolsdf\.|\.py\b|method\.md)[^()]*\)")


def user_help(text: str) -> str:
    """``text`` without its parentheses that cite code or docs ("(docs/method.md 5.4)",
    "(svolsdf.scene.size)"): a help text says what the option does for the user."""
    return re.sub(r"\s+([.,;:])(?=\s|$)", r"\1", _REFERENCE.sub("", text)).strip()


def flag_help(key: str) -> str:
    """The help of the flag setting option ``key``: the first sentence of its docstring, then
    its choices in parentheses when the sentence does not name each of them."""
    from svolsdf.config import option_docs

    text = user_help(first_sentence(option_docs()[key]))
    named = set(re.findall(r"[\w-]+", text))
    allowed = option_choices(key)
    if allowed and not set(allowed) <= named:
        text += f" (one of: {', '.join(allowed)})"
    return text


def _option(flag: str, key: str) -> typer.models.OptionInfo:
    decl = f"{flag}/--no-{flag[2:]}" if flag_type(flag, key) is bool else flag
    return typer.Option(decl, help=flag_help(key))


def with_flags(fn, table: dict[str, str]):
    """``fn`` with the table's flags in its signature, in place of its ``**options`` (typer
    builds the command from that signature; each flag is optional, default None)."""
    sig = inspect.signature(fn, eval_str=True)
    params = [p for p in sig.parameters.values() if p.kind is not p.VAR_KEYWORD]
    if len(params) == len(sig.parameters):
        raise TypeError(f"{fn.__name__} takes no **options for the generated flags")
    taken = {p.name for p in params}
    for flag, key in table.items():
        name = param_name(flag)
        if name in taken:
            raise TypeError(f"{flag}: {fn.__name__} already has a parameter {name}")
        params.append(inspect.Parameter(
            name, inspect.Parameter.KEYWORD_ONLY, default=None,
            annotation=Annotated[flag_type(flag, key) | None, _option(flag, key)]))
    fn.__signature__ = sig.replace(parameters=params)
    return fn


def flag_overrides(table: dict[str, str], options: dict[str, Any]) -> dict[str, Any]:
    """The values typer passed for the table's flags -> dotted option -> value (None: not given;
    a path as a string, as the config holds it)."""
    out = {}
    for flag, key in table.items():
        v = options.get(param_name(flag))
        out[key] = str(user_path(v)) if isinstance(v, Path) else v
    return out


def flag_labels(table: dict[str, str]) -> dict[str, str]:
    """Dotted option -> the flag that sets it (for error messages)."""
    return {key: flag for flag, key in table.items()}


# --------------------------------------------------------------------------- other commands
def field_docs(cls: type) -> dict[str, str]:
    """Field name -> the docstring under it in ``cls``'s source, one paragraph with single
    spaces ("" for a field without one)."""
    import ast
    import textwrap

    docs: dict[str, str] = {}
    node = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0]
    for a, b in zip(node.body, node.body[1:], strict=False):
        if isinstance(a, ast.AnnAssign) and isinstance(a.target, ast.Name) and \
                isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant) and \
                isinstance(b.value.value, str):
            docs[a.target.id] = " ".join(b.value.value.split())
    return docs


def _field_option(cls: type, flag: str, name: str, docs: dict[str, str]
                  ) -> tuple[type, Any, typer.models.OptionInfo]:
    """(value type, default, typer option) of the flag ``flag`` setting field ``name``."""
    hint = get_type_hints(cls)[name]
    field = next((f for f in dataclasses.fields(cls) if f.name == name), None)
    if field is None:
        raise KeyError(f"{flag}: {cls.__name__} has no field {name}")
    tp = _value_type(flag, f"{cls.__name__}.{name}", hint)
    default = None if field.default is dataclasses.MISSING else field.default
    text = user_help(first_sentence(docs.get(name, "")))
    if get_origin(hint) is Literal and not set(get_args(hint)) <= set(re.findall(r"[\w-]+",
                                                                                 text)):
        text += f" (one of: {', '.join(get_args(hint))})"
    decl = f"{flag}/--no-{flag[2:]}" if tp is bool else flag
    return tp, default, typer.Option(decl, help=text)


def with_dataclass_flags(fn, cls: type, table: dict[str, str]):
    """``fn`` with a flag per entry of ``table`` (flag -> field of the dataclass ``cls``) in its
    signature, in place of its ``**options``: the field's type (a ``bool`` as
    ``--flag/--no-flag``), its docstring's first sentence as help and its default.

    Raises:
        TypeError: ``fn`` takes no ``**options`` or already has a parameter of a flag's name, or
            a field's type has no flag (write that flag by hand).
        KeyError: ``table`` names a field ``cls`` does not have.
    """
    sig = inspect.signature(fn, eval_str=True)
    params = [p for p in sig.parameters.values() if p.kind is not p.VAR_KEYWORD]
    if len(params) == len(sig.parameters):
        raise TypeError(f"{fn.__name__} takes no **options for the generated flags")
    taken = {p.name for p in params}
    docs = field_docs(cls)
    for flag, name in table.items():
        param = param_name(flag)
        if param in taken:
            raise TypeError(f"{flag}: {fn.__name__} already has a parameter {param}")
        tp, default, option = _field_option(cls, flag, name, docs)
        params.append(inspect.Parameter(
            param, inspect.Parameter.KEYWORD_ONLY, default=default,
            annotation=Annotated[tp if default is not None else tp | None, option]))
    fn.__signature__ = sig.replace(parameters=params)
    return fn


def dataclass_values(table: dict[str, str], options: dict[str, Any]) -> dict[str, Any]:
    """The values typer passed for ``table``'s flags -> field name -> value (the keywords of
    the command's dataclass)."""
    return {name: options[param_name(flag)] for flag, name in table.items()}
