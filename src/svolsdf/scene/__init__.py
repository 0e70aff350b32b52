"""Scenes and cameras: readers for each on-disk format, and the synthetic scene generator."""

from svolsdf.scene.cameras import Cameras, decompose_projection
from svolsdf.scene.loaders import load_scene
from svolsdf.scene.scene import Normalization, Scene, SceneError

__all__ = ["Cameras", "Normalization", "Scene", "SceneError", "decompose_projection", "load_scene"]
