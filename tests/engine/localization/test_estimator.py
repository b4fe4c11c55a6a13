"""[localization] in twin.toml: any Twin localizes its robots every step."""

import shutil

import numpy as np
import pytest

from engine.config import ConfigError, load_config
from engine.scene import load_scene
from engine.twin import Twin


def _with_localization(lab, tmp_path, table: str):
    folder = tmp_path / "lab"
    shutil.copytree(lab, folder)
    with open(folder / "twin.toml", "a") as f:
        f.write("\n[localization]\n" + table)
    return folder


def test_bad_localization_tables_are_refused_at_load_naming_the_key(lab, tmp_path):
    cases = {
        'method = "GPS"\n': "localization.method: expected one of MCA, MCA-angles",
        'mode = "radar"\n': "localization.mode: expected one of pilots, tracer",
        'fusion = "ukf"\n': "localization.fusion: expected one of ekf, none",
        "spacing_m = 0\n": "localization.spacing_m: expected a positive number",
        "colour = 1\n": "localization.colour: unknown key",
    }
    for i, (table, msg) in enumerate(cases.items()):
        folder = _with_localization(lab, tmp_path / str(i), table)
        with pytest.raises(ConfigError, match=msg):
            load_config(folder)
    ok = load_config(_with_localization(lab, tmp_path / "ok", 'method = "LOS-fix"\n'))
    assert ok.localization.method == "LOS-fix" and ok.localization.fusion == "ekf"
    assert load_config(lab).localization is None


@pytest.mark.slow
def test_a_twin_with_localization_fills_the_estimate_every_step(lab, tmp_path):
    folder = _with_localization(lab, tmp_path, 'method = "MCA-angles"\nspacing_m = 0.2\n'
                                'snr_db = 20.0\ncache_dir = "cache"\n')
    twin = Twin(load_scene(folder), seed=3, dt=0.25)
    assert twin.localizer is not None and twin.estimators[-1] is twin.localizer
    assert twin.localizer.db.spacing == 0.2 and list((folder / "cache").glob("*.npz"))
    errs = []
    for res in twin.run(6):
        rs = res.robots["robot1"]
        assert rs.estimate is not None and rs.estimate.shape == (3,)
        assert np.isfinite(rs.estimate).all()
        errs.append(np.linalg.norm(rs.estimate[:2] - rs.pose[:2]))  # antenna above base
    # the fused estimate starts at odometry (= truth here) and stays near the truth
    assert max(errs) < 0.4, errs
    # a reset restarts the filter; an opted-out twin has no localizer
    twin.reset()
    assert next(iter(twin.run(1))).robots["robot1"].estimate is not None
    plain = Twin(load_scene(folder), seed=3, localize=False)
    assert plain.localizer is None and plain.estimators == []


@pytest.mark.slow
def test_record_stores_the_twins_fixes(lab, tmp_path):
    """`record` writes every topic of the twin's bus: with [localization] that
    includes /robot1/fingerprint, one per step, decodable from the MCAP file."""
    from engine.record import read_messages, record_twin

    folder = _with_localization(lab, tmp_path, 'method = "LOS-fix"\nspacing_m = 0.4\n'
                                'fusion = "none"\ncache_dir = "cache"\n')
    twin = Twin(load_scene(folder), seed=1, dt=0.25)
    record_twin(twin, 3, tmp_path / "run.mcap")
    fixes = [m for m in read_messages(tmp_path / "run.mcap", ["/robot1/fingerprint"])]
    assert len(fixes) == 3
    est = twin.last.robots["robot1"].estimate
    last = fixes[-1].decode()
    np.testing.assert_allclose(last.estimate, est)
    assert last.source == "LOS-fix/pilots" and last.robot == "robot1"
    assert last.mdp.size > 0
