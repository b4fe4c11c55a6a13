"""Calibrate a scene folder from a recording (``isac-twin calibrate``).

:func:`calibrate_recording` reads the recorded CSI of every link (or the links
named) at the robot's recorded poses
(:func:`~isac_twin.calibration.recording.measurements_from_recording`), fits the
chosen parameters (:func:`default_parameters`) with
:class:`isac_twin.calibration.Calibrator` (a first joint fit, scans of each
permittivity (:func:`permittivity_grid`) and optionally of each pose offset
(:func:`pose_grid`), gradient fits from the scans' minima, then a polish and basin
hops of the objects with a path to the robot) and writes

* ``DIR/scene/``: the calibrated scene folder
  (:func:`~isac_twin.calibration.calibrated_scene.write_calibrated_scene`);
* ``DIR/calibration.png``: :func:`isac_twin.calibration.figure.plot_report` of it;
* ``DIR/calibration.json``: every parameter before/after with its
  sensitivity, the mismatch before/after, the residual per snapshot, what
  the measurements did not see (:mod:`~isac_twin.calibration.observability`),
  convergence, time per gradient step.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CalibrationError
from ..phy.units import SPEED_OF_LIGHT
from .calibrated_scene import calibrated_materials, material_users, write_calibrated_scene
from .calibrator import Calibrator
from .figure import plot_report
from .forward_model import SolverSettings
from .observability import CLEAR_PATH_SHARE, object_paths, observability
from .problem import MATERIAL_KINDS, Parameter
from .recording import measurements_from_recording
from .search import local_minima

#: Materials whose parameters are not fitted by default: a metal reflects (almost)
#: totally whatever its conductivity, so the channel does not see it.
NOT_FITTED_BY_DEFAULT = ("metal",)


def default_parameters(scene, what: tuple[str, ...], objects: list[str],
                       materials: list[str] | None = None) -> list[Parameter]:
    """Parameters for ``what`` (``"materials"``: permittivity and conductivity of each of
    ``materials`` (names as :func:`material_users` takes them), default every material
    of the scene but :data:`NOT_FITTED_BY_DEFAULT`; ``"poses"``: x, y, yaw of each
    object in ``objects``)."""
    params: list[Parameter] = []
    for w in what:
        if w == "materials":
            if materials:
                for mat in materials:
                    if not material_users(scene, mat):
                        have = sorted({o.material for o in scene.objects.values()})
                        raise CalibrationError(f"calibrate: --materials: no object has material "
                                               f"{mat!r} (have: {', '.join(have)}; or "
                                               "'<type>-<thickness>')")
                    params += [Parameter(k, mat) for k in MATERIAL_KINDS]
                continue
            for mat in sorted({o.material for o in scene.objects.values()}):
                if mat not in NOT_FITTED_BY_DEFAULT:
                    params += [Parameter(k, mat) for k in MATERIAL_KINDS]
        elif w == "poses":
            if not objects:
                raise CalibrationError("calibrate: --params poses needs --objects NAMES")
            for name in objects:
                if name not in scene.objects:
                    raise CalibrationError(f"calibrate: --objects: no object {name!r} in the "
                                           f"scene (objects: {', '.join(scene.objects)})")
                params += [Parameter(k, name) for k in ("x", "y", "yaw")]
        else:
            raise CalibrationError(f"calibrate: --params: {w!r} is not one of materials, poses")
    return params


def permittivity_grid(scene, material: str, eps0: float, factor: float = 2.0,
                      per_period: int = 6, min_points: int = 12) -> np.ndarray:
    """Start values for a permittivity scan, ``[S]``: ``eps0 / factor .. eps0 * factor``
    (at least 1), uniform in ``sqrt(eps)`` with ``per_period`` points per period
    ``wavelength / (2 d)`` of the thickest slab ``d`` (m) of ``material``, and at least
    ``min_points`` (a thin slab's period is wider than the range: 3 cm of wood at
    2.4 GHz gave 4 points, 30-55 % apart)."""
    lam = 299_792_458.0 / scene.config.scene.frequency_hz
    d = max((o.thickness for o in material_users(scene, material)), default=0.1)
    lo, hi = math.sqrt(max(1.0, eps0 / factor)), math.sqrt(eps0 * factor)
    n = int(math.ceil((hi - lo) / (lam / (2 * d) / per_period))) + 1
    return np.linspace(lo, hi, max(n, min_points, 2)) ** 2


def pose_grid(p: Parameter, wavelength: float, per_wavelength: int = 8) -> np.ndarray:
    """Start values for a pose scan, ``[S]``: x/y offsets over the parameter's bounds in
    steps of ``wavelength / per_wavelength`` (m); yaw in 1 deg steps within +-5 deg."""
    lo, hi = p.limits
    if p.kind == "yaw":
        lo, hi = max(lo, -math.radians(5)), min(hi, math.radians(5))
        return np.linspace(lo, hi, int(round(math.degrees(hi - lo))) + 1)
    lo, hi = max(lo, -0.1), min(hi, 0.1)
    return np.linspace(lo, hi, int(math.ceil((hi - lo) / (wavelength / per_wavelength))) + 1)


#: After a first joint fit, the fits from the permittivity scans' minima run only when a
#: scan point beats the first fit's mismatch by more than this fraction (a better basin).
REFIT_GAIN = 0.01

#: :meth:`~isac_twin.calibration.Calibrator.polish` steps after a :meth:`hop` moved an
#: offset (in each parameter's ``scale``): the other poses are near their minimum.
POLISH_STEPS_AFTER_HOP = (0.25, 0.0625)

#: At most this many rounds of :meth:`~isac_twin.calibration.Calibrator.hop` and polish (a
#: round follows while the last one's hop moved something; lab: a third round moved
#: nothing in two runs, 32-33 s each of 250-302)
HOP_ROUNDS = 2


@dataclass
class RunOutput:
    scene_dir: Path
    report_path: Path
    report: dict


def recording_calibrator(scene, recording, *, what: tuple[str, ...], objects, materials,
                         links=None, max_snapshots: int, max_subcarriers: int,
                         noise: bool = True, solver: SolverSettings | None = None):
    """The :class:`Calibrator` :func:`calibrate_recording` fits with (its arguments of
    the same names): ``(measured, params, calibrator)``, ``measured`` as
    :func:`measurements_from_recording` gives it. One definition, so that another
    evaluation of the same recording (the lab's mismatch at the truth) is of the
    same model."""
    measured = measurements_from_recording(recording, scene.config, links=links,
                                           max_snapshots=max_snapshots,
                                           max_subcarriers=max_subcarriers, noise=noise)
    params = default_parameters(scene, tuple(what), list(objects or []), materials)
    cal = Calibrator(scene, [m for _, m in measured], params,
                     solver or SolverSettings.from_tracer(scene.config.tracer))
    return measured, params, cal


def calibrate_recording(scene_dir: str | Path, recording: str | Path, out: str | Path, *,
                        what: tuple[str, ...] = ("materials",), objects: list[str] | None = None,
                        links: list[tuple[str, str]] | None = None, max_snapshots: int = 6,
                        max_subcarriers: int = 16, max_steps: int = 30,
                        solver: SolverSettings | None = None, scan: bool = True,
                        multistart: int = 3, materials: list[str] | None = None,
                        pose_scan: bool = False, trust: float | None = 1.5,
                        polish: bool = True, hop: bool = True,
                        noise: bool = True) -> RunOutput:
    """Fit the scene at ``scene_dir`` to ``recording``; write ``out/scene`` and
    ``out/calibration.json`` (see the module doc). ``solver``: default the scene's
    ``[tracer]`` settings (:meth:`SolverSettings.from_tracer`). ``scan``: start each
    permittivity from the best of :func:`permittivity_grid` (the mismatch has a local
    minimum per slab resonance, see :meth:`Calibrator.scan`) and fit from the ``multistart``
    best local minima of the scans; the fit with the lowest mismatch wins. With poses fitted
    too, a first joint fit from the scene's values comes first, the scans run at its poses,
    and the fits from their minima only when a scan point beats it by more than
    :data:`REFIT_GAIN`. ``materials``: the materials fitted with ``"materials"`` (default
    all but metal; see :func:`default_parameters`). ``pose_scan``: before fitting, set each
    pose offset in turn to the best of :func:`pose_grid` (the magnitude mismatch has a local
    minimum about every half wavelength of an object's shift); costs one trace per grid
    point. ``trust``: with poses fitted, each fit runs in rounds inside a box of +-``trust``
    typical changes (1 cm, 1 deg, 10 % of a material value) about the round's start
    (:meth:`~isac_twin.calibration.Calibrator.fit`); None: one unbounded L-BFGS-B.
    ``polish``: then search the seen pose offsets of the objects with a path to the robot,
    and the permittivities, on traced values
    (:meth:`~isac_twin.calibration.Calibrator.polish`); the result is where that search ends
    when it lowered the mismatch. The report's ``objects`` says which objects have a clear
    path (:data:`CLEAR_PATH_SHARE`: the accuracy claimed), ``polish`` what the search did,
    ``could_not_see`` names the objects without a clear path with their numbers. ``hop``:
    after the polish, scan those objects' x/y offsets and yaws across the next
    half-wavelength basins (:meth:`~isac_twin.calibration.Calibrator.hop`) and polish again
    (from :data:`POLISH_STEPS_AFTER_HOP`) when that lowered the mismatch, then again (up to
    :data:`HOP_ROUNDS` rounds) while a hop moves something; the report's ``hop`` gives each
    round's scans. ``noise``: the model's power gets each snapshot's noise variance
    estimated from the recording added (:func:`measurements_from_recording`); the report's
    ``noise_snr_db`` gives the estimates."""
    from ..scene.twin_scene import load_scene

    out = Path(out)
    scene = load_scene(scene_dir)
    measured, params, cal = recording_calibrator(
        scene, recording, what=what, objects=objects, materials=materials, links=links,
        max_snapshots=max_snapshots, max_subcarriers=max_subcarriers, noise=noise,
        solver=solver)
    t_start = time.perf_counter()
    stages: list[dict] = []  # [{"stage", "seconds", "evaluations", "gradient_steps"}]
    clock = [t_start, 0, 0]

    def mark(stage: str) -> None:
        """Close a stage of the report's ``stages``: its wall time and calibrator calls."""
        now, n, g = time.perf_counter(), cal.evaluations, len(cal.step_seconds)
        if n > clock[1]:
            stages.append({"stage": stage, "seconds": now - clock[0],
                           "evaluations": n - clock[1], "gradient_steps": g - clock[2]})
        clock[:] = [now, n, g]

    starts, scans = [cal.initial.copy()], {}
    poses = [i for i, p in enumerate(params) if p.kind in ("x", "y", "yaw")]
    first_fit = None
    if scan and poses and any(p.kind == "permittivity" for p in params):
        # Objects off by centimetres hide a material: on the lab the pose mismatch
        # (7.6 dB^2) is ~700 x what +-10 % of the tables' permittivity changes, and a
        # scan there ran to the end of its range (49.5 % off). Fit everything from the
        # scene's values first, then scan each permittivity with the poses held there.
        first_fit = cal.fit(max_steps=max_steps, trust=trust)
        starts = [first_fit.final.copy()]
        mark("first fit")
    if scan:
        for i, p in enumerate(params):
            if p.kind == "permittivity":
                grid = permittivity_grid(scene, p.target, float(cal.initial[i]))
                f = cal.scan(i, grid, starts[0])
                best = local_minima(f)[:multistart]
                scans[p.name] = {"values": grid.tolist(), "mismatch_db2": f.tolist(),
                                 "starts": grid[best].tolist(),
                                 "at": "fitted poses" if first_fit is not None else "start"}
                new = []
                for x in starts:
                    for j in best:
                        y = x.copy()
                        y[i] = grid[j]
                        new.append(y)
                starts = new[:multistart]
        mark("permittivity scans")
    pose_scans = {}
    if pose_scan:
        lam = SPEED_OF_LIGHT / scene.config.scene.frequency_hz
        for x in starts:  # each coordinate in turn, the others where the scans left them
            for i, p in enumerate(params):
                if p.kind in ("x", "y", "yaw"):
                    grid = pose_grid(p, lam)
                    f = cal.scan(i, grid, x)
                    if np.ptp(f) > 1e-6 * max(float(f.max()), 1e-12):  # else: not seen
                        x[i] = grid[int(np.argmin(f))]
                    pose_scans.setdefault(p.name, []).append(
                        {"values": grid.tolist(), "mismatch_db2": f.tolist(),
                         "start": float(x[i])})
        mark("pose scans")
    better = min((min(v["mismatch_db2"]) for v in scans.values()), default=np.inf)
    deferred = None  # starts whose gradient fits wait for the polish's verdict

    def run_fits(xs):
        done = [cal.fit(max_steps=max_steps, start=x, trust=trust if poses else None)
                for x in xs]
        mark("fits from the scans" if scans or pose_scans else "fit")
        return done

    if (first_fit is not None and (first_fit.converged or polish) and not pose_scans
            and better > (1.0 - REFIT_GAIN) * first_fit.mismatch_final):
        # the scans at the fitted poses found no better basin: no further fits (a first
        # fit stopped where a path appears is continued by the polish on traced values,
        # if an object has a clear path to the robot; lab: the refit from the scan's
        # best gained 0.1 % in 14 gradient steps, and the calibration ended at 0.2587
        # dB^2 in 253 s with it, 0.2386 dB^2 in 237 s without)
        fits, starts = [first_fit], [cal.initial.copy()]
    elif first_fit is not None and polish and not pose_scans:
        # a better basin at the first fit's poses: the polish goes on from the scans'
        # best (every scan's best minimum) instead of a gradient fit from each; the
        # fits run below only when the polish does not (no object has a path).
        # Lab, both links: the refit took 45 gradient steps (38 s of 388) for 1.1 %
        # (0.397 -> 0.3926 dB^2); the polish then went on to 0.3331
        deferred = starts
        fits = [cal.result(starts[0], converged=False,
                           message="the permittivity scans' best at the first fit's poses"),
                first_fit]
        mark("the scans' best")
        starts = [starts[0], cal.initial.copy()]
    else:
        fits = run_fits(starts)
        if first_fit is not None:
            fits.append(first_fit)
            starts = starts + [cal.initial.copy()]
    result = min(fits, key=lambda r: r.mismatch_final)
    objects_seen, polished, hopped = {}, None, None
    if poses:
        at_start = object_paths(cal, cal.initial)
        objects_seen = object_paths(cal, result.final, at_start)
        mark("clear paths")
        # every object whose paths reach the robot, not only those with a clear path:
        # a weak path still shapes a fade, and a clear object's pose made up for it
        # (lab, chain model: at a fit 0.51 deg off in Chair_2's yaw, the objects
        # without a clear path set to their true poses took the mismatch from 0.1445
        # to 0.016 dB^2, the ones with a clear path to the truth alone to 0.156)
        touched = {t for t, o in objects_seen.items()
                   if sum(o["paths_per_snapshot"]) or o["power_share_max_at_start"] > 0}
        free = [i for i in poses if params[i].target in touched
                and params[i].name not in result.unobserved]
        # with the permittivities: a material is observable once the poses are right
        # (lab: 3.1 % and 14.8 % off in two runs polishing the poses alone)
        free += [i for i, p in enumerate(params) if p.kind == "permittivity"
                 and p.name not in result.unobserved] if free else []
        if deferred is not None and not free:
            fits = run_fits(deferred) + [first_fit]
            starts = deferred + [cal.initial.copy()]
            result = min(fits, key=lambda r: r.mismatch_final)
            objects_seen = object_paths(cal, result.final, at_start)
        if polish and free:
            # L-BFGS-B stops where a path appears or disappears; a search on traced
            # values goes on (a gradient fit after it gained 1.6 % on the lab, for 28
            # more evaluations: left out)
            x, f, n = cal.polish(result.final, free)
            mark("polish")
            polished = {"parameters": [params[i].name for i in free], "traces": n,
                        "mismatch_db2": {"before": result.mismatch_final, "after": f},
                        "converged": cal.polish_converged,
                        "first_step_trials": cal.polish_trials}
            # the x/y/yaw of those objects, those the start gradient did not see included:
            # a shift along a face can reveal a path a few cm on (lab: Chair_2's x,
            # -5.5 % mismatch from 4 to 7 cm)
            shifts = [i for i in poses if params[i].target in touched]
            if hop and shifts:
                # both searches end in the half-wavelength basin they start in (lab:
                # Table_2's y a period off, 6.9 cm); scan the next basins, then polish
                # again from a better one, with what the hop moved; and again while a
                # hop moves something: a basin's gain counts against the mismatch of
                # its round, and once a hop took the larger errors away the smaller
                # ones clear the bar (lab: a second round moved Table_2.x, then the
                # polish took the mismatch 0.0175 -> 0.0104 dB^2 and the tables'
                # permittivity from 11.4 to 0.3 % off)
                hopped = {"parameters": [params[i].name for i in shifts], "traces": 0,
                          "mismatch_db2": {"before": f, "after": f}, "moved": [],
                          "rounds": []}
                unseen = [i for i in shifts if params[i].name in result.unobserved]
                for _ in range(HOP_ROUNDS):
                    xh, fh, nh = cal.hop(x, shifts, unseen=unseen)
                    mark("hop")
                    moved = [i for i in shifts if cal.hop_report[params[i].name]["kept"]]
                    rnd = {"traces": nh, "mismatch_db2": {"before": f, "after": fh},
                           "moved": [params[i].name for i in moved],
                           "scans": cal.hop_report, "polish_after": None}
                    hopped["rounds"].append(rnd)
                    hopped["traces"] += nh
                    hopped["mismatch_db2"]["after"] = fh
                    hopped["moved"] += [n for n in rnd["moved"] if n not in hopped["moved"]]
                    if not moved:
                        break
                    x, f, n2 = cal.polish(xh, sorted(set(free) | set(moved)),
                                          steps=POLISH_STEPS_AFTER_HOP)
                    mark("polish after the hop")
                    rnd["polish_after"] = {"traces": n2, "mismatch_db2": f,
                                           "converged": cal.polish_converged}
                    hopped["mismatch_db2"]["after"] = f
            if f < result.mismatch_final:
                result = cal.result(
                    x, converged=cal.polish_converged,
                    message=("pattern search on traced values: every step reached its "
                             "last size" if cal.polish_converged else
                             "pattern search on traced values: trace limit reached")
                    + f", after {result.message}", history=result.history)
                objects_seen = object_paths(cal, result.final, at_start)
    seen = observability(cal, result)
    mark("observability")
    for name in (hopped or {}).get("moved", []):
        if name in result.unobserved:
            e = next(r["scans"][name] for r in hopped["rounds"] if name in r["moved"])
            moved = (f"{math.degrees(e['tried_m']):+.2f} deg" if name.endswith(".yaw")
                     else f"{100 * e['tried_m']:+.2f} cm")
            seen["could_not_see"].append(
                f"{name}: not seen at the start; the hop moved it {moved}, where the "
                f"mismatch is {e['mismatch_after_db2']:.4g} dB^2 against "
                f"{e['mismatch_before_db2']:.4g}; the start gradient did not see it, "
                "so no accuracy is claimed for it")
    for t, o in objects_seen.items():
        if not o["clear_path"]:
            share = np.asarray(o["power_share_per_snapshot"])
            seen["could_not_see"].append(
                f"{t}: no clear path to the robot: the paths that touch it carry at most "
                f"{100 * share.max(initial=0.0):.2g} % of a snapshot's path power at the "
                f"fit, {100 * o['power_share_max_at_start']:.2g} % at the start (clear: "
                f">= {100 * CLEAR_PATH_SHARE:g} %; {sum(o['paths_per_snapshot'])} paths over "
                f"{len(share)} snapshots); its pose is fitted, with no accuracy claimed")
    seconds = time.perf_counter() - t_start
    out.mkdir(parents=True, exist_ok=True)
    scene_out = write_calibrated_scene(scene, result, out / "scene")
    materials, assign = calibrated_materials(scene, result)
    report = {"scene": str(Path(scene_dir)), "recording": str(Path(recording)),
              "links": [list(lk) for lk, _ in measured],
              "snapshots": [int(len(m.rx_positions)) for _, m in measured],
              # per link: the noise estimated per snapshot (None: none added to the model)
              "noise_snr_db": [None if m.noise_power is None else m.noise_snr_db().tolist()
                               for _, m in measured],
              "subcarriers": int(len(measured[0][1].subcarrier_offsets_hz)),
              "permittivity_scans": scans, "pose_scans": pose_scans,
              "fits_from_starts": [{"start": [float(v) for v in x], "final": r.final.tolist(),
                                    "mismatch_db2": r.mismatch_final, "converged": r.converged,
                                    "history_db2": [float(h) for h in r.history]}
                                   for x, r in zip(starts, fits)],
              "materials_written": materials,
              "material_of_objects": assign,
              **result.to_json(),
              "evaluations": cal.evaluations, "seconds": seconds, "stages": stages,
              "candidate_buffer": {"size": cal.buffer_size, "regrows": cal.buffer_regrows},
              "observability": seen["materials"],
              "objects": objects_seen, "polish": polished, "hop": hopped,
              "could_not_see": seen["could_not_see"]}
    report_path = out / "calibration.json"
    report_path.write_text(json.dumps(report, indent=2))
    plot_report(report, out / "calibration.png")
    return RunOutput(scene_out, report_path, report)
