"""Calibrate the twin from measured channels: fit materials and object poses.

* :mod:`.problem` -- what is fitted (:class:`Parameter`), to what
  (:class:`Measurements`), the mismatch, the result (:class:`CalibrationResult`);
* :mod:`.forward_model` -- the twin's channel at parameter values, with gradients
  (:class:`SolverSettings`), on the candidates of :mod:`.candidates`;
* :mod:`.search` -- the strategies: gradient fit, polish, basin hops, scans;
* :mod:`.calibrator` -- :class:`Calibrator`, the three wired together;
* :mod:`.recording` -- measurements from an MCAP recording;
* :mod:`.observability` -- what the measurements say about each parameter;
* :mod:`.calibrated_scene` -- the calibrated scene folder;
* :mod:`.run` -- a scene folder calibrated from a recording (``isac-twin calibrate``);
* :mod:`.figure` -- the report's figure.
"""

from .calibrated_scene import material_users, write_calibrated_scene
from .calibrator import Calibrator
from .forward_model import SolverSettings
from .problem import CalibrationResult, Measurements, Parameter
from .recording import measurements_from_recording
from .run import calibrate_recording, recording_calibrator

__all__ = ["CalibrationResult", "Calibrator", "Measurements", "Parameter", "SolverSettings",
           "calibrate_recording", "material_users", "measurements_from_recording",
           "recording_calibrator", "write_calibrated_scene"]
