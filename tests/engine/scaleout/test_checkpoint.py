"""engine/scaleout/checkpoint.py: tile files, keys, damaged files."""

from __future__ import annotations

import logging

import numpy as np

from isac_twin.scaleout.checkpoint import TileCheckpoints, checkpoint_dir, checkpoint_key


def _part(n):
    return {"num_paths": np.arange(n * 2, dtype=np.int32).reshape(n, 2),
            "a": np.ones((n, 2, 3), np.complex64)}


def test_tiles_round_trip_and_keys_separate_settings(tmp_path):
    assert checkpoint_dir(tmp_path / "db.npz") == tmp_path / "db.npz.tiles"
    k1 = checkpoint_key({"scene_hash": "a", "spacing": 0.05})
    assert k1 == checkpoint_key({"spacing": 0.05, "scene_hash": "a"})
    assert k1 != checkpoint_key({"scene_hash": "a", "spacing": 0.1})
    ck = TileCheckpoints(tmp_path / "c", k1)
    pts = np.random.default_rng(0).random((5, 3))
    assert ck.load(0, pts) is None
    ck.save(0, pts, [_part(3), _part(2)], {"cap": 7, "retries": 0, "chains": 4})
    parts, meta = ck.load(0, pts)
    assert meta["cap"] == 7 and len(parts) == 2
    np.testing.assert_array_equal(parts[1]["num_paths"], _part(2)["num_paths"])
    assert TileCheckpoints(tmp_path / "c", checkpoint_key({"x": 1})).load(0, pts) is None
    ck.remove()
    assert not (tmp_path / "c").exists()


def test_a_damaged_or_foreign_tile_is_traced_again(tmp_path, caplog):
    ck = TileCheckpoints(tmp_path, "k")
    pts = np.zeros((2, 3))
    ck.save(1, pts, [_part(2)], {})
    assert ck.load(1, pts + 1.0) is None  # another tile's points
    f = next(tmp_path.rglob("tile-000001.npz"))
    f.write_bytes(b"PK\x03\x04 truncated")
    with caplog.at_level(logging.WARNING):
        assert ck.load(1, pts) is None
    assert "tile-000001.npz" in caplog.text and "tracing the tile again" in caplog.text
