"""One name from YAML to code: an option reaches the code that uses it under its own name.

Every module of the package is read with `ast`. Wherever a value read from a config section
(``cfg.fusion.guided_dilation``, ``f.mlp_depth`` after ``f = cfg.field``, ``mvs.crop_to_masks``
in a function taking the MVS section, a local set once from such a read) is handed on under a
name, as a keyword argument, a string key of a dict (a component's ``**cfg``), an item or an
attribute of another object, that name must be the option's. A type conversion around the read
(``int(...)``, ``tuple(int(x) for x in ...)``) changes nothing. The one other name allowed is the
part of an option named after another option of its section that the same call also passes
(``fusion.network_weights`` as ``weights=`` beside ``fusion.network``: the network's weights).
A value derived from options (a comparison, a rule of `svolsdf.pipeline.options`) has no such
name to keep, and neither has a positional argument at its call site (a registry's ``get(name)``,
a generic operation's ``dilate_mask(mask, radius)``).
"""

from __future__ import annotations

import ast
import dataclasses
import typing
from pathlib import Path

import svolsdf
from svolsdf.config.schema import Config

PACKAGE = Path(svolsdf.__file__).parent
# type conversions that keep the option what it is
_CONVERSIONS = {"int", "float", "bool", "tuple", "list", "str"}


def _sections() -> tuple[dict[str, set[str]], dict[str, str]]:
    """{section name: its option names} of `Config` (nested sections too, ``mesh.poisson`` as
    ``poisson``) and {section class name: section name}."""
    options, classes = {}, {}

    def walk(cls):
        for name, tp in typing.get_type_hints(cls).items():
            if dataclasses.is_dataclass(tp):
                options[name] = {f.name for f in dataclasses.fields(tp)}
                classes[tp.__name__] = name
                walk(tp)

    walk(Config)
    return options, classes


SECTIONS, SECTION_CLASSES = _sections()


class _Function:
    """The config reads of one function: its section names and the locals holding an option."""

    def __init__(self, fn: ast.FunctionDef | ast.AsyncFunctionDef):
        self.sections: dict[str, str] = {}
        args = fn.args.posonlyargs + fn.args.args + fn.args.kwonlyargs
        for a in args:
            ann = ast.unparse(a.annotation) if a.annotation is not None else ""
            named = [s for c, s in SECTION_CLASSES.items() if c in ann.replace('"', "").split()
                     or ann.strip("\"'") == c]
            if named:
                self.sections[a.arg] = named[0]
            elif a.arg in SECTIONS:
                self.sections[a.arg] = a.arg
        assigned: dict[str, list[ast.expr]] = {}
        for n in ast.walk(fn):
            if isinstance(n, ast.Assign | ast.AnnAssign | ast.AugAssign):
                targets = n.targets if isinstance(n, ast.Assign) else [n.target]
                for t in targets:
                    for name in ast.walk(t):
                        if isinstance(name, ast.Name):
                            assigned.setdefault(name.id, []).append(
                                n.value if isinstance(t, ast.Name) else None)
        for name, values in assigned.items():  # x = cfg.mvs: x is the MVS section
            if len(values) == 1 and values[0] is not None:
                s = self.section(values[0])
                if s is not None:
                    self.sections[name] = s
        # x = cfg.mvs.crop_to_masks, assigned once: x is that option
        self.aliases = {name: o for name, values in assigned.items()
                        if len(values) == 1 and values[0] is not None
                        and (o := self.option(values[0], aliases=False)) is not None}

    def section(self, e: ast.expr) -> str | None:
        if isinstance(e, ast.Attribute) and e.attr in SECTIONS:
            return e.attr
        if isinstance(e, ast.Name):
            return self.sections.get(e.id)
        return None

    def option(self, e: ast.expr, aliases: bool = True) -> tuple[str, str] | None:
        """(section, option) that ``e`` reads as it is, or None."""
        while (isinstance(e, ast.Call) and isinstance(e.func, ast.Name)
               and e.func.id in _CONVERSIONS and len(e.args) == 1 and not e.keywords):
            e = e.args[0]
            if isinstance(e, ast.GeneratorExp | ast.ListComp) and len(e.generators) == 1:
                e = e.generators[0].iter
        if isinstance(e, ast.Attribute):
            s = self.section(e.value)
            if s is not None and e.attr in SECTIONS[s]:
                return s, e.attr
        if aliases and isinstance(e, ast.Name):
            return self.aliases.get(e.id)
        return None


def _handed_on(node: ast.AST) -> list[tuple[str, ast.expr, list[ast.expr]]]:
    """(name, value, the values passed beside it) of what ``node`` hands on under a name."""
    out: list = []
    if isinstance(node, ast.Call):
        beside = list(node.args) + [k.value for k in node.keywords]
        out += [(k.arg, k.value, beside) for k in node.keywords if k.arg]
    elif isinstance(node, ast.Dict):
        out += [(k.value, v, list(node.values))
                for k, v in zip(node.keys, node.values, strict=True)
                if isinstance(k, ast.Constant) and isinstance(k.value, str)]
    elif isinstance(node, ast.Assign):
        for t in node.targets:
            if isinstance(t, ast.Subscript) and isinstance(t.slice, ast.Constant) \
                    and isinstance(t.slice.value, str):
                out.append((t.slice.value, node.value, []))
            elif isinstance(t, ast.Attribute):
                out.append((t.attr, node.value, []))
    return out


def renamed_options() -> list[str]:
    """``file:line: name <- section.option`` for every option handed on under another name."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        for fn in ast.walk(tree):
            if not isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            reads = _Function(fn)
            for node in ast.walk(fn):
                for name, value, beside in _handed_on(node):
                    o = reads.option(value)
                    if o is None or o[1] == name:
                        continue
                    if isinstance(node, ast.Assign) and any(
                            isinstance(t, ast.Attribute) and reads.section(t.value) == o[0]
                            for t in node.targets):
                        continue  # setting an option of the section itself
                    parts = {b[1] for b in map(reads.option, beside) if b and b[0] == o[0]}
                    if any(o[1] == f"{p}_{name}" for p in parts):
                        continue  # network_weights: the weights of ``network``
                    rel = path.relative_to(PACKAGE.parent)
                    found.append(f"{rel}:{node.lineno}: {name} <- {o[0]}.{o[1]}")
    return found


def test_options_keep_their_names_in_the_code():
    """No option is handed on under another name than its own (the module's docstring)."""
    assert renamed_options() == []


def test_the_check_sees_a_renamed_option(tmp_path, monkeypatch):
    """The check finds each way of renaming an option (keyword, dict key, item, attribute, a
    local holding it) and passes the same code that keeps the names."""
    bad = tmp_path / "svolsdf" / "bad.py"
    bad.parent.mkdir()
    bad.write_text(
        "def build(cfg, mvs):\n"
        "    f = cfg.field\n"
        "    depth = f.mlp_depth\n"
        "    a = Net(n_layers=depth, mlp_width=f.mlp_width)\n"
        "    kw = {'crop_margin': int(mvs.crop_to_masks),\n"
        "          'ndepths': tuple(int(x) for x in mvs.ndepths)}\n"
        "    kw['guide_init'] = mvs.guide_network\n"
        "    a.alt_mask_dilation = cfg.fusion.unguided_dilation\n"
        "    get(cfg.fusion.network, weights=cfg.fusion.network_weights)\n"
        "    get(cfg.mvs.backbone, weights=cfg.fusion.network_weights)\n"
        "    cfg.fusion.guided_dilation = cfg.fusion.unguided_dilation\n")
    monkeypatch.setitem(globals(), "PACKAGE", bad.parent)
    found = [line.split(": ", 1)[1] for line in renamed_options()]
    assert sorted(found) == ["alt_mask_dilation <- fusion.unguided_dilation",
                             "crop_margin <- mvs.crop_to_masks",
                             "guide_init <- mvs.guide_network", "n_layers <- field.mlp_depth",
                             "weights <- fusion.network_weights"]
