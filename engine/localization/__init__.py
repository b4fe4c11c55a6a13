"""Fingerprint localization in the twin (paper, section IV: MCA on the twin's
multipath delay profiles, the baselines, and the deployment loop).

Modules, one concept each:

* :mod:`~engine.localization.fingerprints` -- the fingerprint database (per grid
  point and AP: path lengths, powers, angles), built from the twin's tracer or a
  grid file, cached by scene hash, flagged stale by edits;
* :mod:`~engine.localization.measurements` -- what a robot observes (ideal MDP
  from traced delays, or estimated from received pilots) and the features
  (CSI at chosen subcarriers via :func:`engine.phy.channel.cfr_at`, PDP);
* :mod:`~engine.localization.mca` -- :class:`MCALocalizer`, multipath component
  analysis (branch-and-bound k-best);
* :mod:`~engine.localization.baselines` -- MCA, MCA with angles, the
  line-of-sight fix, kNN on CSI, PDP matching behind one
  ``localizer(observation)`` interface (:func:`make_localizer` by name);
* :mod:`~engine.localization.fusion` -- :class:`PoseEKF`, odometry + gated fixes;
* :mod:`~engine.localization.estimator` -- :class:`TwinLocalizer`, what
  ``[localization]`` in ``twin.toml`` gives a :class:`~engine.twin.Twin`;
* :mod:`~engine.localization.deployment` -- :class:`Deployment`, a robot in a
  (perturbed) real room localizing against the twin's database, step by step.
"""

from engine.localization.baselines import (MCA, METHODS, KnnCsi, LosFix, MCAAngles,
                                           PdpMatch, make_localizer, make_localizers)
from engine.localization.deployment import (Deployment, DeploymentSettings, StepRecord,
                                            errors, perturb_scene, summarize)
from engine.localization.fingerprints import (DatabaseMismatchError, FingerprintDB, attach,
                                              build_database, cached_database, from_grid,
                                              load_database, save_database)
from engine.localization.estimator import TwinLocalizer
from engine.localization.fusion import PoseEKF
from engine.localization.mca import LocationEstimate, MCALocalizer
from engine.localization.measurements import (FeatureSpec, Observation, PilotSettings,
                                              observe_pilots, observe_tracer)

__all__ = [
    "FingerprintDB", "DatabaseMismatchError", "build_database", "cached_database",
    "from_grid", "load_database", "save_database", "attach",
    "FeatureSpec", "Observation", "PilotSettings", "observe_tracer", "observe_pilots",
    "MCALocalizer", "LocationEstimate", "PoseEKF",
    "MCA", "MCAAngles", "LosFix", "KnnCsi", "PdpMatch", "make_localizers", "make_localizer",
    "METHODS", "TwinLocalizer",
    "Deployment", "DeploymentSettings", "StepRecord", "errors", "summarize",
    "perturb_scene",
]
