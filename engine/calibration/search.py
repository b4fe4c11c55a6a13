"""The search strategies of a calibration: callable objects, each with its settings.

* :class:`GradientFit` -- L-BFGS-B on the forward model's gradients inside the
  parameters' bounds, optionally in trust-box rounds;
* :class:`Polish` -- a coordinate pattern search on traced values (no gradients),
  which goes on where a path appears or disappears and the line search stops;
* :class:`BasinHop` -- x/y offsets and yaws scanned across the next
  half-wavelength basins of the magnitude mismatch, the lower one searched;
* :func:`scan` -- the mismatch along one parameter.

Each is called with the :class:`~isac_twin.calibration.Calibrator` it
searches (its ``params``, ``scales``, ``initial``, ``evaluate``, ``refresh_chains``
and ``model``) and leaves the scene at the values it returns. SciPy's L-BFGS-B keeps
every parameter inside its physical bounds and decides convergence (relative
mismatch change or projected gradient below tolerance); the result says whether it
converged and why.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import CalibrationError

log = logging.getLogger(__name__)

#: :class:`GradientFit` with ``trust``: another round while the last one lowered the
#: mismatch by more than this fraction.
ROUND_GAIN = 0.01

#: Trial steps of one L-BFGS-B line search in a trust-box round of :class:`GradientFit`
#: (SciPy's default 20 without ``trust``: near an exact minimum, 1e-9 dB^2, the shorter
#: search ended "ABNORMAL" where SciPy's converged). Where a path appears or
#: disappears the mismatch jumps and the line search fails; SciPy then shrank the step
#: 20 times down to moves too small to change a float32 vertex (lab: 20 evaluations
#: at exactly 1.7018 dB^2, 200 of the first fit's 324).
MAX_LINE_SEARCH = 6

#: L-BFGS-B's "ABNORMAL" line-search end counts as converged when this many last
#: evaluations all equal the best mismatch (:func:`_flat_tail`).
FLAT_TAIL = 4


def _flat_tail(history: list[float]) -> bool:
    """The last :data:`FLAT_TAIL` mismatches all equal the lowest one seen."""
    return len(history) >= FLAT_TAIL and all(f == min(history) for f in history[-FLAT_TAIL:])


#: :class:`Polish`: first and last step of each parameter, in its ``scale``
#: (x/y 0.5 -> 0.0625 cm, yaw 0.5 -> 0.0625 deg, a material 5 % -> 0.625 %).
POLISH_STEPS = (0.5, 0.0625)

#: :class:`Polish` with chains: enumerate them again after a sweep that
#: moved something once this many traces were made on the last ones (and at the end).
POLISH_REFRESH_TRACES = 40

#: :class:`BasinHop`: the scan of an x/y offset covers shifts between these many
#: wavelengths to either side of its value, in steps of 1 / :data:`HOP_PER_WAVELENGTH`
#: wavelength. The magnitude mismatch has a local minimum about every half wavelength
#: of an object's shift normal to a face it reflects on (period lambda / (2 cos theta)
#: >= lambda / 2), so the next basins lie beyond the current one's quarter period; a
#: basin is about +-1 cm wide at 2.4 GHz (lab, Table_2's y: period ~7 cm, 0.40 dB^2 at
#: 0.2 cm from the bottom of its true basin, 0.43-0.68 dB^2 at 0.6-1.7 cm).
HOP_SPAN = (0.3, 0.6)
HOP_PER_WAVELENGTH = 12
#: The lowest other basin of every scan is searched, whatever its scan points say: the
#: points miss a basin's bottom by up to half a step, and with the chain model a
#: basin is narrow (lab, 32 subcarriers: Table_2's y a period off, its true basin
#: scanned 0.43 dB^2 at the nearest point, 2.1 x the current 0.204, and its bottom
#: was 0.085; a limit of 1.25 x left it a period off). This many times the current
#: mismatch is the limit (a basin scanned higher is not searched).
HOP_SLACK = 4.0
#: ... and a searched basin is kept only when it lowers the mismatch by more than this
#: fraction (a shift along a face the lap does not see scans flat to ~1 %: lab, Table_2's
#: x, 0.287-0.293 dB^2 over 16 cm).
HOP_GAIN = 0.01
#: ... and by more than this, dB^2 (0.03 dB RMS): at a noise-free fit's 1e-7 dB^2, 1 %
#: is float noise, and a flat shift moved 4.7 cm for it.
HOP_MIN_GAIN_DB2 = 1e-3
#: ... and, for a coordinate the start gradient did not see (``unseen``), by more than
#: this fraction: along a face the lap does not see, the mismatch scans flat to ~2 %
#: (lab: Table_2's x, 0.287-0.293 dB^2 over 16 cm), so 1 % moved SwitchBox_2's unseen
#: y by 9.9 cm for a 1.1 % gain; where a path appears the gain is larger (Chair_2's x:
#: 5.5 % and 7.4 % in two runs).
HOP_GAIN_UNSEEN = 0.03


def local_minima(f: np.ndarray) -> np.ndarray:
    """Indices of the local minima of ``f [S]`` (ends included), lowest first."""
    f = np.asarray(f, float)
    idx = [i for i in range(len(f)) if (i == 0 or f[i] <= f[i - 1])
           and (i == len(f) - 1 or f[i] <= f[i + 1])]
    return np.array(sorted(idx, key=lambda i: f[i]), int)


def scan(cal, index: int, values, start=None) -> np.ndarray:
    """Mismatch (dB^2, ``[S]``) with parameter ``index`` set to each of ``values``
    (physical units, ``[S]``, clipped to its bounds) and the others at ``start``
    (default the scene's values); no gradients.

    A slab's reflection is nearly periodic in ``sqrt(permittivity)`` with period
    ``wavelength / (2 thickness)`` (multiple reflections inside it), so over a
    narrow band the mismatch has one local minimum per period: scan permittivity
    on a grid finer than that before a :class:`GradientFit`.
    """
    base = np.array(cal.initial if start is None else start, float)
    lo, hi = cal.params[index].limits
    out = []
    for v in np.clip(np.asarray(values, float).reshape(-1), lo, hi):
        x = base.copy()
        x[index] = v
        out.append(cal.evaluate(x, grad=False)[0])
    return np.array(out)


@dataclass(frozen=True)
class GradientFit:
    """L-BFGS-B on the forward model's gradients, inside the parameters' bounds.

    Attributes:
        max_steps: most optimiser iterations.
        ftol: stop when the relative mismatch change per step is below this.
        gtol: stop when the projected gradient (per ``scale``) is below this, dB^2.
        trust: None, or fit in rounds, each inside a box of +-``trust`` typical
            changes (``scale``) about the round's start, a new round from where a
            round ended while a round lowers the mismatch by more than
            :data:`ROUND_GAIN` of it (``max_steps`` iterations in all).
    """

    max_steps: int = 30
    ftol: float = 1e-7
    gtol: float = 1e-6
    trust: float | None = None

    def __call__(self, cal, start=None, free=None, on_evaluation=None):
        """Fit by L-BFGS-B inside the bounds.

        Args:
            cal: the :class:`~isac_twin.calibration.Calibrator`.
            start: ``[P]`` values to start from (physical units; e.g. the best of a
                :func:`scan`); default the scene's values. ``initial`` in the result
                stays the scene's values.
            free: indices of the parameters to fit (default all); the others stay at
                ``start`` (e.g. materials held while poses are fitted).
            on_evaluation: called with ``(values, (mismatch, gradient, model))``
                after each evaluation.

        Returns:
            :class:`~isac_twin.calibration.problem.CalibrationResult`
            (``cal.result``); the scene is left at the fitted values.
        """
        from scipy.optimize import minimize

        max_steps, ftol, gtol, trust = self.max_steps, self.ftol, self.gtol, self.trust
        x0 = cal.initial if start is None else np.asarray(start, float).reshape(-1)
        if x0.shape != cal.initial.shape:
            raise CalibrationError(f"fit: start must have {len(cal.initial)} values, "
                                   f"got {x0.shape}")
        x0 = np.clip(x0, [p.limits[0] for p in cal.params], [p.limits[1] for p in cal.params])
        idx = np.arange(len(x0)) if free is None else np.unique(np.asarray(free, int))
        if len(idx) == 0 or idx.min() < 0 or idx.max() >= len(x0):
            raise CalibrationError(f"fit: free must name parameters 0..{len(x0) - 1}, "
                                   f"got {free!r}")
        sc = cal.scales[idx]
        history: list[float] = []

        def values(u):
            x = x0.copy()
            x[idx] += u * sc
            return x

        def fun(u):
            x = values(u)
            f, g, model = cal.evaluate(x)
            history.append(f)
            if on_evaluation is not None:
                on_evaluation(x, (f, g, model))
            log.info("calibrate: step %d mismatch %.5g dB^2 at %s", len(history), f,
                     np.round(x, 6).tolist())
            return f, g[idx] * sc

        lo = np.array([(cal.params[i].limits[0] - x0[i]) / s for i, s in zip(idx, sc)])
        hi = np.array([(cal.params[i].limits[1] - x0[i]) / s for i, s in zip(idx, sc)])
        if trust is None:
            res = minimize(fun, np.zeros(len(idx)), jac=True, method="L-BFGS-B",
                           bounds=list(zip(lo, hi)),
                           options={"maxiter": max_steps, "ftol": ftol, "gtol": gtol})
            u, rounds = res.x, 1
        else:
            # rounds of L-BFGS-B in a box of +-trust (scaled units) about the round's
            # start, a new round (fresh candidates and curvature memory) while a round
            # lowers the mismatch by more than ROUND_GAIN. Unbounded, L-BFGS-B's
            # quasi-Newton trial steps jump several cm, across the half-wavelength
            # basins of a magnitude mismatch (lab: trial mismatches of 9-10 dB^2 from
            # 7.6, then a stall at 7.56 after 52 evaluations)
            u, steps_left, rounds, best = np.zeros(len(idx)), max_steps, 0, np.inf
            while steps_left > 0:
                cal.model.candidates.freeze = True  # this round's candidates or chains
                cal.refresh_chains()
                res = minimize(fun, u, jac=True, method="L-BFGS-B",
                               bounds=list(zip(np.maximum(lo, u - trust),
                                               np.minimum(hi, u + trust))),
                               options={"maxiter": steps_left, "ftol": ftol, "gtol": gtol,
                                        "maxls": MAX_LINE_SEARCH})
                rounds += 1
                steps_left -= max(1, int(res.nit))
                gain = best - float(res.fun)
                u, best = res.x, min(best, float(res.fun))
                if gain <= ROUND_GAIN * abs(best):
                    break
            cal.model.candidates.release()
        converged, message = bool(res.success), str(res.message)
        if not converged and message.startswith("ABNORMAL") and _flat_tail(history):
            # the line search's trial steps all gave the best value: no step it
            # can take changes the traced geometry's mismatch (float32 vertices),
            # a minimum to that resolution (a noise-free room: 1e-9 dB^2)
            converged = True
            message += (f" at the float32 floor: the last {FLAT_TAIL} evaluations equal "
                        f"the best mismatch, {min(history):.3g} dB^2")
        return cal.result(values(u), converged=converged,
                          message=message + (f" ({rounds} trust-box rounds)" if trust else ""),
                          history=history)


@dataclass
class SearchResult:
    """Where a search on traced values ended.

    Attributes:
        values: ``[P]`` physical units.
        mismatch: dB^2 there.
        traces: evaluations made.
    """

    values: np.ndarray
    mismatch: float
    traces: int


@dataclass
class PolishResult(SearchResult):
    """Where a :class:`Polish` ended (:class:`SearchResult`), and

    Attributes:
        converged: every step reached its last size (else the trace limit ended it).
        trials: per parameter name, ``[[move (physical units), mismatch change dB^2],
            ...]`` of the first step.
    """

    converged: bool = False
    trials: dict[str, list] = field(default_factory=dict)


@dataclass(frozen=True)
class Polish:
    """Coordinate pattern search on traced values.

    Attributes:
        steps: first and last step of each parameter, in its ``scale``.
        max_evaluations: most traces.
        refresh: enumerate the chains at the start (False: those kept so far).
    """

    steps: tuple[float, float] = POLISH_STEPS
    max_evaluations: int = 400
    refresh: bool = True

    def __call__(self, cal, start, free) -> PolishResult:
        """Coordinate pattern search from ``start`` (physical units, ``[P]``) over the
        parameters ``free`` (indices), no gradients: each trace with fresh candidates,
        or with ``settings.chains`` the chains enumerated at the start and again after
        every sweep that moved something (:attr:`refresh` False: the chains kept so far).

        For each free parameter in turn: try ``+-step`` (in its ``scale``); keep a move
        that lowers the mismatch, else halve its step; until every step is below
        ``steps[1]`` (``steps[0]`` first) or ``max_evaluations`` traces. The mismatch
        jumps wherever a path appears or disappears (a reflection point leaves its
        face, a candidate ray misses it), which stops L-BFGS-B's line search (lab:
        Rack_2's yaw left 0.9 deg off, where 1 deg further along lowered the mismatch
        from 1.29 to 0.83 dB^2); a search that compares traced values is not stopped.

        Returns:
            :class:`PolishResult`.
        """
        steps, max_evaluations = self.steps, self.max_evaluations
        x = np.clip(np.asarray(start, float).reshape(-1).copy(),
                    [p.limits[0] for p in cal.params], [p.limits[1] for p in cal.params])
        free = [int(i) for i in free]
        if not all(0 <= i < len(x) for i in free):
            raise CalibrationError(f"polish: free must name parameters 0..{len(x) - 1}, "
                                   f"got {free!r}")
        step = {i: steps[0] * cal.scales[i] for i in free}
        if self.refresh:  # (else the chains kept so far: the hop's searches)
            cal.refresh_chains()
        f = cal.evaluate(x, grad=False)[0]
        # name -> [[move (physical units), mismatch change dB^2], ...] of the first step
        trials = {cal.params[i].name: [] for i in free}
        n = n_at = 1
        at = x.copy()  # where the chains were enumerated
        stale = self.refresh and cal.settings.chains  # (else nothing to refresh)

        def active():
            return any(step[i] >= steps[1] * cal.scales[i] * (1 - 1e-9) for i in free)

        while n < max_evaluations and (active() or (stale and not np.array_equal(x, at))):
            if stale and not np.array_equal(x, at) and (
                    n - n_at >= POLISH_REFRESH_TRACES or not active()):
                # sweeps moved something: the chains of where they ended (the kept
                # chains' reflection points lag the moved objects; lab: the hop's
                # fresh chains traced the polish's end at another mismatch). Not
                # after every such sweep: late in a search a sweep is a few traces
                # of the coordinates still searched, and an enumeration (~1 s on the
                # lab) cost more than they did
                cal.refresh_chains()
                f, at, n_at = cal.evaluate(x, grad=False)[0], x.copy(), n
                n += 1
                if not active():  # the end, on fresh chains: one more sweep there
                    step = {i: steps[1] * cal.scales[i] for i in free}
            for i in free:
                if step[i] < steps[1] * cal.scales[i] * (1 - 1e-9) or n >= max_evaluations:
                    continue
                lo, hi = cal.params[i].limits
                for sgn in (1.0, -1.0):
                    y = x.copy()
                    y[i] = float(np.clip(x[i] + sgn * step[i], lo, hi))
                    if y[i] == x[i]:
                        continue
                    fy = cal.evaluate(y, grad=False)[0]
                    n += 1
                    if step[i] == steps[0] * cal.scales[i]:
                        trials[cal.params[i].name].append(
                            [float(y[i] - x[i]), float(fy - f)])
                    if fy < f:
                        x, f = y, fy
                        break
                else:
                    step[i] /= 2.0
        converged = not active()
        cal.evaluate(x, grad=False)  # leave the scene there
        log.info("calibrate: polish %d traces -> %.5g dB^2", n, f)
        return PolishResult(x, f, n, converged, trials)


def _hop_gain(i: int, unseen) -> float:
    return HOP_GAIN_UNSEEN if i in unseen else HOP_GAIN


@dataclass
class HopResult(SearchResult):
    """Where a :class:`BasinHop` ended (:class:`SearchResult`), and

    Attributes:
        report: per scanned parameter name, the shifts (m; rad for a yaw), their
            mismatch, the mismatch before its scan, the shift searched, where that
            search ended and whether it was kept.
    """

    report: dict[str, dict] = field(default_factory=dict)


@dataclass(frozen=True)
class BasinHop:
    """Scans of x/y offsets and yaws across the next half-wavelength basins.

    Attributes:
        span: the scan of an x/y offset covers shifts between these many wavelengths
            to either side of its value (:data:`HOP_SPAN`).
        per_wavelength: in steps of 1 / this wavelength.
        steps: the basins' searches end at ``steps[1]`` (in each parameter's ``scale``).
    """

    span: tuple[float, float] = HOP_SPAN
    per_wavelength: int = HOP_PER_WAVELENGTH
    steps: tuple[float, float] = POLISH_STEPS

    def __call__(self, cal, start, free, unseen=()) -> HopResult:
        """Move x/y offsets and yaws into a lower half-wavelength basin.

        From ``start`` (physical units, ``[P]``), for each x, y or yaw parameter of
        ``free`` (indices; others are skipped) in turn: trace (no gradients; the chains
        of the start, with ``settings.chains``, else fresh candidates) its value shifted
        by every multiple of ``wavelength / per_wavelength`` between ``span[0]`` and
        ``span[1]`` wavelengths to either side (a yaw: turns that move the object's
        farthest vertex so far, from one step on) inside its bounds; take the lowest
        local minimum of that scan other than the current value's basin; if it is
        below :data:`HOP_SLACK` times the current mismatch, search it (the calibrator's
        ``polish`` on that coordinate alone, from half a scan step down to ``steps[1]``).
        Then, the best first, a searched basin that gains more than :data:`HOP_GAIN` of the
        mismatch (:data:`HOP_GAIN_UNSEEN` for a parameter of ``unseen``, indices the
        start gradient did not see) and :data:`HOP_MIN_GAIN_DB2` is traced with its own
        chains and kept if it still does (searched again from the values so far once
        another was kept).

        A :class:`GradientFit` and a :class:`Polish` end in the basin they start in; the
        magnitude mismatch repeats about every half wavelength of a shift normal to a
        reflecting face, so an object that starts more than ~1/4 wavelength away (the
        lab's Table_2: 6.9 cm at 12.5 cm wavelength) ends a period off, where the
        truth's basin is lower (0.28 against 0.39 dB^2 there).

        Returns:
            :class:`HopResult`.
        """
        span, per_wavelength, steps = self.span, self.per_wavelength, self.steps
        x = np.asarray(start, float).reshape(-1).copy()
        free = [int(i) for i in free]
        unseen = {int(i) for i in unseen}
        if not all(0 <= i < len(x) for i in [*free, *unseen]):
            raise CalibrationError(f"hop: free and unseen must name parameters "
                                   f"0..{len(x) - 1}, got {free!r} and {sorted(unseen)!r}")
        step = float(cal.model.sc.wavelength[0]) / per_wavelength
        found = []  # (mismatch, index, value) of the searched basins that gained
        k = np.arange(int(math.ceil(span[0] * per_wavelength)),
                      int(math.floor(span[1] * per_wavelength)) + 1)
        k = np.concatenate([-k[::-1], [0], k])
        # a yaw's ring starts at one step: a turn has nearer basins too (lab: Chair_2
        # at -0.87 deg where the truth is +0.89, 1.76 deg or ~1 cm at its corners away)
        k_yaw = np.arange(1, int(math.floor(span[1] * per_wavelength)) + 1)
        k_yaw = np.concatenate([-k_yaw[::-1], [0], k_yaw])
        cal.refresh_chains()
        f = cal.evaluate(x, grad=False)[0]
        n = 1
        report = {}
        steps_of = {}
        for i in free:
            p = cal.params[i]
            if p.kind in ("x", "y"):
                steps_of[i] = step
            elif p.kind == "yaw":
                # a turn moves the object's farthest vertex by radius x angle: the same
                # shifts there (lab: Table_1's yaw 3.6-3.9 deg off, a basin away)
                steps_of[i] = step / cal.model.object_radius(p.target)
            else:
                continue
            lo, hi = p.limits
            ring = k_yaw if p.kind == "yaw" else k
            grid = np.unique(np.clip(x[i] + steps_of[i] * ring, lo, hi))
            at = int(np.argmin(np.abs(grid - x[i])))
            grid[at] = x[i]
            fs = np.insert(scan(cal, i, np.delete(grid, at), x), at, f)
            n += len(grid) - 1
            # the current basin: the points rising away from the current value (the
            # scan skips the shifts within span[0])
            own = {at}
            for d in (-1, 1):
                j = at
                while 0 <= j + d < len(grid) and fs[j + d] >= fs[j]:
                    j += d
                    own.add(j)
            others = [j for j in local_minima(fs) if j not in own]
            entry = {"shifts_m": (grid - x[i]).tolist(), "mismatch_db2": fs.tolist(),
                     "mismatch_before_db2": float(f), "tried_m": None,
                     "mismatch_after_db2": None, "kept": False}
            if others and fs[others[0]] < HOP_SLACK * f:
                j = others[0]
                y = x.copy()
                y[i] = grid[j]
                z, fz, m = cal.polish(y, [i], steps=(0.5 * steps_of[i] / cal.scales[i],
                                                     steps[1]), refresh=False)
                n += m
                entry.update(tried_m=float(z[i] - x[i]), mismatch_after_db2=float(fz))
                if f - fz > max(_hop_gain(i, unseen) * f, HOP_MIN_GAIN_DB2):
                    found.append((fz, i, float(z[i])))
            report[p.name] = entry
        # the best first: the searches all started from the same values, and a hop kept
        # early took the gain of a later, larger one (lab: Rack_2's y moved 8.9 cm
        # while Table_2's y was a period off, then Table_2's hop could not undo it)
        x0 = x.copy()
        for fz, i, zi in sorted(found):
            y = x.copy()
            y[i] = zi
            if not np.array_equal(x, x0):  # another hop was kept: search again from it
                y, fz, m = cal.polish(y, [i], steps=(0.25 * steps_of[i] / cal.scales[i],
                                                     steps[1]), refresh=False)
                n += m
            cal.refresh_chains()  # its own chains there
            fz = cal.evaluate(y, grad=False)[0]
            n += 1
            entry = report[cal.params[i].name]
            entry.update(tried_m=float(y[i] - x0[i]), mismatch_after_db2=float(fz))
            if f - fz > max(_hop_gain(i, unseen) * f, HOP_MIN_GAIN_DB2):
                x, f = y, fz
                entry["kept"] = True
            cal.refresh_chains()
        cal.model.apply(x, False)  # leave the scene there (no trace: fresh chains follow)
        log.info("calibrate: hop %d traces -> %.5g dB^2", n, f)
        return HopResult(x, f, n, report)
