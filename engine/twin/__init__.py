"""The twin: Algorithm 1 of the paper (:class:`Twin`, in :mod:`.twin`), and its parts:
what one step produces (:mod:`.state`: :class:`StepResult`, :class:`RobotState`,
:class:`LinkState`, and the :class:`Edit` / :class:`Command` records a live link sends),
live edits (:mod:`.edits`: :class:`SceneEditor`), commands (:mod:`.commands`) and the
paced run with its stage timings (:mod:`.pacing`: :class:`RunStats`)."""

from .edits import SceneEditor
from .pacing import STAGES, RunStats
from .state import Command, Edit, LinkState, RobotState, StepResult
from .twin import Twin

__all__ = ["Command", "Edit", "LinkState", "RobotState", "RunStats", "STAGES", "SceneEditor",
           "StepResult", "Twin"]
