"""Fingerprint localization in the twin (paper, section IV: MCA on the twin's
multipath delay profiles and the baselines).

Modules, one concept each:

* :mod:`~isac_twin.localization.fingerprints` -- the fingerprint database (per grid
  point and AP: path lengths, powers, angles), built from the twin's tracer or a
  grid file, cached by scene hash, flagged stale by edits;
* :mod:`~isac_twin.localization.measurements` -- what a robot observes (ideal MDP
  from traced delays, or estimated from received pilots) and the features
  (CSI at chosen subcarriers via :func:`isac_twin.phy.channel.cfr_at`, PDP);
* :mod:`~isac_twin.localization.mca` -- :class:`MCALocalizer`, multipath component
  analysis (branch-and-bound k-best);
* :mod:`~isac_twin.localization.baselines` -- MCA, MCA with angles, the
  line-of-sight fix, kNN on CSI, PDP matching behind one
  ``localizer(observation)`` interface (:func:`make_localizer` by name);
* :mod:`~isac_twin.localization.fusion` -- :class:`PoseEKF`, odometry + gated fixes;
* :mod:`~isac_twin.localization.estimator` -- :class:`TwinLocalizer`, what
  ``[localization]`` in ``twin.toml`` gives a :class:`~isac_twin.twin.twin.Twin`.

The paper's deployment loop (a robot in a perturbed real room localizing against
the twin's database) is an experiment: :mod:`isac_twin.experiments.deployment`.
"""

from ..errors import DatabaseMismatchError
from .baselines import (
                                           MCA,
                                           METHODS,
                                           KnnCsi,
                                           LosFix,
                                           MCAAngles,
                                           PdpMatch,
                                           make_localizer,
                                           make_localizers,
)
from .estimator import TwinLocalizer
from .fingerprints import (
                                           FingerprintDB,
                                           attach,
                                           build_database,
                                           cached_database,
                                           from_grid,
                                           load_database,
                                           save_database,
)
from .fusion import PoseEKF
from .mca import LocationEstimate, MCALocalizer
from .measurements import FeatureSpec, Observation, PilotSettings, observe_pilots, observe_tracer

__all__ = [
    "FingerprintDB", "DatabaseMismatchError", "build_database", "cached_database",
    "from_grid", "load_database", "save_database", "attach",
    "FeatureSpec", "Observation", "PilotSettings", "observe_tracer", "observe_pilots",
    "MCALocalizer", "LocationEstimate", "PoseEKF",
    "MCA", "MCAAngles", "LosFix", "KnnCsi", "PdpMatch", "make_localizers", "make_localizer",
    "METHODS", "TwinLocalizer",
]
