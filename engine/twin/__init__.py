"""The twin: Algorithm 1 of the paper (:class:`Twin`), and what one step produces
(:mod:`.state`: :class:`StepResult`, :class:`RobotState`, :class:`LinkState`, and the
:class:`Edit` / :class:`Command` records a live link sends)."""

from .state import Command, Edit, LinkState, RobotState, StepResult
from .twin import Twin

__all__ = ["Command", "Edit", "LinkState", "RobotState", "StepResult", "Twin"]
