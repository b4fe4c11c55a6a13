"""Rooms shared by the calibration tests.

* :func:`cabinet_room`: a 5 x 4 x 3 m concrete room with a metal cabinet, one AP; the
  "measurements" (:func:`measure`) come from plain Sionna RT (its own PathSolver and
  Paths.cfr, no calibration code) on a copy of it with one known change;
* :func:`lap_room`: the same room with a robot driving a lap, and :func:`recording`,
  12 twin steps in its brick version recorded with compact CSI (the recorder's real
  MCAP, the twin's own tracer and PHY).
"""

import numpy as np
import pytest

from isac_twin import load_scene
from isac_twin.calibration import Calibrator, Measurements, Parameter, SolverSettings
from isac_twin.scene import synthetic as syn

FREQ = 2.4e9
OFFSETS = np.linspace(-40e6, 40e6, 6)  # 6 subcarriers over 80 MHz
TX = (0.5, 0.5, 2.0)
RX = np.array([(2.0, 2.0, 0.3), (1.2, 3.0, 0.5), (3.8, 1.2, 0.4), (2.6, 3.2, 0.3)])
SETTINGS = SolverSettings(max_depth=2, samples_per_src=4000, seed=1)
CABINET = ((3.0, 2.5, 0.0), (3.6, 3.0, 1.5))


def cabinet_room(folder, cabinet_shift=(0.0, 0.0), cabinet_yaw=0.0):
    """The cabinet room's folder, the cabinet's mesh shifted by ``cabinet_shift`` (m) and
    turned by ``cabinet_yaw`` (rad)."""
    lo, hi = (np.array(c, float) for c in CABINET)
    d = np.array([*cabinet_shift, 0.0])
    objs = syn.room_objects((5.0, 4.0, 3.0),
                            {"Cabinet": (lo + d, hi + d, "metal", 0.002)})
    if cabinet_yaw:  # the mesh itself turned about its centre (not the calibration's code)
        cab = objs[-1]
        c = 0.5 * (lo + hi)
        cs, sn = np.cos(cabinet_yaw), np.sin(cabinet_yaw)
        x, y = cab.vertices[:, 0] - c[0], cab.vertices[:, 1] - c[1]
        cab.vertices = np.column_stack([c[0] + cs * x - sn * y, c[1] + sn * x + cs * y,
                                        cab.vertices[:, 2]])
    devs = [syn.SyntheticDevice("AP1", "access_point", "tx", TX),
            syn.SyntheticDevice("robot1", "robot", "rx", (2.0, 2.0, 0.0),
                                extra=dict(syn.ROBOT_EXTRA))]
    return syn.write_scene_folder(folder, objs, devs, [("AP1", "robot1")], frequency_hz=FREQ)


def measure(folder, permittivity_factor=1.0):
    """The reference channel [N, K]: Sionna's own solver on the changed room."""
    import mitsuba as mi
    import sionna.rt as rt

    sc = load_scene(folder).sionna
    if permittivity_factor != 1.0:
        for m in sc.radio_materials.values():
            if m.itu_type == "concrete":
                eps = float(m.relative_permittivity.numpy()[0])
                m.frequency_update_callback = None
                m.relative_permittivity = eps * permittivity_factor
    sc.tx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    sc.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    sc.add(rt.Transmitter("tx", position=mi.Point3f(*TX)))
    for i, p in enumerate(RX):
        sc.add(rt.Receiver(f"rx{i}", position=mi.Point3f(*map(float, p))))
    paths = rt.PathSolver()(sc, max_depth=2, samples_per_src=100000, synthetic_array=True,
                            los=True, specular_reflection=True, diffuse_reflection=False,
                            refraction=True, seed=7)
    h = paths.cfr(frequencies=OFFSETS, normalize_delays=False, out_type="numpy")
    return Measurements(TX, RX, OFFSETS, np.asarray(h).reshape(len(RX), len(OFFSETS)))


def arrays_case(folder, settings=SETTINGS):
    """4 positions, a 2x2 AP turned (0.4, 0.1, 0) rad, 1x2 receivers turned differently."""
    n = len(RX)
    ori = np.column_stack([np.linspace(0.3, 2.0, n), np.zeros(n), np.zeros(n)])
    meas = Measurements(TX, RX, OFFSETS, np.ones((n, len(OFFSETS), 2, 4)),
                        tx_array=(2, 2, 0.5, 0.5), rx_array=(1, 2, 0.5, 0.5),
                        tx_orientation=(0.4, 0.1, 0.0), rx_orientations=ori)
    return Calibrator(load_scene(cabinet_room(folder)), meas,
                      [Parameter("permittivity", "concrete"), Parameter("x", "Cabinet"),
                       Parameter("yaw", "Cabinet")], settings)


def lap_room(folder, wall, cabinet_shift=(0.0, 0.0), second_ap=False,
             tracer=(("samples_per_src", 20000), ("max_depth", 2))):
    """The lap room's folder: walls of ITU material ``wall``, the cabinet shifted by
    ``cabinet_shift`` (m), a second AP beyond the cabinet with ``second_ap``."""
    dx, dy = cabinet_shift
    objs = syn.room_objects((5.0, 4.0, 3.0),
                            {"Cabinet": ((3.0 + dx, 2.5 + dy, 0.0), (3.6 + dx, 3.0 + dy, 1.5),
                                         "metal", 0.002)},
                            material=wall)
    path = {"kind": "polyline", "closed": True,
            "waypoints": [[1.5, 1.5], [3.5, 1.5], [3.5, 2.2], [1.5, 2.2]]}
    devs = [syn.SyntheticDevice("AP1", "access_point", "tx", (0.5, 0.5, 2.0), rows=2, cols=2),
            syn.SyntheticDevice("robot1", "robot", "rx", (1.5, 2.0, 0.0), cols=2,
                                extra={**syn.ROBOT_EXTRA, "path": path})]
    links = [("AP1", "robot1")]
    if second_ap:  # on the other side of the cabinet's x-facing faces
        devs.append(syn.SyntheticDevice("AP2", "access_point", "tx", (2.0, 3.8, 2.5)))
        links.append(("AP2", "robot1"))
    return syn.write_scene_folder(folder, objs, devs, links, frequency_hz=FREQ,
                                  num_subcarriers=256, subcarrier_spacing_hz=312500.0,
                                  tracer=dict(tracer))


@pytest.fixture(scope="session")
def recording(tmp_path_factory):
    """12 twin steps in the brick room, recorded with compact CSI."""
    from isac_twin import Twin
    from isac_twin.transport.record import record_twin

    d = tmp_path_factory.mktemp("calrun")
    real = lap_room(d / "real", "brick")
    record_twin(Twin.from_scene(real), 12, d / "run.mcap")
    return d, real, d / "run.mcap"
