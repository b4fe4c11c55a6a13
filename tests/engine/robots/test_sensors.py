"""Simulated sensors: LiDAR against a box room's geometry, encoders, odometry drift, IMU."""

import math

import numpy as np
import pytest

from isac_twin.robots.kinematics import TICK_RAD, DiffDriveRobot, KinematicState, robot_spec
from isac_twin.robots.sensors import (
    DXL_VELOCITY_UNIT,
    DepthCamera,
    ImuNoise,
    ImuSensor,
    Lidar2D,
    WheelEncoders,
    WheelOdometry,
    cast_rays,
)
from isac_twin.scene.synthetic import box_room

SIZE = (8.0, 6.0, 3.0)  # the bundled lab's extent


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    from isac_twin import load_scene

    return load_scene(box_room(tmp_path_factory.mktemp("room"), size=SIZE))


def box_distance(o, d, size=SIZE):
    """Exact distance from o (inside) along unit d to the box [0, size]."""
    t = np.full(len(d), np.inf)
    for ax in range(3):
        with np.errstate(divide="ignore", invalid="ignore"):
            for wall in (0.0, size[ax]):
                ti = (wall - o[ax]) / d[:, ax]
                t = np.where((ti > 0) & np.isfinite(ti), np.minimum(t, ti), t)
    return t


def state_at(pose):
    return KinematicState(pose=np.asarray(pose, float))


@pytest.mark.parametrize("pose", [
    (4.0, 3.0, 0.0, 0.0, 0.0, 0.0),
    (1.3, 4.7, 0.0, 0.0, 0.0, 2.1),
    (6.9, 0.8, 0.0, 0.0, 0.0, -0.77),
    (3.0, 2.0, 0.0, 0.0, 0.12, 0.4),   # pitched: some beams reach floor/ceiling
    (5.0, 3.5, 0.0, -0.2, 0.0, 1.0),   # rolled
])
def test_lidar_matches_the_box_room_within_1mm(room, pose):
    # grazing beams (cos incidence < 0.05) are dropped by design; keep them for geometry
    lidar = Lidar2D(room, "burger", range_noise_rel=0.0, range_noise_abs=0.0,
                    min_cos_incidence=0.0)
    st = state_at(pose)
    scan = lidar.measure(0.0, st)
    assert len(scan.ranges) == 360 and len(scan.intensities) == 360
    assert scan.angle_increment == pytest.approx(2 * math.pi / 360)
    assert scan.angle_max == pytest.approx(math.pi - scan.angle_increment)
    origin, dirs = lidar.rays(st)
    want = box_distance(origin, dirs)
    assert np.all(np.isfinite(scan.ranges))
    assert np.max(np.abs(scan.ranges - want)) < 1e-3
    assert np.all((scan.intensities > 0) & (scan.intensities <= 63))


def test_lidar_beam_zero_points_backwards_and_frames(room):
    # beam i at angle -pi + i deg in base_scan: beam 180 looks forward (+x)
    lidar = Lidar2D(room, "burger", range_noise_rel=0.0, range_noise_abs=0.0)
    scan = lidar.measure(1.5, state_at((4.0, 3.0, 0, 0, 0, 0)))
    mx = lidar.spec.lidar_mount[0]
    assert scan.ranges[180] == pytest.approx(8.0 - 4.0 - mx, abs=1e-3)
    assert scan.ranges[0] == pytest.approx(4.0 + mx, abs=1e-3)
    assert scan.ranges[270] == pytest.approx(3.0, abs=1e-3)  # +90 deg: left wall y = 6
    assert scan.header.frame_id == "base_scan" and scan.header.stamp == 1.5


def test_lidar_range_limits_and_noise(room):
    st = state_at((4.0, 3.0, 0, 0, 0, 0))
    short = Lidar2D(room, "burger", range_max=3.5, range_noise_rel=0.0, range_noise_abs=0.0)
    scan = short.measure(0.0, st)
    far = np.isinf(scan.ranges)
    assert far.any() and (~far).any()
    assert np.all(scan.intensities[far] == 0)
    assert np.all(scan.ranges[~far] <= 3.5)
    # a robot against the wall: beams shorter than range_min read inf
    near = Lidar2D(room, "burger", range_noise_rel=0.0, range_noise_abs=0.0)
    s2 = near.measure(0.0, state_at((7.9, 3.0, 0, 0, 0, 0)))
    assert np.isinf(s2.ranges[180]) and np.isfinite(s2.ranges[0])
    exact = Lidar2D(room, "burger", range_noise_rel=0.0, range_noise_abs=0.0).measure(0.0, st)
    noisy = Lidar2D(room, "burger", range_noise_rel=0.01, range_noise_abs=0.0, seed=3)
    res = np.concatenate([(noisy.measure(0.0, st).ranges - exact.ranges) / exact.ranges
                          for _ in range(5)])
    assert res.std() == pytest.approx(0.01, rel=0.15)
    drop = Lidar2D(room, "burger", dropout=0.3, seed=1).measure(0.0, st)
    assert 0.2 < np.isinf(drop.ranges).mean() < 0.4


def test_lidar_rate(room):
    lidar = Lidar2D(room, "burger")
    n = sum(lidar.poll(k * 0.05, state_at((4, 3, 0, 0, 0, 0))) is not None for k in range(40))
    assert n == 11  # 5.5 Hz over 2 s


@pytest.mark.parametrize("kind", ["lidar", "camera"])
def test_skipped_scans_leave_later_scans_unchanged(room, kind):
    """Issue 19: ``skip`` advances the schedule and the noise stream as a poll
    does, so the scans polled after some were skipped equal those of a sensor
    that rendered every one (dropout and range noise on)."""
    def make():
        if kind == "lidar":
            return Lidar2D(room, "burger", dropout=0.2, range_noise_rel=0.01, seed=7)
        return DepthCamera(room, "burger", enabled=True, depth_noise_rel=0.02, seed=7)

    every, skipping = make(), make()
    poses = [(4.0 + 0.1 * k, 3.0, 0, 0, 0, 0.05 * k) for k in range(30)]
    got, want, skipped = [], [], 0
    for k, pose in enumerate(poses):
        t, st = 0.05 * k, state_at(pose)
        m = every.poll(t, st)
        if k < 15:
            skipped += skipping.skip(t, st)
            continue
        g = skipping.poll(t, st)
        assert (g is None) == (m is None)
        if m is not None:
            got.append(g.ranges if kind == "lidar" else g.data)
            want.append(m.ranges if kind == "lidar" else m.data)
    assert skipped == 4 and len(got) >= 3  # 5.5 / 5 Hz: due on 4 of the first 15 steps
    for g, m in zip(got, want):
        np.testing.assert_array_equal(g, m)
    assert not DepthCamera(room, "burger").skip(0.0, state_at(poses[0]))  # off: nothing due


def test_cast_rays_misses_are_inf(room):
    t, valid, _ = cast_rays(room, np.array([50.0, 50.0, 50.0]), np.array([[0.0, 0.0, 1.0]]))
    assert not valid[0] and np.isinf(t[0])


def test_depth_camera_off_by_default_and_exact_when_on(room):
    st = state_at((4.0, 3.0, 0, 0, 0, 0))
    off = DepthCamera(room, "burger")
    assert off.poll(0.0, st) is None
    cam = DepthCamera(room, "burger", enabled=True, depth_noise_rel=0.0)
    img = cam.poll(0.0, st)
    assert img.encoding == "16UC1" and img.data.shape == (60, 80) and img.data.dtype == np.uint16
    origin = st.to_world(cam.mount)
    want = box_distance(origin, cam._dirs_local) * cam._z_body  # depth along the optical axis
    got = img.data.reshape(-1).astype(float) / 1000
    assert np.abs(got - want).max() <= 0.0006  # mm rounding + float32
    # upper rows see the x = 8 wall at constant depth, lower rows the floor
    assert img.data[5, 40] == round((8.0 - 4.0 - cam.mount[0]) * 1000)
    assert img.data[-1, 40] < img.data[5, 40]


# ---------------------------------------------------------------- encoders and odometry


def drive_circle(model="burger", seconds=60.0, dt=0.05, v=0.2, w=0.25):
    r = DiffDriveRobot(model, (4.0, 1.5, 0.0))
    for _ in range(int(seconds / dt)):
        yield r.step((v, w), dt)


def test_encoders_quantise_to_ticks_and_dxl_units():
    enc = WheelEncoders(slip_std=0.0, tick_jitter=0.0)
    for st in drive_circle(seconds=3.0):
        msg = enc.measure(st.t, st)
    assert np.array_equal(enc.ticks, np.round(st.wheel_pos / TICK_RAD).astype(np.int64))
    assert np.all(np.abs(msg.position - st.wheel_pos) <= TICK_RAD / 2 + 1e-12)
    assert np.all(np.abs(msg.velocity - st.wheel_vel) <= DXL_VELOCITY_UNIT / 2 + 1e-12)
    assert msg.name == ["wheel_left_joint", "wheel_right_joint"]


def odometry_error(**kw):
    enc_kw = {k: kw.pop(k) for k in ("slip_std", "tick_jitter", "seed") if k in kw}
    enc = WheelEncoders(**enc_kw)
    odo = None
    for st in drive_circle():
        js = enc.poll(st.t, st)
        if js is None:
            continue
        if odo is None:
            odo = WheelOdometry("burger", initial_pose=(4.0, 1.5, 0.0), **kw)
            # start from the first reading's pose
            odo.pose[:] = (st.x, st.y, st.yaw)
        msg = odo.update(js)
    p = msg.pose.position
    return math.hypot(p[0] - st.x, p[1] - st.y)


def test_odometry_is_exact_when_calibrated_and_drifts_when_not():
    exact = odometry_error(slip_std=0.0, tick_jitter=0.0, radius_scale=(1, 1),
                           separation_scale=1.0)
    assert exact < 0.005  # 12 m of driving: only tick quantisation
    bigger_wheel = odometry_error(slip_std=0.0, tick_jitter=0.0, radius_scale=(1.02, 1.0),
                                  separation_scale=1.0)
    assert bigger_wheel > 0.1  # 2 % on one wheel: heading drifts, position follows
    noisy = [odometry_error(seed=s) for s in range(3)]
    assert all(e > exact for e in noisy)
    assert odometry_error(seed=5) == odometry_error(seed=5)


# ---------------------------------------------------------------- IMU


def test_imu_reads_gravity_and_rotation_without_noise():
    imu = ImuSensor("burger", noise=ImuNoise.off())
    m = imu.measure(0.0, state_at((1, 1, 0, 0, 0, 0.3)))
    assert m.linear_acceleration == pytest.approx([0, 0, 9.80665])
    assert m.angular_velocity == pytest.approx([0, 0, 0])
    # tilted by pitch: gravity shows on body x like a real accelerometer
    m = imu.measure(0.1, state_at((1, 1, 0, 0, 0.1, 0)))
    assert m.linear_acceleration == pytest.approx([-9.80665 * math.sin(0.1), 0,
                                                   9.80665 * math.cos(0.1)])
    # turning at constant v, w: centripetal v w on y, lever arm -w^2 r_x on x
    st = state_at((1, 1, 0, 0, 0, 0))
    st.v, st.w, st.accel = 0.2, 0.5, np.array([0.0, 0.1, 0.0])
    m = imu.measure(0.2, st)
    rx = robot_spec("burger").imu_mount[0]
    assert m.linear_acceleration == pytest.approx([-0.25 * rx, 0.1, 9.80665])
    assert m.angular_velocity == pytest.approx([0, 0, 0.5])


def test_imu_noise_bias_and_determinism():
    noise = ImuNoise(gyro_noise=1e-3, gyro_bias_rw=0.0, gyro_bias0=0.01, accel_noise=0.0,
                     accel_bias_rw=0.0, accel_bias0=0.0)
    imu = ImuSensor("burger", rate_hz=100.0, noise=noise, seed=4)
    st = state_at((0, 0, 0, 0, 0, 0))
    g = np.array([imu.measure(k / 100, st).angular_velocity for k in range(2000)])
    assert g.mean(axis=0) == pytest.approx(imu.gyro_bias, abs=1.2e-3)  # 5 sigma
    assert g[:, 2].std() == pytest.approx(1e-3 * 10, rel=0.1)  # density * sqrt(rate)
    # the yaw it reports drifts with the bias, as a gyro-only heading does
    yaw = math.atan2(*imu.measure(20.0, st).orientation[[2, 3]]) * 2
    assert yaw == pytest.approx(imu.gyro_bias[2] * 20.0, abs=0.01)
    a = [ImuSensor(seed=9).measure(k * 0.05, st).linear_acceleration for k in range(5)]
    b = [ImuSensor(seed=9).measure(k * 0.05, st).linear_acceleration for k in range(5)]
    c = [ImuSensor(seed=10).measure(k * 0.05, st).linear_acceleration for k in range(5)]
    assert np.array_equal(a, b) and not np.allclose(a, c)


# --------------------------------------------------------------------------- with sensing on


def _recorded_returns(tmp_path, sensing: bool, steps: int = 14) -> dict[str, list[int]]:
    """Per scan / depth image of a recording of the shipped lab: its count of
    finite beams / valid pixels, with the radar (``[[sensing]]``) on or off."""
    from isac_twin import Twin, bundled_scene_dir, load_scene
    from isac_twin.robots import SensorOptions
    from isac_twin.transport.record import read_messages, record_twin

    twin = Twin(load_scene(bundled_scene_dir("aces_lab")), sensors=SensorOptions(camera=True),
                sensing=sensing, sync_sensing=True, localize=False)
    out = tmp_path / f"lab_{sensing}.mcap"
    record_twin(twin, steps, out)
    counts: dict[str, list[int]] = {"scan": [], "depth": []}
    for m in read_messages(out, ["/robot1/scan", "/robot1/camera/depth"]):
        msg = m.decode()
        if m.topic.endswith("scan"):
            counts["scan"].append(int(np.isfinite(np.asarray(msg.ranges)).sum()))
        else:
            counts["depth"].append(int((np.asarray(msg.data) > 0).sum()))
    return counts


@pytest.mark.slow
def test_radar_targets_never_blind_the_robots_own_sensors(tmp_path):
    """The radar puts a target cuboid around each robot into the scene; the
    robot's LiDAR and depth camera sit inside it. Every scan and depth image
    of a recording of the lab as shipped returns what the run without
    ``[[sensing]]`` returns (within 2 beams / pixels): neither the robot's own
    target nor its body occludes them."""
    on = _recorded_returns(tmp_path, True)
    off = _recorded_returns(tmp_path, False)
    assert len(on["scan"]) == len(off["scan"]) >= 3
    assert len(on["depth"]) == len(off["depth"]) >= 3
    assert min(off["scan"]) >= 350 and min(off["depth"]) > 0.9 * 80 * 60
    for key in ("scan", "depth"):
        for i, (a, b) in enumerate(zip(on[key], off[key])):
            assert abs(a - b) <= 2, f"{key} {i}: {a} returns with sensing, {b} without"
