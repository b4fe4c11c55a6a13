"""engine/calibration/figure.py: the report figure is written from a report dict."""

import math

import numpy as np

from isac_twin.calibration.figure import plot_report


def test_plot_report_writes_a_png(tmp_path):
    rep = {"parameters": [
        {"name": "concrete.permittivity", "initial": 5.24, "final": 6.81,
         "gradient_initial": -0.8},
        {"name": "Cabinet.x", "initial": 0.0, "final": 1e-6, "gradient_initial": 1e-9},
        {"name": "Cabinet.y", "initial": 0.0, "final": -0.02, "gradient_initial": 3.1},
        {"name": "Cabinet.yaw", "initial": 0.0, "final": math.radians(1.2),
         "gradient_initial": 0.4}],
        "unobserved": ["Cabinet.x"], "mismatch_db2": {"initial": 12.0, "final": 0.01},
        "converged": True, "residual_db_per_measurement": [0.1, 0.2, 0.1],
        "residual_db_per_measurement_initial": [3.0, 4.0, 2.5]}
    out = plot_report(rep, tmp_path / "calibration.png")
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    rep.pop("residual_db_per_measurement_initial")  # older reports: after only
    plot_report(rep, tmp_path / "b.png")
    assert np.frombuffer((tmp_path / "b.png").read_bytes()[:4], np.uint8)[1] == ord("P")
