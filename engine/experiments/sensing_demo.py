"""Sensing demo on a room (default the bundled lab): tracking, range-Doppler maps, ISAC trade-off.

``python -m isac_twin.experiments.sensing_demo --out docs/figures [--steps 95 --dt 0.5] [--scene NAME|DIR]``
writes ``sensing_range_doppler.png``, ``sensing_tracking.png`` and
``sensing_tradeoff.png`` and prints the metrics. The functions are reused by
the tests (``tests/engine/sensing``).

Lab sensing link: AP2 (1x1, at (4, 0.05, 2)) transmits, AP1 (4x8 array at
(0.05, 3, 2), facing +x) receives -- the receiver needs the array for
angles; the 1x1 AP2 cannot measure an angle. On another scene the demo
takes the first ``[[sensing]]`` link, the first robot and its own
``[devices.path]`` from its twin.toml, and draws the room's floor plan.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

LAB = Path(__file__).resolve().parents[2] / "blend_scenes" / "aces_lab" / "scene"
CIRCLE = {"kind": "circle", "centre": [4.0, 3.0], "radius": 1.5}


def lab_link(rho: float = 0.25, power_dbm: float = 20.0):
    """The bistatic AP2 -> AP1 sensing link of the lab."""
    from ..phy import PlanarArray
    from ..sensing.link import SensingLinkSpec

    return SensingLinkSpec(tx="AP2", rx="AP1", rx_array=PlanarArray(4, 8), rho=rho,
                           power_dbm=power_dbm)


def scene_link(config, rho: float | None = None, power_dbm: float | None = None):
    """The first ``[[sensing]]`` link of a scene's config, radar every step (the demo
    runs it on every step), ``rho`` and ``power_dbm`` overriding the table's.

    Raises:
        ConfigError: the scene has no ``[[sensing]]`` table (naming its twin.toml).
    """
    import dataclasses

    from ..errors import ConfigError
    from ..sensing.config import link_spec

    if not config.sensing:
        raise ConfigError(f"{config.path}: sensing: the sensing demo needs a [[sensing]] link "
                          "(tx, rx with an array for angles)")
    spec = link_spec(config, config.sensing[0])
    return dataclasses.replace(spec, every=1, rho=spec.rho if rho is None else rho,
                               power_dbm=spec.power_dbm if power_dbm is None else power_dbm)


def first_robot(config) -> str:
    """Name of the scene's first robot (the demo's target)."""
    from ..errors import ConfigError

    for d in config.devices:
        if d.kind == "robot":
            return d.name
    raise ConfigError(f"{config.path}: devices: the sensing demo needs a robot")


def lab_twin(dt: float = 0.5, path: dict | None = CIRCLE, scene=LAB):
    """The bundled lab's twin with robot1 on the circle (no PHY stage)."""
    from ..twin.twin import Twin

    tw = Twin.from_scene(scene, dt=dt, phy=False, sensing=False)  # its own radar below
    if path is not None:
        tw.set_path("robot1", path)
    return tw


def run_tracking(steps: int = 30, dt: float = 0.5, *, background: str = "ema",
                 range_method: str = "first_arrival", rho: float = 0.25,
                 power_dbm: float = 20.0, keep_maps: bool = False, twin=None,
                 robot_targets: bool = True, seed: int = 0, link=None) -> dict:
    """Run the lab with a :class:`RadarEstimator` and score it against truth.

    Returns a dict: ``truth [S, 2]``, ``detections`` (list of ``[M, 2]``),
    ``tracks`` (list of ``{id: [2]}``), ``det_rmse`` (m, nearest detection
    to the truth, steps with one), ``track_rmse`` (m, confirmed track
    nearest the truth, steps with one), ``track_coverage`` (share of steps
    with a confirmed track within 0.5 m), ``false_tracks`` (confirmed
    track-steps farther than 1 m from every target), ``estimator``.
    """
    from ..sensing.estimator import RadarEstimator

    tw = twin or lab_twin(dt)
    robot = first_robot(tw.config)
    link = link or lab_link(rho, power_dbm)
    est = RadarEstimator([link], background=background, keep_maps=keep_maps,
                         radar_kw={"range_method": range_method}, robot_targets=robot_targets,
                         seed=seed)
    tw.estimators.append(est)
    truth, dets, tracks = [], [], []
    det_err, trk_err, false_tracks, covered = [], [], 0, 0
    for _ in range(steps):
        r = tw.step()
        s = r.sensing
        t = np.array([r.robots[robot].pose[:2]]) if robot_targets else np.zeros((0, 2))
        truth.append(t[0] if len(t) else np.full(2, np.nan))
        p = np.array([d.position[:2] for ds in s.detections.values() for d in ds
                      if d.position is not None]).reshape(-1, 2)
        dets.append(p)
        tracks.append({tr.id: tr.position for tr in s.tracks})
        if len(t) and len(p):
            det_err.append(np.min(np.linalg.norm(p - t[0], axis=1)))
        tp = np.array([tr.position for tr in s.tracks]).reshape(-1, 2)
        if len(t) and len(tp):
            e = np.min(np.linalg.norm(tp - t[0], axis=1))
            trk_err.append(e)
            covered += e < 0.5
        for q in tp:
            if not len(t) or np.min(np.linalg.norm(t - q, axis=1)) > 1.0:
                false_tracks += 1
    rm = lambda e: float(np.sqrt(np.mean(np.square(e)))) if e else float("nan")  # noqa: E731
    return {"truth": np.array(truth), "detections": dets, "tracks": tracks,
            "det_rmse": rm(det_err), "track_rmse": rm(trk_err),
            "track_coverage": covered / max(steps, 1), "false_tracks": false_tracks,
            "estimator": est, "twin": tw}


def tradeoff(rhos=(1 / 64, 1 / 32, 1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0), poses: int = 12,
             power_dbm: float = 20.0, sensing_power_dbm: float = -10.0, seed: int = 0,
             scene=None) -> dict:
    """Rate of the sensing transmitter -> robot on the data REs vs sensing position RMSE
    (per-frame detections, empty-room background) over ``poses`` robot poses on the
    lab's circle, or (``scene`` given) along the robot's own ``[devices.path]``.

    The radar runs at ``sensing_power_dbm`` (a low power shows the
    noise-limited regime where the number of sensing REs matters); the
    rate uses ``power_dbm``.
    """
    from ..phy import PlanarArray
    from ..sensing.estimator import RadarEstimator, grid_from_config
    from ..sensing.isac import comm_channel, data_rate

    tw = lab_twin(0.5, path=None, scene=scene or LAB)
    grid = grid_from_config(tw.config)
    robot = first_robot(tw.config)
    dev = tw.config.device(robot)
    if scene is None:
        ang = np.linspace(0, 2 * np.pi, poses, endpoint=False)
        xyyaw = [(4 + 1.5 * np.cos(a), 3 + 1.5 * np.sin(a), a + np.pi / 2) for a in ang]
        make_link, tx = (lambda r: lab_link(r, sensing_power_dbm)), "AP2"
    else:
        from ..robots.control import path_from_spec

        if dev.path is None:
            raise ValueError(f"{tw.config.path}: devices ({robot}).path: the trade-off "
                             "samples the robot's path; add [devices.path]")
        path = path_from_spec(dev.path, start=dev.position[:2])
        sv = (np.arange(poses) + 0.25) * path.length / poses
        tg = path.tangent(sv)
        xyyaw = [(x, y, float(np.arctan2(t[1], t[0]))) for (x, y), t in zip(path.point(sv), tg)]
        make_link = lambda r: scene_link(tw.config, r, sensing_power_dbm)  # noqa: E731
        tx = tw.config.sensing[0].tx
    rates, rmse = [], []
    for rho in rhos:
        est = RadarEstimator([make_link(rho)], background="reference",
                             radar_kw={"range_method": "first_arrival"}, publish=False,
                             seed=seed)
        errs, rr = [], []
        for x, y, yaw in xyyaw:
            st = tw.agents[robot].state
            st.pose[0], st.pose[1], st.pose[5] = x, y, yaw
            res = _fake_result(tw, x, y, yaw, robot)
            est(tw, res)
            p = [d.position[:2] for ds in res.sensing.detections.values() for d in ds
                 if d.position is not None]
            errs.append(min(np.linalg.norm(np.array(p) - [x, y], axis=1)) if p else np.nan)
            poses_now = tw.device_poses()
            paths = tw.tracer(tw.scene, poses_now, [(tx, robot)])[(tx, robot)]
            ta = tw.config.device(tx).array
            h = comm_channel(paths, grid, PlanarArray(dev.array.rows, dev.array.cols),
                             PlanarArray(ta.rows, ta.cols))
            rr.append(data_rate(h, grid, rho, power_dbm))
        e = np.array(errs)
        miss = np.isnan(e) | (e > 1.0)
        rmse.append(float(np.sqrt(np.mean(np.where(miss, 1.0, e) ** 2))))
        rates.append(float(np.mean(rr)))
        log.info("rho=%.4f rate=%.1f Mbit/s rmse=%.3f m (misses %d)", rho, rates[-1] / 1e6,
                 rmse[-1], int(miss.sum()))
    return {"rho": np.array(rhos), "rate_bps": np.array(rates), "rmse_m": np.array(rmse)}


def _fake_result(tw, x, y, yaw, robot="robot1"):
    from ..twin.state import RobotState, StepResult

    res = StepResult(step=0, time_s=0.0)
    res.robots[robot] = RobotState(robot, np.array([x, y, 0, 0, 0, yaw]), np.zeros(2))
    return res


def figures(out: Path, steps: int = 95, dt: float = 0.5, scene=None) -> dict:
    """Write the three figures into ``out``; return the metrics. ``scene``: a scene folder
    (default the bundled lab with its circle and AP2 -> AP1 link)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    if scene is None:
        twin_of = lambda: lab_twin(dt)  # noqa: E731
        link = lab_link()
    else:
        twin_of = lambda: lab_twin(dt, path=None, scene=scene)  # noqa: E731  own path
        link = scene_link(twin_of().config)
    tw = twin_of()
    robot = first_robot(tw.config)
    m = run_tracking(steps, dt, keep_maps=True, twin=tw, link=link)
    est = m["estimator"]
    # --- range-Doppler map: raw vs background-subtracted (one step)
    from ..sensing.estimator import RadarEstimator

    tw2 = twin_of()
    raw = RadarEstimator([link], background="none", keep_maps=True, publish=False)
    tw2.estimators.append(raw)
    for _ in range(3):
        r2 = tw2.step()
    fig, axs = plt.subplots(1, 2, figsize=(11, 4))
    sub = est.history[min(20, len(est.history) - 1)]
    for ax, (title, step) in zip(axs, [("no background subtraction", r2.sensing),
                                       ("EMA background subtracted", sub)]):
        rd = step.maps[link.name]
        p = 10 * np.log10(rd.power / rd.power.max() + 1e-12)
        ext = [rd.path_length_m[0], rd.path_length_m[-1], rd.doppler_hz[0], rd.doppler_hz[-1]]
        im = ax.imshow(p, aspect="auto", origin="lower", extent=ext, vmin=-60, vmax=0,
                       cmap="viridis")
        for d in step.detections[link.name]:
            ax.plot(d.path_length_m, d.doppler_hz, "rx")
        ax.set_xlim(0, 40)
        ax.set_xlabel("bistatic path length |T-tx|+|T-rx| [m]")
        ax.set_ylabel("Doppler [Hz]")
        ax.set_title(f"{link.name} range-Doppler, {title}")
        fig.colorbar(im, ax=ax, label="dB")
    fig.tight_layout()
    fig.savefig(out / "sensing_range_doppler.png", dpi=110)
    plt.close(fig)
    # --- tracking
    fig, ax = plt.subplots(figsize=(6.5, 5.5))
    if scene is not None:  # the room's own floor plan
        from ..scene.room import draw_plan

        draw_plan(ax, tw.scene, label_aps=False)
    t = m["truth"]
    ax.plot(t[:, 0], t[:, 1], "k-", lw=2, label=f"{robot} truth")
    d = np.concatenate([x for x in m["detections"] if len(x)]) if any(
        len(x) for x in m["detections"]) else np.zeros((0, 2))
    ax.plot(d[:, 0], d[:, 1], ".", color="tab:orange", ms=4, label="radar detections")
    ids = sorted({i for tr in m["tracks"] for i in tr})
    for i in ids:
        p = np.array([tr[i] for tr in m["tracks"] if i in tr])
        ax.plot(p[:, 0], p[:, 1], "-", lw=1.2, label=f"track {i}")
    rx, txd = tw.config.device(link.rx), tw.config.device(link.tx)
    ax.plot(*rx.position[:2], "bs", label=f"{rx.name} (rx, {rx.array.rows}x{rx.array.cols})")
    ax.plot(*txd.position[:2], "g^", label=f"{txd.name} (tx)")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    kind = "monostatic" if link.rx == link.tx else "bistatic"
    ax.set_title(f"{kind} {link.name} tracking: det RMSE {m['det_rmse']:.2f} m, "
                 f"track RMSE {m['track_rmse']:.2f} m", fontsize=9)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(out / "sensing_tracking.png", dpi=110)
    plt.close(fig)
    # --- trade-off
    tr = tradeoff(scene=scene)
    fig, ax1 = plt.subplots(figsize=(6.5, 4.2))
    ax1.semilogx(tr["rho"], tr["rate_bps"] / 1e6, "o-", color="tab:blue")
    ax1.set_xlabel("sensing share rho of the REs")
    ax1.set_ylabel(f"{link.tx}->{robot} rate on data REs [Mbit/s]", color="tab:blue")
    ax2 = ax1.twinx()
    ax2.semilogx(tr["rho"], tr["rmse_m"], "s-", color="tab:red")
    ax2.set_ylabel("sensing position RMSE [m] (miss = 1 m)", color="tab:red")
    ax1.set_title(f"ISAC trade-off, {tw.config.scene.name} (radar at -10 dBm, rate at 20 dBm)",
                  fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "sensing_tradeoff.png", dpi=110)
    plt.close(fig)
    return {"det_rmse": m["det_rmse"], "track_rmse": m["track_rmse"],
            "track_coverage": m["track_coverage"], "false_tracks": m["false_tracks"],
            "tradeoff": {k: np.asarray(v).tolist() for k, v in tr.items()}}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("docs/figures"))
    ap.add_argument("--steps", type=int, default=95)
    ap.add_argument("--dt", type=float, default=0.5)
    ap.add_argument("--scene", default=None,
                    help="a bundled room's name or a scene folder with a [[sensing]] link "
                         "(default: the lab, robot1 on its circle, AP2 -> AP1)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    scene = a.scene
    if scene is not None and not Path(scene).exists():
        from ..scene.bundled import bundled_scene_dir

        scene = bundled_scene_dir(scene)
    print(figures(a.out, a.steps, a.dt, scene=scene))


if __name__ == "__main__":
    main()
