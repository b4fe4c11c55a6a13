"""The public :class:`Calibrator`: a calibration problem, its forward model and the
search strategies wired together.

* :mod:`.problem` -- what is fitted (:class:`~.problem.Parameter`), to what
  (:class:`~.problem.Measurements`), the mismatch, the result;
* :mod:`.forward_model` -- the twin's channel at parameter values, with gradients
  (Sionna RT through Dr.Jit);
* :mod:`.search` -- the strategies: gradient fit, polish, basin hops, scans.
"""

from __future__ import annotations

import numpy as np

from .forward_model import ForwardModel, SolverSettings
from .problem import (
    CalibrationResult,
    Measurements,
    Parameter,
    as_links,
    check_parameters,
    residual_db,
    unobserved,
)
from .search import HOP_PER_WAVELENGTH, HOP_SPAN, POLISH_STEPS, BasinHop, GradientFit, Polish, scan


class Calibrator:
    """Fits :class:`~.problem.Parameter` s of a scene to :class:`~.problem.Measurements`.

    The calibrator's model owns ``scene`` (:class:`~.forward_model.ForwardModel`: it
    adds its own devices, replaces the arrays and writes object offsets straight into
    Mitsuba's vertex buffers, which the ``TwinScene``'s edit bookkeeping does not see):
    do not trace the twin with this scene afterwards; load the calibrated folder
    (:func:`isac_twin.calibration.write_calibrated_scene`) instead.

    Args:
        scene: the twin's scene (``isac_twin.scene.twin_scene.load_scene``).
        measurements: what was measured: one link's :class:`~.problem.Measurements`,
            or a list of them, one per link (transmitter), on the same subcarriers;
            each snapshot counts the same in the mismatch, whichever its link.
        params: what to fit (at least one).
        solver: :class:`~.forward_model.SolverSettings`.

    Raises:
        CalibrationError: unknown material/object, a parameter given twice, no
            measurements, links measured on other subcarriers.
    """

    def __init__(self, scene, measurements: Measurements | list[Measurements],
                 params: list[Parameter], solver: SolverSettings | None = None):
        self.params = check_parameters(params)
        #: The measurements, one :class:`~.problem.Measurements` per link.
        self.links = as_links(measurements)
        self._one_link = isinstance(measurements, Measurements)
        self.settings = solver or SolverSettings()
        #: The forward model (:class:`~.forward_model.ForwardModel`).
        self.model = ForwardModel(scene, self.links, self.params, self.settings)
        #: ``[P]`` the parameters' values in the scene as loaded, physical units.
        self.initial = self.model.initial
        #: ``[P]`` each parameter's typical change (:meth:`~.problem.Parameter.typical_change`).
        self.scales = np.array([p.typical_change(v) for p, v in zip(self.params, self.initial)])
        self._at_initial = None  # (mismatch, gradient, model) at the scene's values
        #: The last :meth:`polish`: its first step's trials per parameter name and
        #: whether every step reached its last size (None before one ran).
        self.polish_trials: dict[str, list] = {}
        self.polish_converged: bool | None = None
        #: The last :meth:`hop`: per scanned parameter name, its scan and what was kept.
        self.hop_report: dict[str, dict] = {}

    @property
    def evaluations(self) -> int:
        """Mismatch evaluations (traces) so far."""
        return self.model.evaluations

    @property
    def step_seconds(self) -> list[float]:
        """Wall time of each gradient evaluation, s."""
        return self.model.step_seconds

    @property
    def buffer_size(self) -> int:
        """Candidate buffer entries of every evaluation, all links (0 before the first)."""
        return self.model.candidates.buffer_size

    @property
    def buffer_regrows(self) -> int:
        """Evaluations that found more candidates than the buffer held."""
        return self.model.candidates.buffer_regrows

    def refresh_chains(self) -> None:
        """New candidates at the next trace, at the geometry then
        (:meth:`~.candidates.Candidates.refresh`)."""
        self.model.refresh_chains()

    def evaluate(self, values, grad: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
        """Mismatch at ``values`` (physical units, ``[P]``).

        Returns:
            ``(mismatch dB^2, gradient [P] in dB^2 per unit, model power [N, K, Nr, Nt]
            dB)``; the model is a list of those, one per link, when the calibrator was
            given a list of measurements.
        """
        f, g, models = self.model.evaluate(values, grad)
        return f, g, models[0] if self._one_link else models

    def visibility(self, values=None) -> dict[str, dict]:
        """How much of the measured channel each parameter's target touches
        (:meth:`~.forward_model.ForwardModel.visibility`)."""
        return self.model.visibility(values)

    def scan(self, index: int, values, start=None) -> np.ndarray:
        """Mismatch along parameter ``index`` (:func:`~.search.scan`), dB^2, ``[S]``."""
        return scan(self, index, values, start)

    def fit(self, *, max_steps: int = 30, ftol: float = 1e-7, gtol: float = 1e-6,
            start=None, free=None, trust: float | None = None) -> CalibrationResult:
        """Fit by L-BFGS-B inside the bounds (:class:`~.search.GradientFit`, whose
        settings these are) from ``start`` (default the scene's values) over ``free``
        (indices, default all); the scene is left at the fitted values."""
        return GradientFit(max_steps, ftol, gtol, trust)(self, start, free,
                                                         on_evaluation=self._keep_initial)

    def _keep_initial(self, x, out) -> None:
        """Keep the fit's evaluation at the scene's values for :meth:`result`."""
        if self._at_initial is None and np.array_equal(x, self.initial):
            self._at_initial = out

    def polish(self, start, free, *, steps: tuple[float, float] = POLISH_STEPS,
               max_evaluations: int = 400,
               refresh: bool = True) -> tuple[np.ndarray, float, int]:
        """Pattern search on traced values (:class:`~.search.Polish`, whose settings
        these are) from ``start`` over ``free`` (indices).

        Returns:
            ``(values [P], mismatch dB^2, traces)``; :attr:`polish_converged` says whether
            every step reached ``steps[1]`` (else ``max_evaluations`` ended it).
        """
        r = Polish(steps, max_evaluations, refresh)(self, start, free)
        self.polish_trials, self.polish_converged = r.trials, r.converged
        return r.values, r.mismatch, r.traces

    def hop(self, start, free, *, unseen=(), span: tuple[float, float] = HOP_SPAN,
            per_wavelength: int = HOP_PER_WAVELENGTH,
            steps: tuple[float, float] = POLISH_STEPS) -> tuple[np.ndarray, float, int]:
        """Move x/y offsets and yaws of ``free`` (indices) into a lower half-wavelength
        basin (:class:`~.search.BasinHop`, whose settings these are); ``unseen``: indices
        the start gradient did not see.

        Returns:
            ``(values [P], mismatch dB^2, traces)``; :attr:`hop_report` lists, per
            scanned parameter name, the shifts (m; rad for a yaw), their mismatch, the
            mismatch before its scan, the shift searched, where that search ended and
            whether it was kept.
        """
        r = BasinHop(span, per_wavelength, steps)(self, start, free, unseen)
        self.hop_report = r.report
        return r.values, r.mismatch, r.traces

    def result(self, final, *, converged: bool, message: str,
               history: list[float] | None = None) -> CalibrationResult:
        """The :class:`~.problem.CalibrationResult` of ``final`` (physical units,
        ``[P]``), traced afresh and reported against the scene's values; leaves the
        scene at ``final``."""
        final = np.asarray(final, float).reshape(-1)
        if self._at_initial is None:  # report against the scene's values
            self._at_initial = self.evaluate(self.initial)
        first = dict(zip(("f", "g", "model"), self._at_initial))
        self.refresh_chains()  # the final values' own chains
        f_final, _, model = self.evaluate(final, grad=False)  # leaves the scene there

        def rms(models):  # per snapshot, the links' snapshots one after the other
            return residual_db([models] if self._one_link else models, self.links)

        residual, residual0 = rms(model), rms(first["model"])
        names = [p.name for p in self.params]
        return CalibrationResult(
            names=names, initial=self.initial.copy(), final=final, gradient_initial=first["g"],
            unobserved=unobserved(first["g"] * self.scales, names),
            mismatch_initial=first["f"], mismatch_final=f_final, residual_db=residual,
            converged=bool(converged), message=message, evaluations=self.evaluations,
            seconds_per_step=float(np.mean(self.step_seconds)) if self.step_seconds else 0.0,
            history=list(history or []),
            residual_db_initial=residual0)
