"""Camera calibration of your own photos or video: structure from motion (pycolmap) -> a scene."""

from svolsdf.calibrate.align import Similarity, centre_errors, similarity_fit
from svolsdf.calibrate.sfm import CalibrateConfig, CalibrationError, calibrate

__all__ = ["CalibrateConfig", "CalibrationError", "Similarity", "calibrate", "centre_errors",
           "similarity_fit"]
