"""engine/localization/fingerprints.py: build, round trip, refusal, off-grid, staleness."""

import dataclasses

import numpy as np
import pytest

from isac_twin import Edit, load_scene
from isac_twin.errors import DatabaseMismatchError
from isac_twin.localization.fingerprints import (
    DB_ARRAYS,
    attach,
    cache_path,
    cached_database,
    load_database,
    save_database,
)

pytestmark = pytest.mark.slow


def test_database_contents(lab_db):
    db = lab_db
    assert set(DB_ARRAYS) <= set(db.arrays)
    n, a, L = db.lengths.shape
    assert a == 2 and L == 16 and db.ap_names == ["AP1", "AP2"]
    free = db.free
    assert free.sum() > 20 and (~free).sum() > 0  # the cabinet's footprint is not free
    # strongest first, and the shortest path at a free point is at least the LOS distance
    i = db.free_indices[0]
    p = db.power[i, 0, : db.num_paths[i, 0]]
    assert np.all(np.diff(p) <= 1e-12)
    los = np.linalg.norm(db.points[i] - np.array([0.1, 2.0, 2.0]))
    assert np.nanmin(db.lengths[i, 0]) == pytest.approx(los, abs=1e-3)
    assert db.height == pytest.approx(0.25)
    assert db.meta["tracer"]["max_depth"] == 2


def test_round_trip_and_cache(lab, lab_db, tmp_path):
    scene = load_scene(lab)
    p = save_database(lab_db, tmp_path / "db.npz").path
    back = load_database(p, scene=scene)
    for k in DB_ARRAYS:
        np.testing.assert_array_equal(back.arrays[k], lab_db.arrays[k])
    assert back.meta == lab_db.meta
    # the cache holds it under the scene hash, frequency and spacing
    assert lab_db.path == cache_path(scene, 0.4, lab_db.path.parent)
    stamp = lab_db.path.stat().st_mtime_ns
    again = cached_database(scene, spacing=0.4, cache_dir=lab_db.path.parent, max_paths=16)
    assert again.path == lab_db.path
    assert lab_db.path.stat().st_mtime_ns == stamp  # read, not rebuilt


@pytest.mark.parametrize("tracer", [{"method": "sbr", "chains": None},
                                    {"chains": {"version": 0}},
                                    {"samples_per_src": 12345},
                                    {"max_depth": 1},
                                    {"refraction": False},
                                    {"chains": {"version": 2, "probe_spacing": 0.5}}],
                         ids=["shoot-and-bounce", "older-chain-reuse", "other-ray-count",
                              "other-depth", "no-refraction", "probe-lattice-v2"])
def test_cache_traced_another_way_is_rebuilt(lab, lab_db, tmp_path, tracer):
    from isac_twin.raytrace.chains import CHAIN_REUSE_VERSION

    scene = load_scene(lab)
    assert lab_db.meta["tracer"]["method"] == "chains"
    assert lab_db.meta["tracer"]["chains"]["version"] == CHAIN_REUSE_VERSION
    old = dataclasses.replace(lab_db, meta={**lab_db.meta,
                                            "tracer": {**lab_db.meta["tracer"], **tracer}})
    path = save_database(old, cache_path(scene, 0.4, tmp_path)).path
    stamp = path.stat().st_mtime_ns
    db = cached_database(scene, spacing=0.4, cache_dir=tmp_path, max_paths=16, verify=0)
    assert path.stat().st_mtime_ns != stamp  # rebuilt and rewritten
    assert db.meta["tracer"]["method"] == "chains"
    assert db.meta["tracer"]["chains"]["version"] == CHAIN_REUSE_VERSION
    np.testing.assert_array_equal(db.arrays["num_paths"], lab_db.arrays["num_paths"])


def test_refuses_other_frequency(lab_db, tmp_path, make_lab):
    other = load_scene(make_lab(tmp_path / "f", frequency_hz=3.5e9), load_sionna=False)
    with pytest.raises(DatabaseMismatchError, match="2.4 GHz, the scene is at 3.5 GHz"):
        load_database(lab_db.path, scene=other)


def test_refuses_edited_room_and_twin_flags_it_stale(lab, lab_db):
    from isac_twin import Twin

    twin = Twin.from_scene(lab, phy=False)
    attach(twin, lab_db)
    assert twin.stale_databases() == []
    twin.apply_edit(Edit("move", "table", position=(1.0, 3.0, 0.375)))
    twin._apply_pending()
    assert twin.stale_databases() == [lab_db.name]
    with pytest.raises(DatabaseMismatchError, match="room was edited"):
        lab_db.check(twin.scene)


def test_refuses_moved_access_point(lab, lab_db):
    scene = load_scene(lab, load_sionna=False)
    with pytest.raises(DatabaseMismatchError, match="access point 'AP2'"):
        lab_db.check(scene, tx_positions={"AP2": (2.0, 0.1, 2.0)})


def test_off_grid_positions(lab_db):
    db = lab_db
    i = db.locate(db.points[db.free_indices[3], :2] + 0.05)
    assert i == db.free_indices[3]
    with pytest.raises(ValueError, match="outside the fingerprint grid"):
        db.locate((10.0, 2.0))
    j = db.locate((10.0, 2.0), outside="nearest")
    assert db.free[j] and db.points[j, 0] > 4.0
    # inside the cabinet: the nearest free point
    k = db.locate((4.5, 0.5))
    assert db.free[k]
    with pytest.raises(ValueError, match="finite"):
        db.locate((np.nan, 1.0))


def test_bad_files(tmp_path, lab_db):
    with pytest.raises(ValueError, match="no such"):
        load_database(tmp_path / "nope.npz")
    (tmp_path / "x.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable"):
        load_database(tmp_path / "x.npz")
    bad = dataclasses.replace(lab_db, meta={**lab_db.meta, "version": 99})
    save_database(bad, tmp_path / "v.npz")
    with pytest.raises(ValueError, match="version 99"):
        load_database(tmp_path / "v.npz")


@pytest.mark.parametrize("damage, reason", [
    (lambda m, a: m.pop("max_paths"), "metadata key 'max_paths' missing"),
    (lambda m, a: m.update(shape="7x9"), "metadata 'shape': expected"),
    (lambda m, a: m.update(ap_names=["AP1"]), "ap_names for"),
    (lambda m, a: a.update(points=a["points"][:10]), "array 'points': shape \\[10, 3\\]"),
    (lambda m, a: a.update(power=a["power"][:, :, :-1]), "array 'power': shape"),
    (lambda m, a: a.update(free=a["free"].astype(np.float32)), "array 'free': dtype"),
])
def test_malformed_cache_is_refused_with_a_reason_and_rebuilt(tmp_path, lab, lab_db, damage,
                                                               reason, caplog):
    """Issue 22: metadata missing a key or of the wrong type gave a traceback; a points
    array cut to 10 rows was accepted. Each is refused naming the file and what is wrong,
    and cached_database rebuilds instead of using it."""
    import logging

    meta, arrays = dict(lab_db.meta), dict(lab_db.arrays)
    damage(meta, arrays)
    scene = load_scene(lab)
    path = cache_path(scene, 0.4, tmp_path)
    save_database(dataclasses.replace(lab_db, meta=meta, arrays=arrays), path)
    with pytest.raises(ValueError, match=reason):
        load_database(path)
    with caplog.at_level(logging.WARNING):
        db = cached_database(scene, spacing=0.4, cache_dir=tmp_path, max_paths=16, verify=0)
    assert any(reason.split(":")[0].strip("\\[") in r.getMessage() and "rebuilding" in
               r.getMessage() for r in caplog.records)
    assert load_database(db.path).arrays["points"].shape == lab_db.arrays["points"].shape


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # numpy's zip
def test_cache_writes_are_atomic(tmp_path, lab_db):
    """A write that fails half-way leaves the old file whole and no temporary behind
    (before, the file was written in place: a crash left half a database)."""
    from isac_twin.utils.npzfile import write_npz

    class DiskFull:  # fails when np.savez reaches it, after the other arrays are written
        def __array__(self, *args, **kwargs):
            raise OSError("no space left on device")

    path = save_database(lab_db, tmp_path / "db.npz").path
    before = path.read_bytes()
    with pytest.raises(OSError, match="no space left"):
        write_npz(path, lab_db.meta, dict(lab_db.arrays, extra=DiskFull()))
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["db.npz"]
