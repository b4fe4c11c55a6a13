"""Closing the loop (issue 20, item 4): calibrate the twin from a lap recorded in its
perturbed "real" room and compare with the truth.

:func:`closing_the_loop` builds the real room as the case study does
(:func:`isac_twin.experiments.deployment.perturb_scene`: every furniture object shifted
by N(0, 3 cm) in x and y and turned by N(0, 2 deg)) and changes one material: the
objects of ``changed_material`` (e.g. ``"wood-0.03"``, the tables) get a custom radio
material whose relative permittivity is ``permittivity_factor`` times the twin's. It
records the robot's CSI over one lap of its path there (``record_twin``, optionally
with noise at an SNR), calibrates the twin's folder from that recording
(:func:`isac_twin.calibration.calibrate_recording`: the changed material and the moved
objects' x/y/yaw), and reports each recovered offset against the truth, the fitted
permittivity against the real one, and the time.
"""

from __future__ import annotations

import gc
import logging
import math
import time
from pathlib import Path

import numpy as np

from ..calibration import (
    SolverSettings,
    calibrate_recording,
    material_users,
    recording_calibrator,
    write_calibrated_scene,
)
from ..scene.twin_scene import load_scene
from ..transport.record import CsiRecording, record_twin
from .casestudy import CASE_STUDY_MCA
from .deployment import perturb_scene

log = logging.getLogger(__name__)


#: What :func:`closing_the_loop` calibrates (and :func:`mismatch_at_truth` evaluates).
CALIBRATED = ("materials", "poses")


def real_room(folder, *, seed: int = 1, changed_material: str = "wood-0.03",
              permittivity_factor: float = 1.3):
    """The perturbed "real" room of the twin at ``folder``: ``(scene, truth)`` with
    ``truth = {"moved": {object: [dx m, dy m, dyaw deg]}, "material": {"name",
    "relative_permittivity", "twin_permittivity", "objects"}}``."""
    from sionna.rt.radio_materials.itu import itu_material

    scene = load_scene(folder)
    users = material_users(scene, changed_material)
    if not users:
        raise ValueError(f"real_room: no object of material {changed_material!r}")
    # the case study's perturbation, with its material change made a no-op: the change
    # of this case is a permittivity (a table turned metal has none to recover)
    pert = perturb_scene(scene, seed=seed, material=(users[0].name, users[0].material))
    itu = users[0].material
    eps, sigma = (float(np.asarray(v).reshape(-1)[0])
                  for v in itu_material(itu, scene.config.scene.frequency_hz))
    name = f"{itu}-real"
    scene.define_material(name, {"relative_permittivity": eps * permittivity_factor,
                                 "conductivity": sigma, "thickness": users[0].thickness})
    for o in users:
        scene.set_material(o.name, name)
    truth = {"moved": pert["moved"],
             "material": {"name": changed_material, "relative_permittivity":
                          eps * permittivity_factor, "twin_permittivity": eps,
                          "objects": [o.name for o in users]}}
    return scene, truth


def lap_steps(config, dt: float, robot: str | None = None, laps: float = 1.0) -> int:
    """Twin steps of ``laps`` laps of the robot's closed path at the model's speed limit."""
    from ..contract import schema

    dev = next(d for d in config.devices if d.kind == "robot" and (robot in (None, d.name)))
    path = dev.path or {}
    body = schema.ROBOT_MODELS[dev.model]
    speed = float(path.get("speed") or 0.0) or body.max_linear
    if path.get("kind") == "circle":
        length = 2 * math.pi * float(path["radius"])
    elif path.get("kind") == "polyline":
        pts = np.asarray(path["waypoints"], float)
        length = float(np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1).sum())
    else:
        raise ValueError(f"lap_steps: robot {dev.name!r} has no circle or polyline path")
    return max(2, int(math.ceil(laps * length / speed / dt)))


def closing_the_loop(folder, out, *, seed: int = 1, changed_material: str = "wood-0.03",
                     permittivity_factor: float = 1.3, objects: list[str] | None = None,
                     dt: float = 1.0, laps: float = 1.0, snr_db: float | None = None,
                     snapshots: int = 8, subcarriers: int = 16, max_steps: int = 40,
                     solver: SolverSettings | None = None, multistart: int = 1,
                     pose_scan: bool = False, noise: bool = True) -> dict:
    """Record one lap in the perturbed room, calibrate the twin at ``folder``, compare.

    Args:
        folder: the twin's scene folder (e.g. the bundled lab).
        out: working folder (``real.mcap``, ``calibration/``).
        objects: the objects whose poses are fitted (default the room's furniture).
        dt: twin step of the recording, s (only the snapshots used matter).
        snr_db: noise of the recorded CSI (None: the twin's exact channel).
        snapshots, subcarriers, max_steps, solver, multistart, pose_scan, noise: of the
            calibration (:func:`isac_twin.calibration.calibrate_recording`).

    Returns:
        A JSON-serialisable dict: ``objects`` (per object: truth and fitted dx, dy cm,
        dyaw deg, errors, observed), ``material`` (truth, fitted, error %), seconds of
        recording and calibration, the calibration's convergence.
    """
    from ..twin.twin import Twin

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scene, truth = real_room(folder, seed=seed, changed_material=changed_material,
                             permittivity_factor=permittivity_factor)
    objects = list(objects if objects is not None else scene.config.room.furniture)
    twin = Twin(scene, seed=seed, dt=dt, sensing=False, localize=False)
    steps = lap_steps(scene.config, dt, laps=laps)
    t0 = time.perf_counter()
    mcap = out / "real.mcap"
    record_twin(twin, steps, mcap, csi=CsiRecording(snr_db=snr_db, seed=seed))
    t_rec = time.perf_counter() - t0
    # the calibration runs as `isac-twin calibrate` does, in a process with one scene:
    # the real room kept alive made each traced evaluation 20 % slower (lab: 0.53
    # against 0.445 s, a frozen gradient step 0.77 against 0.54 s; a second scene
    # merely loaded does the same, likely because Dr.Jit dispatches calls on radio
    # materials over every registered instance, those of both scenes)
    del twin, scene
    gc.collect()
    t0 = time.perf_counter()
    run = calibrate_recording(folder, mcap, out / "calibration", what=CALIBRATED,
                              objects=objects, materials=[changed_material],
                              max_snapshots=snapshots, max_subcarriers=subcarriers,
                              max_steps=max_steps, solver=solver, multistart=multistart,
                              pose_scan=pose_scan, noise=noise)
    t_cal = time.perf_counter() - t0
    rep = run.report
    gc.collect()
    at_truth, true_folder = mismatch_at_truth(
        folder, mcap, truth, objects=objects, changed_material=changed_material,
        snapshots=snapshots, subcarriers=subcarriers, solver=solver, noise=noise,
        out=out / "true_room")
    got = {p["name"]: p["final"] for p in rep["parameters"]}
    unseen = set(rep["unobserved"])
    rows = {}
    for name in objects:
        dx, dy, dyaw = truth["moved"].get(name, [0.0, 0.0, 0.0])
        fx, fy, fyaw = (got[f"{name}.x"], got[f"{name}.y"], math.degrees(got[f"{name}.yaw"]))
        rows[name] = {"truth_cm_deg": [dx * 100, dy * 100, dyaw],
                      "fitted_cm_deg": [fx * 100, fy * 100, fyaw],
                      "error_cm_deg": [abs(fx - dx) * 100, abs(fy - dy) * 100, abs(fyaw - dyaw)],
                      "unobserved": sorted(k for k in ("x", "y", "yaw")
                                           if f"{name}.{k}" in unseen),
                      "clear_path": rep["objects"].get(name, {}).get("clear_path")}
    m = truth["material"]
    eps_fit = got[f"{changed_material}.permittivity"]
    return {"steps": steps, "dt": dt, "snr_db": snr_db, "seed": seed, "objects": rows,
            "material": {**m, "fitted": eps_fit, "error_percent":
                         100 * abs(eps_fit - m["relative_permittivity"])
                         / m["relative_permittivity"]},
            "mismatch_db2": {**rep["mismatch_db2"], "at_truth": at_truth},
            "converged": rep["converged"],
            "message": rep["message"], "evaluations": rep["evaluations"],
            "seconds_per_step": rep["seconds_per_step"], "record_s": t_rec,
            "observability": rep["observability"], "could_not_see": rep["could_not_see"],
            "polish": rep["polish"], "hop": rep["hop"], "stages": rep["stages"],
            "candidate_buffer": rep["candidate_buffer"], "links": rep["links"],
            "noise_snr_db": rep["noise_snr_db"],
            "calibration_s": t_cal, "calibrated_scene": str(run.scene_dir),
            "true_room_scene": str(true_folder),
            "recording": str(mcap),
            "report": str(run.report_path)}


def mismatch_at_truth(folder, recording, truth: dict, *, objects: list[str],
                      changed_material: str, snapshots: int, subcarriers: int,
                      solver: SolverSettings | None = None, noise: bool = True,
                      out=None) -> tuple[float, Path | None]:
    """The calibration's mismatch (dB^2) at the real room's values: the objects' true
    offsets and the changed material's true permittivity (``truth`` of
    :func:`real_room`), the rest at the twin's values, on the same measurements and
    model as :func:`closing_the_loop`'s calibration. A fit that ends below it has
    fitted the recording's noise as well as the truth does: its errors are the
    measurements' limit, not the search's. With ``out``, the twin calibrated to those
    values is written there (:func:`~isac_twin.calibration.write_calibrated_scene`):
    the best any calibration can do, the reference of :func:`localization_errors`.

    Returns:
        ``(mismatch dB^2, the folder written or None)``.
    """
    scene = load_scene(folder)
    _, params, cal = recording_calibrator(
        scene, recording, what=CALIBRATED, objects=objects, materials=[changed_material],
        max_snapshots=snapshots, max_subcarriers=subcarriers, noise=noise, solver=solver)
    x = cal.initial.copy()
    for i, p in enumerate(params):
        if p.kind == "permittivity" and p.target == changed_material:
            x[i] = truth["material"]["relative_permittivity"]
        elif p.kind in ("x", "y", "yaw"):
            dx, dy, dyaw = truth["moved"].get(p.target, [0.0, 0.0, 0.0])
            x[i] = {"x": dx, "y": dy, "yaw": math.radians(dyaw)}[p.kind]
    cal.evaluate(x, grad=False)  # the scene at the truth, then the true room's chains
    res = cal.result(x, converged=True, message="the real room's values")
    if out is None:
        return float(res.mismatch_final), None
    return float(res.mismatch_final), write_calibrated_scene(scene, res, Path(out))


def localization_errors(folder, calibrated_folder, *, true_folder=None, seed: int = 1,
                        run_seed: int | None = None,
                        changed_material: str = "wood-0.03", permittivity_factor: float = 1.3,
                        spacing: float = 0.05, dt: float = 0.25, steps: int | None = None,
                        snr_db: float = 20.0, method: str = "MCA-angles", fusion: str = "ekf",
                        closed_loop: bool = True, cache_dir: str | Path = "out/cache") -> dict:
    """Localization errors against the truth in the real room (:func:`real_room`), in the
    realistic mode the twin runs by default (the case study's closed loop: MCA-angles on
    pilots received there at ``snr_db``, the controller steering on an EKF over odometry
    with the gated fixes, on the twin's ``spacing`` fingerprint database; the README's
    closed-loop figures), once with the original twin's database and once with the
    calibrated twin's, and with ``true_folder`` (:func:`mismatch_at_truth`'s) once with
    the twin at the real room's values: what no calibration can beat, and where the
    errors are not the twin's at all. Returns ``{"original": summary, "calibrated":
    summary[, "true room": summary]}``; ``seed`` makes the real room, ``run_seed``
    (default ``seed``) the run's noise (pilots, odometry, start calibration)
    (:func:`isac_twin.experiments.deployment.summarize` of the per-step
    ``estimate_vs_truth`` errors, m) plus the database build times and the settings."""
    from ..localization.fingerprints import cached_database
    from .deployment import Deployment, DeploymentSettings, errors, summarize

    mca = dict(CASE_STUDY_MCA)
    out: dict = {"settings": {"method": method, "fusion": fusion, "closed_loop": closed_loop,
                              "mode": "pilots", "snr_db": snr_db, "spacing_m": spacing,
                              "dt_s": dt, "seed": seed, "run_seed": run_seed}}
    twins = [("original", folder), ("calibrated", calibrated_folder)]
    for label, f in twins + ([("true room", true_folder)] if true_folder else []):
        t0 = time.perf_counter()
        db = cached_database(load_scene(f), spacing=spacing, cache_dir=cache_dir)
        t_db = time.perf_counter() - t0
        real, _ = real_room(folder, seed=seed, changed_material=changed_material,
                            permittivity_factor=permittivity_factor)
        settings = DeploymentSettings(source="real", mode="pilots", snr_db=snr_db,
                                      closed_loop=closed_loop, method=method, fusion=fusion,
                                      mca=mca, num_paths=mca["num_paths"])
        t0 = time.perf_counter()
        dep = Deployment(f, db, settings, seed=seed if run_seed is None else run_seed,
                         dt=dt, rate_every=10 ** 9,
                         real_scene=real)
        n = steps if steps is not None else dep.lap_steps()
        dep.run(n)
        err = errors(dep.records)["estimate_vs_truth"]
        out[label] = {**summarize(err), "steps": n, "database_s": t_db,
                      "run_s": time.perf_counter() - t0}
    return out


def per_fix_errors(twins: dict, real_scene, recording, *, methods=("MCA", "MCA-angles"),
                   modes=("pilots", "tracer"), spacing: float = 0.05, dt: float = 0.5,
                   snr_db: float = 20.0,
                   seed: int = 1, robot: str | None = None,
                   cache_dir: str | Path = "out/cache") -> dict:
    """Per-fix localization errors against the truth, before any fusion, of the same
    observations matched against each twin's fingerprint database.

    The robot is replayed along the lap of ``recording`` (its ``/<robot>/ground_truth``,
    :class:`~isac_twin.transport.record.TrajectoryReplay`) in ``real_scene`` every ``dt`` s; at each
    step one observation per mode of ``modes`` is formed there: ``"pilots"`` from the
    pilots received at ``snr_db`` (the realistic mode:
    :func:`~isac_twin.localization.measurements.observe_pilots` with the delay-only MDP at
    every AP and the delay-direction estimates at multi-antenna APs), ``"tracer"``
    straight from the real room's traced paths (the paper's MDP, noise-free:
    :func:`~isac_twin.localization.measurements.observe_tracer`); every method of
    ``methods`` (``"MCA"``: the paper's fingerprinting on multipath delay profiles;
    ``"MCA-angles"``: the twin's default localizer) localizes each on every twin's
    database (the case study's MCA options). No odometry, no EKF: what the database
    alone gives.

    Args:
        twins: ``label -> TwinScene`` (e.g. original, calibrated, the real room itself).
        real_scene: the room the pilots are received in (not one of ``twins``' objects:
            its twin runs the replay).
        recording: an ``.mcap`` with the robot's ground truth.
        spacing: database grid, m (cached in ``cache_dir`` by scene content).

    Returns:
        ``{"settings": {...}, "steps": n, label: {"method/mode": summary}, "database_s":
        {label: s}, "errors_m": {label: {"method/mode": [n]}}}``
        (:func:`~isac_twin.experiments.deployment.summarize`: RMSE, median, P90, max, m).
    """
    from ..localization.baselines import make_localizer
    from ..localization.fingerprints import cached_database
    from ..localization.measurements import (
        FeatureSpec,
        PilotSettings,
        observe_pilots,
        observe_tracer,
    )
    from ..phy.network import NetworkPHY
    from ..robots import SensorOptions
    from ..transport.record import TrajectoryReplay
    from ..twin.twin import Twin
    from ..utils.geometry import antenna_pose, planar_pose
    from .deployment import summarize

    if not modes or set(modes) - {"pilots", "tracer"}:
        raise ValueError(f"per_fix_errors: modes must be 'pilots' and/or 'tracer', got {modes!r}")
    cfg = real_scene.config
    spec = FeatureSpec.from_config(cfg)
    robot = robot or next(d.name for d in cfg.devices if d.kind == "robot")
    dev = cfg.device(robot)
    locs, t_db, ap_names = {}, {}, None
    for label, sc in twins.items():
        t0 = time.perf_counter()
        db = cached_database(sc, spacing=spacing, cache_dir=cache_dir)
        t_db[label] = time.perf_counter() - t0
        if ap_names is not None and db.ap_names != ap_names:
            raise ValueError(f"per_fix_errors: twin {label!r} has APs {db.ap_names}, "
                             f"the others {ap_names}")
        ap_names = db.ap_names
        for m in methods:
            locs[(label, m)] = make_localizer(m, db, spec, num_paths=CASE_STUDY_MCA["num_paths"],
                                              mca=CASE_STUDY_MCA)
    phy = NetworkPHY(cfg)
    pilots = PilotSettings(snr_db=snr_db, seed=seed)
    rng = np.random.default_rng([seed, 7])
    truth, est = [], {}

    def localize(twin, result):
        pose = result.robots[robot].pose
        links = [result.links[(ap, robot)].paths for ap in ap_names]
        obs = {}
        if "pilots" in modes:
            obs["pilots"] = observe_pilots(links, [phy.channel(lp) for lp in links], spec,
                                           pilots, CASE_STUDY_MCA["num_paths"], rng=rng,
                                           features=("mdp", "dirs"))
        if "tracer" in modes:
            obs["tracer"] = observe_tracer(links, spec, CASE_STUDY_MCA["num_paths"])
        truth.append(np.asarray(antenna_pose(planar_pose(pose[0], pose[1], pose[5]),
                                             dev.antenna_offset).position)[:2])
        for (label, m), loc in locs.items():
            for mode, o in obs.items():
                est.setdefault((label, f"{m}/{mode}"), []).append(
                    np.asarray(loc(o), float)[:2])

    reality = Twin(real_scene, seed=seed, dt=dt, phy=False, sensing=False, localize=False,
                   sensors=SensorOptions(lidar=False, imu=False), estimators=[localize])
    replay = TrajectoryReplay(reality, recording)
    span = float(replay.trajectories[robot].t[-1] - replay.trajectories[robot].t[0])
    n = max(1, int(span / dt))
    for _ in reality.run(n):
        pass
    truth = np.array(truth)
    out: dict = {"settings": {"methods": list(methods), "modes": list(modes), "snr_db": snr_db,
                              "fusion": None, "spacing_m": spacing, "dt_s": dt, "seed": seed,
                              "recording": str(recording)},
                 "steps": n, "database_s": t_db, "errors_m": {}}
    for (label, m), e in est.items():
        err = np.linalg.norm(np.array(e) - truth, axis=1)
        out.setdefault(label, {})[m] = summarize(err)
        out["errors_m"].setdefault(label, {})[m] = err.tolist()
    return out
