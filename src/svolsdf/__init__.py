"""svolsdf: S-VolSDF surface reconstruction from a few calibrated views, fast on a CPU."""

__version__ = "0.1.0"
