"""Robots benchmark: LiDAR scan cost and kinematics + controller step cost.

Prints figures, asserts nothing. The LiDAR baseline is a per-beam loop of
Mitsuba ``ray_intersect`` calls (one ray each) measured in the same run, in
a closed box room the size of the bundled lab (8 x 6 x 3 m). Two loops: the
naive one builds each ray from Python floats, which Dr.Jit bakes into the
kernel as literals, so every beam compiles a kernel (its cost depends on
whether Dr.Jit's on-disk kernel cache already holds them from an earlier
run: seconds cold, ~0.25 s warm); the fair one passes opaque values so one
kernel is compiled once and reused, leaving the per-call overhead.

Run: ``.venv/bin/python bench/bench_robots.py``
"""

from __future__ import annotations

import math
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

import isac_twin  # noqa: E402,F401  (configures Dr.Jit's LLVM before mitsuba loads)
from isac_twin import load_scene  # noqa: E402
from isac_twin.bus.bus import Bus  # noqa: E402
from isac_twin.robots import (  # noqa: E402
    CirclePath,
    DiffDriveRobot,
    FigureEightPath,
    Lidar2D,
    PurePursuit,
    RobotAgent,
    SensorOptions,
)
from isac_twin.robots.kinematics import KinematicState  # noqa: E402
from isac_twin.robots.sensors import cast_rays  # noqa: E402
from isac_twin.scene.synthetic import box_room  # noqa: E402


def per_call(fn, n: int, warm: int = 3) -> float:
    """Median seconds per call of ``fn`` over ``n`` calls (after ``warm`` warm-up calls)."""
    for _ in range(warm):
        fn()
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def main() -> None:
    import mitsuba as mi

    scene = load_scene(box_room(tempfile.mkdtemp(), size=(8.0, 6.0, 3.0)))
    mi_scene = scene.sionna.mi_scene
    lidar = Lidar2D(scene, "burger")
    rng = np.random.default_rng(0)
    poses = [np.array([rng.uniform(1, 7), rng.uniform(1, 5), 0, 0, 0, rng.uniform(-3, 3)])
             for _ in range(64)]
    it = iter(range(10 ** 9))

    def scan():  # a new pose each call, as in a moving robot
        lidar.measure(0.0, KinematicState(pose=poses[next(it) % len(poses)]))

    def raw():
        o, d = lidar.rays(KinematicState(pose=poses[next(it) % len(poses)]))
        cast_rays(scene, o, d)

    def loop():
        o, d = lidar.rays(KinematicState(pose=poses[next(it) % len(poses)]))
        out = np.empty(len(d))
        for i in range(len(d)):
            si = mi_scene.ray_intersect(mi.Ray3f(o=mi.Point3f(*map(float, o)),
                                                 d=mi.Vector3f(*map(float, d[i]))))
            out[i] = si.t[0]
        return out

    import drjit as dr

    def loop_opaque():  # the fair loop: opaque inputs, so one kernel is compiled and reused
        o, d = lidar.rays(KinematicState(pose=poses[next(it) % len(poses)]))
        org = mi.Point3f(*(dr.opaque(mi.Float, float(c)) for c in o))
        out = np.empty(len(d))
        for i in range(len(d)):
            di = mi.Vector3f(*(dr.opaque(mi.Float, float(c)) for c in d[i]))
            out[i] = mi_scene.ray_intersect(mi.Ray3f(o=org, d=di)).t[0]
        return out

    t_scan = per_call(scan, 200)
    t_loop_o = per_call(loop_opaque, 5, warm=1)
    t_raw = per_call(raw, 200)
    t_loop = per_call(loop, 1, warm=0)  # every call recompiles: warming is pointless
    print("LiDAR, 360 beams, 8 x 6 x 3 m box room (median over new poses):")
    print(f"  Lidar2D.measure (one ray_intersect, noise, LaserScan): {t_scan * 1e3:8.3f} ms/scan")
    print(f"  cast_rays only                                       : {t_raw * 1e3:8.3f} ms/scan")
    print(f"  baseline: per-beam ray_intersect loop (naive, literal inputs recompile): "
          f"{t_loop * 1e3:8.1f} ms/scan")
    print(f"  baseline: per-beam ray_intersect loop (opaque inputs, cached kernel) : "
          f"{t_loop_o * 1e3:8.1f} ms/scan")
    print(f"  speed-up of Lidar2D.measure: {t_loop_o / t_scan:6.0f}x vs the cached loop, "
          f"{t_loop / t_scan:6.0f}x vs the naive loop")

    # the radar's target cuboid around the robot encloses its LiDAR: cast_rays casts
    # every beam on from past it (a second ray_intersect); baseline: no target
    from isac_twin.sensing.tracer import SensingTracer, TargetSpec

    here = KinematicState(pose=np.array([4.0, 3.0, 0.0, 0.0, 0.0, 0.3]))
    o, d = lidar.rays(here)
    t_plain = per_call(lambda: cast_rays(scene, o, d), 200)
    tracer = SensingTracer(scene)
    tracer.set_target(TargetSpec("tb", position=np.array([4.0, 3.0, 0.096]), yaw=0.3))
    t_skip = per_call(lambda: cast_rays(scene, o, d), 200)
    tracer.remove_target("tb")
    print(f"  cast_rays inside the robot's own radar target: {t_skip * 1e3:8.3f} ms/scan, "
          f"{t_skip / t_plain:4.2f}x the same scan without a target ({t_plain * 1e3:.3f} ms)")

    r = DiffDriveRobot("burger", (5.5, 3.0, math.pi / 2))
    t_step = per_call(lambda: r.step((0.2, 0.13), 0.05), 5000)
    circ = PurePursuit(CirclePath((4, 3), 1.5), "burger")
    t_circ = per_call(lambda: circ.command(r.state), 5000)
    f8 = PurePursuit(FigureEightPath((4, 3), 4.0), "burger")
    r8 = DiffDriveRobot("burger", (4.0, 3.0, math.pi / 4))
    t_f8 = per_call(lambda: r8.step(f8.command(r8.state), 0.05), 3000)
    t_both = per_call(lambda: r.step(circ(r.state), 0.05), 5000)
    print("kinematics + control, per 50 ms twin step:")
    print(f"  DiffDriveRobot.step               : {t_step * 1e6:8.1f} us")
    print(f"  PurePursuit(circle).command       : {t_circ * 1e6:8.1f} us")
    print(f"  step + PurePursuit(circle) -> Twist: {t_both * 1e6:8.1f} us")
    print(f"  step + PurePursuit(figure-eight)  : {t_f8 * 1e6:8.1f} us")

    bus = Bus()
    agent = RobotAgent("tb", "burger", (5.5, 3.0, 0, 0, 0, math.pi / 2), bus, scene)
    agent.drive(PurePursuit(CirclePath((4, 3), 1.5), "burger"))
    bus.node("rec").subscribe("/tb/scan", "sensor_msgs/msg/LaserScan", lambda m: None)
    k = iter(range(1, 10 ** 9))
    for _ in range(20):
        agent.step(next(k) * 0.05, 0.05)
    ts = []
    for _ in range(400):
        t0 = time.perf_counter()
        agent.step(next(k) * 0.05, 0.05)
        ts.append(time.perf_counter() - t0)
    print(f"RobotAgent.step (f, encoders, odom, IMU, 5.5 Hz LiDAR, controller, bus): "
          f"{np.mean(ts) * 1e3:.3f} ms mean, {np.median(ts) * 1e3:.3f} ms median, "
          f"{np.max(ts) * 1e3:.3f} ms max")
    opt = SensorOptions(camera=True)
    agent_c = RobotAgent("tc", "burger", (5.5, 3.0, 0, 0, 0, math.pi / 2), bus, scene,
                         options=opt)
    cam = agent_c.camera
    t_cam = per_call(lambda: cam.measure(0.0, agent_c.state), 50)
    print(f"DepthCamera.measure 80 x 60 (when enabled): {t_cam * 1e3:.3f} ms")


if __name__ == "__main__":
    main()
