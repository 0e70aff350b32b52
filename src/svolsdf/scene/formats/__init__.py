"""On-disk scene formats, by name. A format is a module of this package with
``detect(path) -> bool`` and ``read(path, lighting) -> SceneSource`` (cameras and file lists, no
pixels), its ``read`` decorated with ``@register_scene_format(name, detect, order, looks_for)``;
`svolsdf.scene.loaders` detects a folder's format with `scene_formats` and turns the
`SceneSource` into a `Scene`.

Adding a format is one module with one decorator: the modules of this package that use the
decorator are imported the first time the formats are asked for (`svolsdf.registry.Registry`).
Built in, in detection order (the most specific layouts first): idr, dtu_raw, mvsnet, colmap,
nerf.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from svolsdf.registry import Registry
from svolsdf.scene.formats._common import SceneSource

__all__ = ["SCENE_FORMATS", "SceneFormat", "SceneSource", "get_scene_format",
           "register_scene_format", "scene_formats"]


@dataclass(frozen=True)
class SceneFormat:
    """A registered format.

    Attributes:
        name: the format's name (`SceneSource.format`, `Scene.format`).
        detect: (scene folder) -> whether the folder is in this format.
        read: (scene folder, lighting) -> `SceneSource`.
        order: place in the detection order (lower first: the most specific layouts first; the
            built-in formats take 10, 20, .., 50).
        looks_for: what ``detect`` looks for, for the message of a folder no format reads
            ("transforms.json (NeRF)").
        title: the format in words, for ``svolsdf info`` ("NeRF transforms.json"; "" = the
            name).
    """

    name: str
    detect: Callable[[Path], bool]
    read: Callable[..., SceneSource]
    order: int
    looks_for: str
    title: str = ""


def _format_entry(name: str, read: Callable[..., SceneSource], detect: Callable[[Path], bool],
                  order: int, looks_for: str, title: str = "") -> SceneFormat:
    return SceneFormat(name, detect, read, order, looks_for, title)


#: name -> format; the modules of this package that use ``@register_scene_format(...)`` are
#: imported the first time a format is asked for (`svolsdf.registry.Registry`)
SCENE_FORMATS: Registry[SceneFormat] = Registry("scene format", "svolsdf.scene.formats",
                                                "register_scene_format", entry=_format_entry)

#: ``@register_scene_format(name, detect, order, looks_for, title="")``: a function decorator
#: registering the decorated ``read(path, lighting)`` (see `SceneFormat`)
register_scene_format = SCENE_FORMATS.register
#: the format registered as a name (InputError when none is)
get_scene_format = SCENE_FORMATS.get


def scene_formats() -> list[SceneFormat]:
    """The registered formats in detection order (by ``order``, then by name)."""
    return sorted((f for _, f in SCENE_FORMATS.items()), key=lambda f: (f.order, f.name))
