"""The deployment loop and the case-study outputs on the small lab."""

import json
from pathlib import Path

import numpy as np
import pytest

from engine.localization.deployment import (Deployment, DeploymentSettings, errors,
                                            perturb_scene, summarize)
from engine.scene import load_scene

pytestmark = pytest.mark.slow

PATH = {"kind": "circle", "centre": [2.5, 2.0], "radius": 0.8}


@pytest.mark.parametrize("settings", [
    DeploymentSettings(source="twin", mode="tracer", path=PATH),
    DeploymentSettings(source="real", mode="pilots", snr_db=20.0, closed_loop=True,
                       method="PDP", path=PATH),
    DeploymentSettings(source="real", mode="pilots", snr_db=20.0, closed_loop=True,
                       method="MCA-angles", fusion="ekf", path=PATH),
], ids=["paper", "closed-loop-pilots", "closed-loop-ekf-angles"])
def test_loop_produces_four_positions_and_finite_errors(lab, lab_db, settings):
    dep = Deployment(lab, lab_db, settings, seed=1, dt=0.25, rate_every=2)
    recs = dep.run(3)
    assert len(recs) == 3
    for r in recs:
        for k in ("truth", "odometry", "twin", "estimate"):
            v = getattr(r, k)
            assert v.shape == (2,) and np.isfinite(v).all(), k
    assert np.isfinite(recs[0].rates_bps["AP1->robot1"])
    assert np.isnan(recs[1].rates_bps["AP1->robot1"])  # rate_every=2
    # beside Shannon, the modem's rate through the MCS table (engine/phy/mcs.py)
    assert 0 < recs[0].rates_bps["AP1->robot1 [MCS]"] < recs[0].rates_bps["AP1->robot1"]
    err = errors(recs)
    for k, v in err.items():
        assert np.isfinite(v).all(), k
    # modelling error = twin vs odometry: the calibration offset, a few cm
    assert err["modelling"].max() < 0.2
    s = summarize(err["positioning"])
    assert set(s) == {"rmse", "median", "p90", "max"}
    assert dep.twin.stale_databases() == []
    assert dep.reality.scene.content_hash() != dep.twin.scene.content_hash()


def test_perturbation_is_seeded_and_keeps_the_shell(lab):
    a, b = load_scene(lab), load_scene(lab)
    pa, pb = perturb_scene(a, seed=3), perturb_scene(b, seed=3)
    assert pa == pb and a.content_hash() == b.content_hash()
    assert set(pa["moved"]) == {"cabinet", "table"}
    assert pa["material"] == ["table", "wood", "metal"]
    assert max(abs(v) for m in pa["moved"].values() for v in m[:2]) < 0.2


def test_case_study_writes_metrics(lab, lab_db, tmp_path):
    from engine.casestudy import METRICS_KEYS, run_case_study

    lines = []
    m = run_case_study(lab, tmp_path / "out", spacing=0.4, steps=2, cache_dir=lab_db.path.parent,
                       table_points=2, snrs=(30.0,), rate_every=1, report=lines.append,
                       path=PATH, closed_loop=False)
    data = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert set(METRICS_KEYS) <= set(data)
    assert data["closed_loop"] is None
    for run in ("paper_mode",):
        for k in ("positioning", "modelling", "estimate_vs_truth", "odometry_vs_truth"):
            assert set(data[run]["errors"][k]) == {"rmse", "median", "p90", "max"}
    assert {r["method"] for r in data["table"]} == {"MCA", "MCA-angles", "LOS-fix", "kNN-CSI",
                                                   "PDP"}
    assert {r["room"] for r in data["table"]} == {"twin", "perturbed"}
    for f in data["figures"]:
        assert Path(f).exists()
    assert (tmp_path / "out" / "table.md").read_text().count("| MCA |") == 2
    assert any("paper mode" in x for x in lines)
    assert m["paper_reference"]["max_positioning_m"] == 0.16


def test_deployment_settings_refuse_unknown_method_and_fusion():
    with pytest.raises(ValueError, match="method: expected one of 'MCA', 'MCA-angles'"):
        DeploymentSettings(method="MCA+")
    with pytest.raises(ValueError, match="fusion: expected 'blend' or 'ekf'"):
        DeploymentSettings(fusion="ukf")
