"""The paper's section IV case study: fingerprint database, localization, deployment loop.

:func:`run_case_study` does everything ``python -m isac_twin.experiments.demo`` shows after
the export: the cached fingerprint database of the twin's room, the
deployment loop in the paper's mode (MDP from the twin's tracer at the
twin's robot position, odometry as ground truth) and a closed-loop run in
the realistic mode (MDP from pilots received in a perturbed "real" room),
a static comparison table of MCA and two baselines, figures, and
``metrics.json``. Definitions: ``docs/casestudy.md``.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..localization.baselines import make_localizers
from ..localization.fingerprints import FingerprintDB, cached_database
from ..localization.measurements import FeatureSpec, PilotSettings, observe_pilots, observe_tracer
from ..phy.network import NetworkPHY
from ..raytrace import DevicePose, device_poses, make_tracer
from ..robots.control import path_from_spec
from ..scene.config import parse_path_spec
from ..scene.room import check_placement, draw_plan
from ..scene.twin_scene import load_scene
from .deployment import Deployment, DeploymentSettings, errors, perturb_scene, summarize

log = logging.getLogger(__name__)

#: The case study's MCA options (:func:`run_case_study`'s default ``mca``).
CASE_STUDY_MCA = {"eps": 0.5, "k": 4, "num_paths": 9}

#: The paper's reported numbers (section IV-B), m.
PAPER_MAX_POSITIONING_M = 0.16
PAPER_MAX_MODELLING_M = 0.08

#: Keys of ``metrics.json`` (each error entry holds rmse, median, p90, max in m).
#: ``headline`` comes first: errors against the simulator's truth; ``paper_mode`` is
#: the paper's comparison (estimate and twin against odometry: self-consistency).
METRICS_KEYS = ("headline", "paper_mode", "closed_loop", "table", "database",
                "paper_reference", "timings_s", "rates")

#: Rate samples (PHY evaluations) per closed-loop run at least, when the run is long
#: enough: the closed loop's rates figure needs a curve, not one point.
CLOSED_LOOP_RATE_SAMPLES = 24


def rate_cadence(steps: int, rate_every: int, samples: int = CLOSED_LOOP_RATE_SAMPLES) -> int:
    """PHY cadence (every this many steps) of a run of ``steps`` steps: ``rate_every``,
    coarsened so that about ``samples`` steps get rates (at least 2 if ``steps`` >= 2).

    The PHY costs most of a step, so the closed-loop run evaluates it sparsely; a
    fixed huge cadence left a single sample (step 0) and an empty rates figure."""
    if steps < 1 or rate_every < 1 or samples < 2:
        raise ValueError(f"rate_cadence: expected steps, rate_every >= 1 and samples >= 2, "
                         f"got {steps}, {rate_every}, {samples}")
    every = max(int(rate_every), math.ceil(steps / samples))
    return min(every, max(1, steps - 1))  # steps 0 and ``every`` both inside the run


def disjoint_config(config):
    """``config`` with the APs on disjoint OFDM symbols: the K symbols split into
    consecutive equal blocks in AP order (2 APs, K = 14: [0, 7) and [7, 14))."""
    import dataclasses

    aps = [d for d in config.devices if d.kind == "access_point"]
    k = config.ofdm.num_symbols
    edges = np.linspace(0, k, len(aps) + 1).round().astype(int)
    blocks = {d.name: (int(edges[i]), int(edges[i + 1])) for i, d in enumerate(aps)}
    devs = tuple(dataclasses.replace(d, symbols=blocks[d.name]) if d.name in blocks else d
                 for d in config.devices)
    return dataclasses.replace(config, devices=devs)


def shared_config(config):
    """``config`` with every AP on every resource element (they interfere)."""
    import dataclasses

    o = config.ofdm
    devs = tuple(dataclasses.replace(d, symbols=(0, o.num_symbols),
                                     subcarriers=(0, o.num_subcarriers))
                 if d.kind == "access_point" else d for d in config.devices)
    return dataclasses.replace(config, devices=devs)


def allocation(config) -> str:
    """``"shared REs"`` if any two APs' resource sets overlap, else ``"disjoint"``."""
    aps = [d for d in config.devices if d.kind == "access_point"]
    for i, a in enumerate(aps):
        for b in aps[i + 1:]:
            if (max(a.symbols[0], b.symbols[0]) < min(a.symbols[1], b.symbols[1])
                    and max(a.subcarriers[0], b.subcarriers[0])
                    < min(a.subcarriers[1], b.subcarriers[1])):
                return "shared REs"
    return "disjoint"


def circle_points(centre, radius: float, n: int, height: float) -> tuple[np.ndarray, np.ndarray]:
    """``n`` antenna positions ``[n, 3]`` m on a circle and tangent yaws ``[n]`` rad (ccw)."""
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False) + np.pi / (2 * n)
    pts = np.stack([centre[0] + radius * np.cos(ang), centre[1] + radius * np.sin(ang),
                    np.full(n, height)], axis=1)
    return pts, ang + np.pi / 2


def path_points(path: dict, n: int, height: float,
                start=None) -> tuple[np.ndarray, np.ndarray]:
    """``n`` antenna positions ``[n, 3]`` m evenly spaced in arc length along a path spec
    (any ``[devices.path]`` kind; ``start`` ``[2]`` m is the robot's position, needed for
    ``"goal"``) and the path's heading there ``[n]`` rad. A closed path is sampled
    a quarter step past its start point (on a circle: the points of
    :func:`circle_points`, the lab's table), an open one from end to end."""
    p = path_from_spec(path, start=start)
    if p.closed:
        s = (np.arange(n) + 0.25) * p.length / n
    else:
        s = np.linspace(0.0, p.length, n)
    xy = p.point(s)
    t = p.tangent(s)
    pts = np.column_stack([xy, np.full(n, height)])
    return pts, np.arctan2(t[:, 1], t[:, 0])


def robot_path(config, path: dict | None = None, robot: str | None = None) -> tuple[str, dict]:
    """The robot the case study drives and its path: ``path`` if given, else the
    robot's ``[devices.path]`` from twin.toml.

    Raises:
        ConfigError: no robot, or no path anywhere (naming the file and robot).
    """
    robots = [d for d in config.devices if d.kind == "robot"]
    if robot is not None:
        robots = [d for d in robots if d.name == robot]
    if not robots:
        raise ConfigError(f"{config.path}: devices: the case study needs a robot"
                          + (f" named {robot!r}" if robot else ""))
    dev = robots[0]
    if path is None:
        if dev.path is None:
            raise ConfigError(f"{config.path}: devices ({dev.name}).path: the case study needs "
                              "the robot's path (circle, polyline, figure_eight or goal): add "
                              "[devices.path] or pass one")
        path = dev.path
    return dev.name, dict(path)


# --------------------------------------------------------------------------- static table


def static_table(folder, db: FingerprintDB, *, n_points: int = 12,
                 snrs=(0.0, 10.0, 20.0, 30.0), seed: int = 0, path: dict | None = None,
                 mca: dict | None = None) -> list[dict]:
    """Localization errors of MCA, kNN-CSI and PDP at test points along the robot's path.

    For the twin's own room and for the perturbed "real" room (the same
    perturbation as :class:`Deployment` with this seed), each method gets the
    tracer-mode observation and pilot-mode observations at each SNR.

    Args:
        path: the path spec (default: the robot's ``[devices.path]``); ``n_points``
            points evenly spaced along it, robot heading along the path.

    Returns:
        Rows ``{"method", "mode", "room", "median", "p90", "max", "errors"}`` (m).
    """
    twin_scene = load_scene(folder)
    real_scene = load_scene(folder)
    perturb_scene(real_scene, seed=seed + 1)
    cfg = twin_scene.config
    spec = FeatureSpec.from_config(cfg)
    locs = make_localizers(db, spec, mca=mca)
    robot, path = robot_path(cfg, path)
    pts, yaws = path_points(path, n_points, db.height, start=cfg.device(robot).position[:2])
    phy = NetworkPHY(cfg)
    rows = []
    for room, scene in (("twin", twin_scene), ("perturbed", real_scene)):
        tracer = make_tracer(scene.config)
        per_point = []
        for p, yaw in zip(pts, yaws):
            poses = dict(device_poses(scene.config))
            poses[robot] = DevicePose(tuple(p), (0.0, 0.0, float(yaw)))
            links = tracer(scene, poses)
            lk = [links[(ap, robot)] for ap in db.ap_names]
            per_point.append((lk, [phy.channel(x) for x in lk]))
        modes = [("tracer", None)] + [(f"pilots {s:g} dB", s) for s in snrs]
        for mode, snr in modes:
            errs = {m: [] for m in locs}
            rng = np.random.default_rng([seed, int(snr or 0) + 100])
            for (lk, ch), p in zip(per_point, pts):
                obs = observe_tracer(lk, spec) if snr is None else observe_pilots(
                    lk, ch, spec, PilotSettings(snr_db=snr, seed=seed), rng=rng)
                for m, loc in locs.items():
                    errs[m].append(float(np.linalg.norm(np.asarray(loc(obs))[:2] - p[:2])))
            for m, e in errs.items():
                s = summarize(e)
                rows.append({"method": m, "mode": mode, "room": room, "median": s["median"],
                             "p90": s["p90"], "max": s["max"], "errors": e})
            log.info("table: %s room, %s done", room, mode)
    return rows


def table_markdown(rows: list[dict]) -> str:
    """Rows of :func:`static_table` as a markdown table (cm: median / P90 / max)."""
    rooms = list(dict.fromkeys(r["room"] for r in rows))
    keys = list(dict.fromkeys((r["method"], r["mode"]) for r in rows))
    cell = {(r["method"], r["mode"], r["room"]): r for r in rows}
    head = "| method | measured MDP / CSI | " + " | ".join(
        f"{room} room: median / P90 / max (cm)" for room in rooms) + " |"
    lines = [head, "|" + "---|" * (2 + len(rooms))]
    for m, mode in keys:
        vals = []
        for room in rooms:
            r = cell.get((m, mode, room))
            vals.append("-" if r is None else
                        f"{100 * r['median']:.1f} / {100 * r['p90']:.1f} / {100 * r['max']:.1f}")
        lines.append(f"| {m} | {mode} | " + " | ".join(vals) + " |")
    return "\n".join(lines)


# --------------------------------------------------------------------------- figures


def plot_run(dep: Deployment, out: Path, tag: str, title: str) -> list[Path]:
    """Trajectories, errors over time and rates of a deployment run -> PNGs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recs = dep.records
    g = {k: np.array([getattr(r, k) for r in recs]) for k in
         ("truth", "odometry", "twin", "estimate")}
    t = np.array([r.time_s for r in recs])
    err = errors(recs)
    files = []

    scene = dep.twin.scene
    lo, hi = scene.bounds_min, scene.bounds_max
    fig, ax = plt.subplots(figsize=(7, 1.0 + 6.0 * min(1.5, max(0.4, (hi[1] - lo[1])
                                                                / max(hi[0] - lo[0], 1e-9)))))
    draw_plan(ax, scene)  # floor, walls, furniture and APs from the scene's own geometry
    plan = dep.path.sample(400)
    ax.plot(plan[:, 0], plan[:, 1], color="0.6", lw=0.8, ls=(0, (4, 3)), zorder=3,
            label=f"path ({dep.path.describe()})")
    est_label = (closed_loop_label(dep.settings) + ", fused" if dep.settings.closed_loop
                 and dep.settings.fusion == "ekf" else dep.settings.method)
    style = {"estimate": ("C3", ".", f"estimate ({est_label})", 0.5),
             "twin": ("C2", "-", "twin", 1.6),
             "odometry": ("C0", "-", "odometry (paper's ground truth)", 1.6),
             "truth": ("k", "--", "truth (simulator)", 1.2)}
    for k, (c, ls, lab, lw) in style.items():
        if ls == ".":
            ax.plot(g[k][:, 0], g[k][:, 1], ".", color=c, ms=4, label=lab, zorder=4)
        else:
            ax.plot(g[k][:, 0], g[k][:, 1], ls, color=c, lw=lw, label=lab, zorder=4)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"Robot trajectories: {title}")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    files.append(out / f"trajectories_{tag}.png")
    fig.savefig(files[-1], dpi=120)
    plt.close(fig)

    # against the simulator's truth first (solid); the paper's comparison against
    # odometry (self-consistency) dashed
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.plot(t, 100 * err["estimate_vs_truth"], color="C3", lw=1.6,
            label="estimate vs truth")
    ax.plot(t, 100 * err["odometry_vs_truth"], color="C0", lw=1.2,
            label="odometry vs truth (drift)")
    ax.plot(t, 100 * err["positioning"], color="C3", ls=(0, (3, 2)), lw=1,
            label="paper's positioning: estimate vs odometry (self-consistency)")
    ax.plot(t, 100 * err["modelling"], color="C2", ls=(0, (3, 2)), lw=1,
            label="paper's modelling: twin vs odometry (self-consistency)")
    ax.axhline(100 * PAPER_MAX_POSITIONING_M, color="C3", ls=":", lw=0.8)
    ax.axhline(100 * PAPER_MAX_MODELLING_M, color="C2", ls=":", lw=0.8)
    box = {"facecolor": "white", "alpha": 0.8, "lw": 0, "pad": 1}
    ax.text(t[-1], 100 * PAPER_MAX_POSITIONING_M + 0.5, "paper: max positioning 16 cm",
            color="C3", fontsize=8, ha="right", bbox=box)
    ax.text(t[-1], 100 * PAPER_MAX_MODELLING_M + 0.5, "paper: modelling < 8 cm", color="C2",
            fontsize=8, ha="right", bbox=box)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("error (cm)")
    ax.set_title(f"Errors against the truth and the paper's: {title}", fontsize=10)
    top = max(100 * max(float(np.max(v)) for v in err.values()), 16.0)
    ax.set_ylim(0, 1.45 * top)
    ax.legend(fontsize=7, loc="upper left", ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    files.append(out / f"errors_{tag}.png")
    fig.savefig(files[-1], dpi=120)
    plt.close(fig)

    rates = {k: np.array([r.rates_bps.get(k, np.nan) for r in recs]) for k in recs[0].rates_bps}
    fig, ax1 = plt.subplots(figsize=(8, 4.2))
    ap_names = [d.name for d in dep.twin.config.devices if d.kind == "access_point"]
    alloc = allocation(dep.twin.config)
    for k, v in rates.items():
        ok = np.isfinite(v)
        if not ok.any():
            continue
        c = f"C{ap_names.index(k.split('->')[0]) if k.split('->')[0] in ap_names else 9}"
        alt = "(" in k
        if k.endswith("[MCS]"):  # the modem's rate through the MCS table
            la = dep.twin.config.link_adaptation
            ax1.plot(t[ok], v[ok] / 1e6, "-.", lw=1.6, color=c,
                     label=f"{k[:-6]} MCS rate ({la.table}, EVM {la.evm_db:g} dB)")
            continue
        ax1.plot(t[ok], v[ok] / 1e6, "--" if alt else "-", lw=1.0 if alt else 1.8, color=c,
                 label=f"{k} Shannon" + ("" if alt else f" (as configured: {alloc})"))
    ax1.set_ylim(bottom=0)
    ax1.set_xlabel("time (s)")
    ax1.set_ylabel("rate (Mbit/s): Shannon (solid), MCS (dash-dot)")
    ax2 = ax1.twinx()
    for i, d in enumerate(d for d in dep.twin.config.devices if d.kind == "access_point"):
        dist = np.linalg.norm(g["truth"] - np.asarray(d.position[:2]), axis=1)
        ax2.plot(t, dist, ls=":", color=f"C{i}", lw=1, label=f"distance to {d.name}")
    ax2.set_ylabel("horizontal distance to AP (m)")
    h1, l1 = ax1.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax1.legend(h1 + h2, l1 + l2, fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.15),
               ncol=2)
    ax1.set_title(f"Shannon and MCS rates along the path: {title}")
    ax1.grid(alpha=0.3)
    files.append(out / f"rates_{tag}.png")
    fig.savefig(files[-1], dpi=120, bbox_inches="tight")
    plt.close(fig)
    return files


def rate_observations(dep: Deployment) -> dict:
    """Check "AP1 well above AP2, each rising as the robot nears its AP" on a run.

    Returns per link the mean rate (Mbit/s) and the Spearman-like rank
    correlation between rate and distance to the AP (negative: rises when nearer).
    """
    recs = dep.records
    truth = np.array([r.truth for r in recs])
    out = {}
    aps = {d.name: d for d in dep.twin.config.devices if d.kind == "access_point"}
    for k in recs[0].rates_bps:
        d = aps.get(k.split("->")[0])
        if d is None or k.endswith("[MCS]"):  # MCS rates saturate: no rank trend
            continue
        v = np.array([r.rates_bps.get(k, np.nan) for r in recs])
        ok = np.isfinite(v)
        if ok.sum() < 3:
            continue
        dist = np.linalg.norm(truth[ok] - np.asarray(d.position[:2]), axis=1)
        rv = np.argsort(np.argsort(v[ok]))
        rd = np.argsort(np.argsort(dist))
        corr = float(np.corrcoef(rv, rd)[0, 1])
        out[k] = {"mean_mbps": float(v[ok].mean() / 1e6), "min_mbps": float(v[ok].min() / 1e6),
                  "max_mbps": float(v[ok].max() / 1e6), "rank_corr_rate_vs_distance": corr}
    return out


# --------------------------------------------------------------------------- driver


def _run(folder, db, settings, steps, dt, seed, rate_every, label, extra_phy=None,
         rate_samples=None):
    """One deployment run -> (Deployment, result dict). ``rate_samples``: coarsen the PHY
    cadence to about that many rate samples over the run (:func:`rate_cadence`)."""
    t0 = time.perf_counter()
    dep = Deployment(folder, db, settings, seed=seed, dt=dt, rate_every=rate_every,
                     extra_phy=extra_phy)
    n = steps if steps is not None else dep.lap_steps()
    if rate_samples is not None:  # before the first step: the cadence of the whole run
        dep.rate_every = rate_cadence(n, rate_every, rate_samples)
    dep.run(n)
    wall = time.perf_counter() - t0
    err = errors(dep.records)
    key = next(iter(dep.records[0].rates_bps), None) if dep.records else None
    res = {"settings": {k: v for k, v in asdict(settings).items() if k != "mca"},
           "steps": n, "dt_s": dt, "wall_s": wall, "rate_every": dep.rate_every,
           "rate_samples": int(sum(np.isfinite(r.rates_bps.get(key, np.nan))
                                   for r in dep.records)) if key else 0,
           "errors": {k: summarize(v) for k, v in err.items()},
           "perturbation": dep.perturbation["material"] if dep.perturbation else None,
           "calibration_error": {"dxy_m": dep.calib[0].tolist(),
                                 "dyaw_deg": math.degrees(dep.calib[1])}}
    # How well the physical robot follows the intended path (truth vs path).
    truth = np.array([r.truth for r in dep.records])
    res["path"] = dep.path_spec
    res["rejected_estimates"] = dep.rejected
    res["truth_off_path"] = summarize([abs(dep.path.project(p).error) for p in truth])
    i = int(np.argmax(err["positioning"]))
    r = dep.records[i]
    res["worst_step"] = {"step": r.step, "positioning_m": float(err["positioning"][i]),
                         "modelling_m": float(err["modelling"][i]),
                         "estimate": r.estimate.tolist(), "odometry": r.odometry.tolist(),
                         "twin": r.twin.tolist(),
                         "twin_to_estimate_m": float(np.linalg.norm(r.estimate - r.twin))}
    log.info("%s: %d steps in %.1f s", label, n, wall)
    return dep, res


def run_case_study(folder, out_dir="out/demo", *, spacing: float = 0.05, steps: int | None = None,
                   dt: float = 0.25, seed: int = 0, cache_dir="out/cache", table_points: int = 12,
                   snrs=(0.0, 10.0, 20.0, 30.0), closed_loop_steps: int | None = None,
                   rate_every: int = 2, mca: dict | None = None,
                   closed_loop_method: str = "MCA-angles", closed_loop_fusion: str = "ekf",
                   closed_loop: bool = True, path: dict | None = None,
                   report=print) -> dict:
    """Run the whole case study on a scene folder; write figures, table.md, metrics.json.

    Errors are reported against the simulator's truth first (``metrics["headline"]``
    and the summary printed last); the paper-mode run's errors against odometry are
    the paper's comparison, a self-consistency check of the twin.

    Args:
        folder: scene folder of the twin's room.
        out_dir: output folder.
        spacing: fingerprint grid spacing, m (default 5 cm, the paper's; the
            database takes ~41 s to trace on 2 cores with chain reuse).
        steps: deployment steps (default: one lap of a closed path, or to the end of
            an open one).
        dt: step, s.
        table_points: test points along the path for the static table.
        closed_loop_steps: steps of the closed-loop realistic run (default ``steps``).
        rate_every: PHY (rates) every this many steps in the paper-mode run; the
            closed loop coarsens it to about :data:`CLOSED_LOOP_RATE_SAMPLES` samples.
        mca: MCA parameters (eps, k, num_paths).
        closed_loop_method: localizer of the closed-loop realistic run (default
            ``"MCA-angles"``; ``"PDP"`` with ``closed_loop_fusion="blend"`` is the
            earlier run).
        closed_loop_fusion: ``"ekf"`` (default: :class:`~isac_twin.localization.fusion.PoseEKF`
            over odometry with the gated fixes) or ``"blend"`` (complementary filter).
        closed_loop: run it at all (``metrics["closed_loop"]`` is None otherwise).
        path: the path the robot follows, a ``[devices.path]`` spec of any kind
            (``{"kind": "circle", "centre": [x, y], "radius": r}``, ``"polyline"``,
            ``"figure_eight"``, ``"goal"``; docs/config.md); default: the robot's
            own ``[devices.path]`` in twin.toml. Checked like twin.toml's (keys,
            units, free space: exit 2 on the CLI).
        report: where progress lines go (the CLI prints; pass a logger method).

    Returns:
        The metrics dictionary (also written to ``metrics.json``).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mca = dict(mca or CASE_STUDY_MCA)
    # refused before anything is traced (the same checks as DeploymentSettings)
    closed = DeploymentSettings(source="real", mode="pilots", snr_db=20.0, perturb=True,
                                closed_loop=True, method=closed_loop_method,
                                fusion=closed_loop_fusion, mca=mca, path=path,
                                num_paths=mca.get("num_paths", 9))
    timings = {}
    t0 = time.perf_counter()
    scene = load_scene(folder)
    if path is not None:  # an override: checked as if it stood in twin.toml
        import dataclasses

        robot, _ = robot_path(scene.config, path)
        path = parse_path_spec(path, scene.config.path, f"case study path ({robot})")
        dev = dataclasses.replace(scene.config.device(robot), path=path)
        check_placement(scene, devices=[dev])
    robot, path = robot_path(scene.config, path)
    closed.path = path
    report(f"case study on {scene.config.scene.name!r}: {robot} follows "
           f"{path_from_spec(path, start=scene.config.device(robot).position[:2]).describe()}")
    db = cached_database(scene, spacing=spacing, cache_dir=cache_dir)
    timings["database"] = time.perf_counter() - t0
    report(f"fingerprint database: {db.path} ({db.summary()['free']} free points, "
           f"{spacing * 100:g} cm grid, {len(db.ap_names)} APs) in {timings['database']:.1f} s")

    paper = DeploymentSettings(source="twin", mode="tracer", perturb=True, mca=mca, path=path,
                               num_paths=mca.get("num_paths", 9))
    # Rates as configured, and with the other allocation for comparison: APs on
    # disjoint symbols if they share REs (then each link is interfered by the
    # other AP), else all APs on all REs.
    if allocation(scene.config) == "shared REs":
        extra = {"disjoint symbols": NetworkPHY(disjoint_config(scene.config))}
    else:
        extra = {"shared REs": NetworkPHY(shared_config(scene.config))}
    dep, res_paper = _run(folder, db, paper, steps, dt, seed, rate_every, "paper mode", extra)
    res_paper["comparison"] = ("self-consistency (the paper's): the twin's own tracer at the "
                               "twin's position, errors against odometry")
    timings["paper_mode"] = res_paper["wall_s"]
    e = res_paper["errors"]
    report(f"paper mode, self-consistency ({res_paper['steps']} steps, "
           f"{res_paper['wall_s']:.1f} s): estimate vs truth RMSE "
           f"{100 * e['estimate_vs_truth']['rmse']:.1f} cm, max "
           f"{100 * e['estimate_vs_truth']['max']:.1f} cm; against odometry (the paper's "
           f"comparison): max positioning error {100 * e['positioning']['max']:.1f} cm "
           f"(paper ~16 cm), max modelling error {100 * e['modelling']['max']:.1f} cm "
           f"(paper < 8 cm)")
    files = plot_run(dep, out, "paper",
                     "paper mode (twin tracer MDP, open loop; self-consistency)")
    rates = rate_observations(dep)
    for k, v in rates.items():
        report(f"  rate {k}: mean {v['mean_mbps']:.1f} Mbit/s "
               f"({v['min_mbps']:.1f}..{v['max_mbps']:.1f}), rank corr. with distance "
               f"{v['rank_corr_rate_vs_distance']:+.2f}")

    res_closed = None
    cl_label = closed_loop_label(closed)
    if closed_loop:
        # Closed loop in the realistic mode: pilots at 20 dB received in the perturbed
        # room, the controller steering on the fused estimate.
        n_cl = closed_loop_steps if closed_loop_steps is not None else steps
        dep2, res_closed = _run(folder, db, closed, n_cl, dt, seed, rate_every, "closed loop",
                                rate_samples=CLOSED_LOOP_RATE_SAMPLES)
        res_closed["rates"] = rate_observations(dep2)
        timings["closed_loop"] = res_closed["wall_s"]
        e2 = res_closed["errors"]
        report(f"closed loop, realistic mode ({cl_label}, pilots 20 dB, perturbed room, "
               f"{res_closed['steps']} steps, {res_closed['wall_s']:.1f} s): estimate vs truth "
               f"RMSE {100 * e2['estimate_vs_truth']['rmse']:.1f} cm, max "
               f"{100 * e2['estimate_vs_truth']['max']:.1f} cm; {res_closed['rejected_estimates']} "
               f"fixes gated out; {res_closed['rate_samples']} rate samples")
        files += plot_run(dep2, out, "closed_loop",
                          f"closed loop, {cl_label}, pilots 20 dB, perturbed room")

    t1 = time.perf_counter()
    rows = static_table(folder, db, n_points=table_points, snrs=snrs, seed=seed, mca=mca,
                        path=path)
    timings["table"] = time.perf_counter() - t1
    md = table_markdown(rows)
    (out / "table.md").write_text(
        f"Static localization error against the simulator's truth at {table_points} points "
        f"along the robot's path (database: {spacing * 100:g} cm grid of the twin's room; "
        f"cm):\n\n{md}\n")
    report(md)

    head = headline(res_paper, res_closed, rows, cl_label)
    for line in headline_lines(head):
        report(line)
    metrics = {
        "headline": head,
        "paper_mode": res_paper, "closed_loop": res_closed,
        "table": [{k: v for k, v in r.items() if k != "errors"} for r in rows],
        "database": {**db.summary(), "path": str(db.path)},
        "paper_reference": {"max_positioning_m": PAPER_MAX_POSITIONING_M,
                            "max_modelling_m": PAPER_MAX_MODELLING_M},
        "timings_s": timings, "rates": rates,
        "figures": [str(f) for f in files],
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float))
    return metrics


def closed_loop_label(settings: DeploymentSettings) -> str:
    """``"MCA-angles + EKF"``, ``"PDP + complementary filter"``: method and fusion."""
    return settings.method + (" + EKF" if settings.fusion == "ekf"
                              else " + complementary filter")


def best_pilot_rows(rows: list[dict], snr_db: float = 20.0) -> list[dict]:
    """The static table's best pilot-mode method (lowest median in the first room) at the
    table's SNR nearest ``snr_db``: its rows in every room ([] without pilot rows)."""
    pil = [r for r in rows if r["mode"].startswith("pilots ")]
    if not pil:
        return []
    snr = lambda r: float(r["mode"].split()[1])  # noqa: E731  ("pilots 20 dB")
    near = min({snr(r) for r in pil}, key=lambda v: abs(v - snr_db))
    pil = [r for r in pil if snr(r) == near]
    first = pil[0]["room"]
    best = min((r for r in pil if r["room"] == first), key=lambda r: r["median"])["method"]
    return [r for r in pil if r["method"] == best]


def headline(res_paper: dict, res_closed: dict | None, rows: list[dict],
             closed_label: str = "") -> dict:
    """``metrics["headline"]``: errors against the simulator's truth (m), then the paper's
    self-consistency figures (against odometry), each entry labelled."""
    h = {}
    if res_closed is not None:
        e = res_closed["errors"]
        h["closed_loop_vs_truth"] = {
            "what": f"closed loop, realistic mode ({closed_label}, pilots 20 dB, perturbed "
                    "room): estimate vs the simulator's truth",
            **e["estimate_vs_truth"], "odometry_vs_truth": e["odometry_vs_truth"],
            "fixes_gated_out": res_closed["rejected_estimates"], "steps": res_closed["steps"]}
    best = best_pilot_rows(rows)
    if best:
        h["static_best_pilots_vs_truth"] = {
            "what": f"static table, {best[0]['method']} on {best[0]['mode']}: estimate vs "
                    "the simulator's truth",
            **{r["room"]: {k: r[k] for k in ("median", "p90", "max")} for r in best}}
    e = res_paper["errors"]
    h["paper_mode_vs_truth"] = {
        "what": "paper mode (twin tracer MDP at the twin's position, open loop): estimate "
                "vs the simulator's truth", **e["estimate_vs_truth"]}
    h["paper_self_consistency"] = {
        "what": "the paper's comparison, self-consistency: positioning = estimate vs "
                "odometry, modelling = twin vs odometry (odometry is the paper's ground truth)",
        "positioning": e["positioning"], "modelling": e["modelling"],
        "paper": {"max_positioning_m": PAPER_MAX_POSITIONING_M,
                  "max_modelling_m": PAPER_MAX_MODELLING_M}}
    return h


def headline_lines(h: dict) -> list[str]:
    """The printed summary of :func:`headline`: against the truth first."""
    cm = lambda d: (f"RMSE {100 * d['rmse']:.1f} cm, median {100 * d['median']:.1f} cm, "  # noqa
                    f"max {100 * d['max']:.1f} cm")
    out = ["summary, against the simulator's truth:"]
    if "closed_loop_vs_truth" in h:
        c = h["closed_loop_vs_truth"]
        out.append(f"  {c['what']}: {cm(c)} ({c['fixes_gated_out']} of {c['steps']} fixes "
                   f"gated out; odometry alone: {cm(c['odometry_vs_truth'])})")
    if "static_best_pilots_vs_truth" in h:
        c = h["static_best_pilots_vs_truth"]
        rooms = "; ".join(f"{room} room median {100 * v['median']:.1f} / P90 "
                          f"{100 * v['p90']:.1f} / max {100 * v['max']:.1f} cm"
                          for room, v in c.items() if room != "what")
        out.append(f"  {c['what']}: {rooms}")
    c = h["paper_mode_vs_truth"]
    out.append(f"  {c['what']}: {cm(c)}")
    c = h["paper_self_consistency"]
    out.append("the paper's comparison (self-consistency, against odometry): max positioning "
               f"error {100 * c['positioning']['max']:.1f} cm (paper ~16 cm), max modelling "
               f"error {100 * c['modelling']['max']:.1f} cm (paper < 8 cm)")
    return out
