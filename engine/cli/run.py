"""``run``, ``record``, ``replay``, ``recover``: the twin run for N steps, recorded to MCAP,
replayed from a recording, and a killed recording made readable again."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..bus.bus import Bus
from ..errors import UsageError
from ..live.server import LiveServer
from ..transport.bridge import TwinBridge
from ..transport.record import (
    CsiRecording,
    TrajectoryReplay,
    read_metadata,
    record_twin,
    recover,
    replay_to_bus,
)
from ..twin import Twin
from .lifecycle import StopSignals, wait_for_stop
from .options import check_radar, input_errors, radar_arg, radar_kw, scene_arg, scene_path

__all__ = ["COMMANDS", "cmd_run", "cmd_record", "cmd_replay", "cmd_recover", "radar_line"]


def _run_args(p: argparse.ArgumentParser) -> None:
    scene_arg(p)
    p.add_argument("--steps", type=int, default=100, help="steps to run (default 100)")
    p.add_argument("--rate", type=float, default=None,
                   help="pace the loop at this many steps per second in real time "
                        "(default: as fast as possible); prints the overruns and the "
                        "stage that caused each")
    p.add_argument("--dt", type=float, default=0.05, help="simulated time per step, s")
    p.add_argument("--seed", type=int, default=0, help="seed of every random stream")
    p.add_argument("--no-phy", action="store_true", help="skip channels and rates")
    p.add_argument("--timing", action="store_true", help="print the per-stage timing table")
    radar_arg(p)


def radar_line(frame) -> str:
    """``radar (step k) N det M tracks`` of a delivered radar frame (a ``SensingStep``)."""
    n = sum(len(v) for v in frame.detections.values())
    return f"radar (step {frame.step}) {n} det {len(frame.tracks)} tracks"


def _step_line(r, no_phy: bool) -> str:
    """The line ``run`` prints for a step result ``r``: poses, paths, rates, radar."""
    parts = [f"step {r.step:4d} t={r.time_s:6.2f}s"]
    for name, rb in r.robots.items():
        parts.append(f"{name} ({rb.pose[0]:.2f}, {rb.pose[1]:.2f}) yaw {rb.pose[5]:+.2f}")
    for (tx, rx), ls in r.links.items():
        parts.append(f"{tx}->{rx} {ls.paths.num_paths if ls.paths else 0} paths"
                     + ("" if no_phy else f" {ls.rate_bps / 1e6:.0f} Mbit/s"
                        f" (MCS {ls.mcs_rate_bps / 1e6:.0f})"))
    if r.sensing is not None:  # a [[sensing]] radar frame was delivered this step
        parts.append(radar_line(r.sensing))
    return "  ".join(parts)


def cmd_run(args) -> int:
    """Run the twin (the paper's Algorithm 1) for N steps; print a line per step."""
    if args.steps < 0:
        raise UsageError(f"--steps {args.steps}: expected >= 0")
    if args.rate is not None and not args.rate > 0:
        raise UsageError(f"--rate {args.rate}: expected a positive rate in Hz")
    check_radar(args)
    twin = Twin.from_scene(scene_path(args), seed=args.seed, dt=args.dt, phy=not args.no_phy,
                           **radar_kw(args))
    try:
        for r in twin.run(args.steps, rate_hz=args.rate):
            print(_step_line(r, args.no_phy), flush=True)
        last = twin.flush_sensing()  # a frame still computed off the stepping thread
    finally:
        twin.close()
    if last is not None:
        print(radar_line(last), flush=True)
    if args.rate is not None:
        st = twin.stats
        print(f"paced at {args.rate:g} Hz: {st.steps} steps in {st.wall_s:.2f} s, "
              f"{st.overrun_summary()}", flush=True)
    if args.timing:
        print(twin.stats.table())
    return 0


def _record_args(p: argparse.ArgumentParser) -> None:
    scene_arg(p)
    p.add_argument("--steps", type=int, default=100, help="twin steps to run (default 100)")
    p.add_argument("--out", type=Path, required=True, help="output .mcap")
    p.add_argument("--rate", type=float, default=None, help="steps per second (default: max)")
    p.add_argument("--seed", type=int, default=0, help="seed of the twin's noise")
    p.add_argument("--compression", choices=("none", "zstd", "lz4"), default="zstd")
    p.add_argument("--stamps", choices=("sim", "wall"), default="sim",
                   help="header stamps and log times: simulated s from 0 (default) or "
                        "wall clock (Unix epoch of the start + simulated s)")
    p.add_argument("--csi", choices=("compact", "full"), default="compact",
                   help="CSI: 1 symbol in 14, 1 subcarrier in 16 (default) or everything")
    p.add_argument("--csi-snr", type=float, default=None, metavar="DB",
                   help="add white Gaussian noise to the recorded CSI at this SNR (dB; "
                        "seeded by --seed): a measured channel estimate")
    p.add_argument("--connect", action="append", default=None,
                   help="zenoh endpoint of real robots to mirror (repeatable), "
                        "e.g. tcp/127.0.0.1:7448")
    p.add_argument("--share", action="store_true",
                   help="also publish every twin topic on zenoh (rmw_zenoh format, "
                        "wall-clock stamps) for ROS 2 nodes; needs --connect")
    p.add_argument("--share-prefix", default="/twin",
                   help="prefix of shared topic names (default /twin; '' keeps the names)")
    radar_arg(p)


def _bridge(twin: Twin, args) -> TwinBridge:
    """The zenoh bridge of ``--connect`` (and ``--share``) for ``record``."""
    from ..transport.zenoh_transport import ZenohConfig, ZenohTransport  # imports zenoh

    transport = ZenohTransport(ZenohConfig(connect=args.connect))
    try:
        with input_errors():
            return TwinBridge(twin, transport, share="all" if args.share else None,
                              share_prefix=args.share_prefix)
    except BaseException:
        transport.close()
        raise


def cmd_record(args) -> int:
    """Run the twin and record its topics, link metrics and paths to an MCAP file."""
    if args.share and not args.connect:
        raise UsageError("--share needs --connect (the zenoh router or peer to publish to)")
    noise = {"snr_db": args.csi_snr, "seed": args.seed}
    with input_errors("--csi-snr: "):
        csi = CsiRecording(**noise) if args.csi == "compact" else CsiRecording.full(**noise)
    check_radar(args)
    twin = Twin.from_scene(scene_path(args), seed=args.seed, **radar_kw(args))
    bridge = None
    try:
        bridge = _bridge(twin, args) if args.connect else None
        rec = record_twin(twin, args.steps, args.out, rate_hz=args.rate,
                          compression=args.compression, bridge=bridge,
                          stamp_epoch_s=time.time() if args.stamps == "wall" else 0.0,
                          csi=csi)
    finally:
        if bridge is not None:
            bridge.close()
        twin.close()  # (record_twin kept the last radar frame)
    print(f"recorded {rec.messages} messages of {args.steps} steps to {args.out}")
    return 0


def _recover_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", type=Path, help="an .mcap whose writer was killed")
    p.add_argument("--out", type=Path, default=None,
                   help="output (default <name>.recovered.mcap next to it)")


def cmd_recover(args) -> int:
    """Rewrite a killed recording's complete chunks as a finished MCAP file."""
    with input_errors():
        out, n = recover(args.recording, args.out)
    print(f"recovered {n} messages of {args.recording} to {out}")
    return 0


def _replay_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", type=Path, help="an .mcap written by `isac-twin record`")
    p.add_argument("--scene", type=Path, default=None,
                   help="scene folder (default: the one named in the recording)")
    p.add_argument("--speed", type=float, default=1.0,
                   help="pace relative to the recording (0 = as fast as possible)")
    p.add_argument("--steps", type=int, default=None, help="steps (default: the recording's)")
    p.add_argument("--bus-only", action="store_true",
                   help="only re-publish the messages on a bus and print the topic table")
    p.add_argument("--serve", type=int, default=None, metavar="PORT",
                   help="stream the replaying twin to Blender viewers on 127.0.0.1:PORT")


def cmd_replay(args) -> int:
    """Drive a twin along a recording's trajectories (or only re-publish its messages)."""
    if args.bus_only:
        bus = Bus()
        n = replay_to_bus(args.recording, bus, speed=args.speed or None)
        print(f"replayed {n} messages")
        print(bus.registry().table())
        return 0
    meta = read_metadata(args.recording)
    scene = args.scene or (Path(meta["scene"]) if meta.get("scene") else None)
    if scene is None:
        raise UsageError("the recording names no scene: pass --scene")
    dt = float(meta.get("dt", 0.05))
    twin = Twin.from_scene(scene, seed=int(meta.get("seed", 0)), dt=dt)
    with input_errors():
        rp = TrajectoryReplay(twin, args.recording)
    steps = args.steps if args.steps is not None else rp.steps
    rate = args.speed / dt if args.speed else None
    if args.serve is not None:
        server = LiveServer(twin, "127.0.0.1", args.serve, rate_hz=rate or 0.0, max_steps=steps)
        server.start()
        print(f"isac-twin replay: serving on 127.0.0.1:{server.address[1]}", flush=True)
        try:
            with StopSignals() as life:
                wait_for_stop(life.stop, done=server.done, linger_s=0.0)
        finally:
            server.stop()
        return 0
    for res in twin.run(steps, rate_hz=rate):
        poses = "  ".join(f"{n} ({r.pose[0]:.2f}, {r.pose[1]:.2f})" for n, r in res.robots.items())
        snr = "  ".join(f"{tx}->{rx} {ls.snr_db:.1f} dB" for (tx, rx), ls in res.links.items())
        print(f"step {res.step:4d} t={res.time_s:7.2f} s  {poses}  {snr}")
    return 0


#: command -> (adds its options to a sub-parser, runs it: args -> exit status)
COMMANDS = {
    "run": (_run_args, cmd_run),
    "record": (_record_args, cmd_record),
    "recover": (_recover_args, cmd_recover),
    "replay": (_replay_args, cmd_replay),
}
