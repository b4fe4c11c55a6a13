"""What the measurements say about each fitted parameter, at the fit.

:func:`observability`: per fitted material, the traced paths that touch it and the
mismatch's curvature in its permittivity (a 1-sigma uncertainty); :func:`object_paths`:
per object with a fitted pose, the paths that touch it and whether it has a clear path
to the robot (:data:`CLEAR_PATH_SHARE`), which decides the accuracy claimed for it.
"""

from __future__ import annotations

import math

import numpy as np

from .calibrator import Calibrator

#: A fitted permittivity is reported as not determined to this fraction when changing it
#: by this much changes the mismatch by less than the fit's own residual mismatch.
SENSITIVITY_STEP = 0.10


def observability(cal: Calibrator, result) -> dict:
    """What the measurements say about each fitted material, at the fit (``result``).

    Per material named by a parameter: how many traced paths touch it and their share of each
    snapshot's path power (:meth:`~isac_twin.calibration.Calibrator.visibility`), and the
    mismatch when its permittivity is changed by -+:data:`SENSITIVITY_STEP` (two traces, no
    gradients), and from that curvature its 1-sigma ``uncertainty_percent`` ``= 100 step
    sqrt(residual / (N K mean change))``: the fit's residual mismatch taken as independent
    noise per snapshot and subcarrier (the antennas of one snapshot and subcarrier as one
    sample: their residuals are correlated). ``could_not_see``: a sentence per parameter the
    start gradient did not see (:attr:`CalibrationResult.unobserved`) and per permittivity
    whose 1-sigma exceeds the step (not determined to 10 %).

    Returns:
        ``{"materials": {target: {...}}, "could_not_see": [str]}``.
    """
    final = np.asarray(result.final, float)
    vis = cal.visibility(final)
    out, notes = {}, [f"{n}: no traced path changes with it at the start (gradient "
                      f"{abs(g):.3g})" for n, g in zip(result.names, result.gradient_initial)
                      if n in result.unobserved]
    for i, p in enumerate(cal.params):
        if p.kind != "permittivity":
            continue
        v = vis[p.target]
        changes = []
        for sgn in (-1.0, 1.0):
            x = final.copy()
            x[i] = float(np.clip(x[i] * (1 + sgn * SENSITIVITY_STEP), *p.limits))
            changes.append(cal.evaluate(x, grad=False)[0] - result.mismatch_final)
        cal.evaluate(final, grad=False)  # leave the scene at the fit
        share = np.asarray(v["power_share"], float)
        out[p.target] = {"paths_per_snapshot": [int(c) for c in v["paths"]],
                         "power_share_per_snapshot": [float(c) for c in share],
                         "strongest_path_db_per_snapshot": [float(c) for c in v["strongest_db"]],
                         "mismatch_change_db2_at_minus_plus_10_percent": changes,
                         "mismatch_final_db2": float(result.mismatch_final)}
        curv = float(np.mean(changes))
        n_k = sum(m.csi.shape[0] * m.csi.shape[1] for m in cal.links)
        sigma = (100.0 * SENSITIVITY_STEP * math.sqrt(result.mismatch_final / (n_k * curv))
                 if curv > 0 else math.inf)
        out[p.target]["uncertainty_percent"] = sigma
        if not sigma <= 100.0 * SENSITIVITY_STEP:
            notes.append(
                f"{p.name}: not determined to {SENSITIVITY_STEP:.0%} by these measurements: "
                f"-+{SENSITIVITY_STEP:.0%} changes the mismatch by {changes[0]:+.3g} / "
                f"{changes[1]:+.3g} dB^2 against a residual mismatch of "
                f"{result.mismatch_final:.3g} dB^2 (1-sigma {sigma:.3g} %); its paths carry "
                f"at most {100 * share.max():.2g} % of a snapshot's path power "
                f"({int(np.sum(v['paths']))} paths over {len(share)} snapshots)")
    return {"materials": out, "could_not_see": notes}


#: An object has a *clear path* to the robot when the traced paths that touch it (a
#: reflection or refraction on it) carry at least this share of some snapshot's path
#: power at the fit or at the scene's values (a pose the fit got wrong can lose the
#: paths: lab, both links, 32 subcarriers: SwitchBox_2 1.4 % at the start, 0.92 % at a
#: fit 1.8 deg off in yaw, left out of the polish; at its true pose the mismatch fell
#: from 0.486 to 0.300 dB^2): only then does the issue's target (1 cm, 0.5 deg)
#: apply (every object with a path to the robot is polished and hopped). Lab: racks
#: 3.8 / 7.8 %, a switch box 1.4 %, the chairs and tables out of the robot's sight
#: 0-0.4 %.
CLEAR_PATH_SHARE = 0.01


def object_paths(cal: Calibrator, values, start: dict | None = None) -> dict[str, dict]:
    """Per object with a fitted pose: the paths that touch it at ``values`` (physical
    units, ``[P]``; :meth:`~isac_twin.calibration.Calibrator.visibility`) and whether it
    has a clear path to the robot (:data:`CLEAR_PATH_SHARE`) there or, with ``start`` (this
    function's result at the scene's values), at the start; then also
    ``power_share_max_at_start``."""
    vis = cal.visibility(values)
    out = {}
    for t in dict.fromkeys(p.target for p in cal.params if p.kind in ("x", "y", "yaw")):
        v = vis[t]
        share = np.asarray(v["power_share"], float)
        out[t] = {"paths_per_snapshot": [int(c) for c in v["paths"]],
                  "power_share_per_snapshot": [float(c) for c in share],
                  "strongest_path_db_per_snapshot": [float(c) for c in v["strongest_db"]],
                  "clear_path": bool(share.max(initial=0.0) >= CLEAR_PATH_SHARE)}
        if start is not None:
            s0 = start[t]
            out[t]["power_share_max_at_start"] = max(s0["power_share_per_snapshot"],
                                                     default=0.0)
            out[t]["clear_path"] = out[t]["clear_path"] or s0["clear_path"]
    return out
