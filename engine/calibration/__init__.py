"""Calibrate the twin from measured channels: fit materials and object poses.

* :mod:`.calibrator` -- the problem (parameters, measurements, the forward model
  over the twin's path chains) and the search (gradient fit, polish, basin hops);
* :mod:`.run` -- a scene folder calibrated from a recording
  (``isac-twin calibrate``): measurements, parameters, the calibrated scene folder;
* :mod:`.figure` -- the report's figure.
"""

from .calibrator import Calibrator, Measurements, Parameter
from .run import calibrate_recording, measurements_from_recording, write_calibrated_scene

__all__ = ["Calibrator", "Measurements", "Parameter", "calibrate_recording",
           "measurements_from_recording", "write_calibrated_scene"]
