"""`svolsdf.registry.Registry`: names in registration or alphabetical order, a package's modules
that use the decorator imported on the first read (and only those), unknown names refused with
the available ones."""

from __future__ import annotations

import sys

import pytest

from svolsdf.errors import InputError
from svolsdf.registry import Registry


@pytest.fixture
def plugins(tmp_path, monkeypatch):
    """A package ``toyplugins`` of three modules: two register a piece, one does not."""
    pkg = tmp_path / "toyplugins"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("from svolsdf.registry import Registry\n"
                                     "REG = Registry('toy', 'toyplugins', 'register_toy')\n"
                                     "def register_toy(name):\n"
                                     "    return REG.decorator(name)\n")
    for mod, name in (("b_mod", "beta"), ("a_mod", "alpha")):
        (pkg / f"{mod}.py").write_text("from toyplugins import register_toy\n\n"
                                       f"@register_toy({name!r})\n"
                                       f"def {name}():\n    return {name!r}\n")
    (pkg / "c_mod.py").write_text("raise RuntimeError('never imported')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    yield pkg
    for m in [m for m in sys.modules if m.split(".")[0] == "toyplugins"]:
        del sys.modules[m]


def test_modules_that_use_the_decorator_are_imported_on_the_first_read(plugins):
    import toyplugins

    assert "toyplugins.a_mod" not in sys.modules
    assert toyplugins.REG.names() == ["alpha", "beta"]  # the modules in file-name order
    assert "toyplugins.c_mod" not in sys.modules
    assert toyplugins.REG.get("beta")() == "beta"
    assert "alpha" in toyplugins.REG


def test_order_removal_and_unknown_names():
    reg: Registry[int] = Registry("number", "svolsdf.io", "register_number")
    reg.decorator("two")(2)
    reg.add("one", 1)
    assert reg.names() == ["two", "one"] and list(reg.items()) == [("two", 2), ("one", 1)]
    assert Registry("n", "svolsdf.io", "x", sort=True).names() == []
    reg.decorator("ten", make=lambda v: v * 10)(1)
    assert reg.get("ten") == 10
    reg.remove("two")
    reg.remove("never")
    with pytest.raises(InputError, match=r"unknown number 'two' \(available: one, ten\)"):
        reg.get("two")


def test_register_stores_what_the_entry_function_builds_from_the_declaration():
    reg: Registry[tuple] = Registry("piece", "svolsdf.io", "register_piece",
                                    entry=lambda name, obj, size=1: (name, obj, size))
    plain: Registry[int] = Registry("number", "svolsdf.io", "register_number")

    @reg.register("big", size=3)
    def fn():
        return "made"

    assert fn() == "made"  # the decorated object is returned unchanged
    assert reg.get("big") == ("big", fn, 3)
    assert plain.register("one")(1) == 1 and plain.get("one") == 1
    with pytest.raises(TypeError, match="a number declares nothing beside its name"):
        plain.register("two", size=2)


def test_each_kind_is_one_registry_read_through_its_own_methods():
    """The five kinds keep no wrapper functions of their own: their register/get/names names
    are the bound methods of one `Registry`."""
    from svolsdf.field import kinds
    from svolsdf.fusion import mesh_methods
    from svolsdf.mvs import backbone
    from svolsdf.render import sampler_registry
    from svolsdf.scene import formats

    for reg, register, get in (
            (backbone.BACKBONES, backbone.register_backbone, backbone._backbone_class),
            (kinds.FIELD_KINDS, kinds.register_field_kind, kinds.get_field_kind),
            (sampler_registry.SAMPLERS, sampler_registry.register_sampler,
             sampler_registry.get_sampler),
            (formats.SCENE_FORMATS, formats.register_scene_format, formats.get_scene_format),
            (mesh_methods.MESH_METHODS, mesh_methods.register_mesh_method,
             mesh_methods.get_mesh_method)):
        assert isinstance(reg, Registry)
        assert register == reg.register and get == reg.get
