"""engine/live/radiomap_feed.py: radio maps on the live link, from a real Twin over a real
socket; an edit from the viewer makes the next step publish a new map."""

from __future__ import annotations

import math

import numpy as np
import pytest

from isac_twin.live.radiomap_feed import RadioMapFeed, radiomap_message
from isac_twin.radiomap.radio_map import radio_map_from_gain


def test_message_layout_and_no_coverage_as_null(wire):
    gain = np.array([[[1e-6, 0.0, 1e-7], [1e-8, 1e-6, 1e-6]],
                     [[1e-7, 0.0, 1e-6], [1e-8, 1e-7, 1e-9]]])     # [S=2, ny=2, nx=3]
    rm = radio_map_from_gain(gain, ["AP1", "AP2"], origin=(0.25, 0.5), cell_size=0.5,
                             height=0.2, tx_positions=[[0, 0, 2], [3, 0, 2]],
                             tx_power_dbm=[20.0, 20.0], noise_dbm=-90.0,
                             meta={"scene_hash": "h"})
    msg = radiomap_message(rm, step=7)
    assert wire.validate(msg) is None
    assert [lay["name"] for lay in msg["layers"]] == ["AP1", "AP2", "best", "sinr"]
    ap1 = msg["layers"][0]
    # row-major: value k is cell (iy, ix) = divmod(k, nx)
    assert ap1["values"][0] == pytest.approx(-40.0) and ap1["values"][1] is None
    assert ap1["values"][4] == pytest.approx(-40.0) and msg["shape"] == [2, 3]
    assert ap1["vmax"] == -40.0 and ap1["vmax"] - ap1["vmin"] == 60.0
    assert msg["layers"][2]["values"][2] == pytest.approx(-40.0)   # AP2 serves cell (0, 2)
    assert msg["step"] == 7 and msg["tx"][1] == {"name": "AP2", "position": [3.0, 0.0, 2.0]}
    assert len(wire.encode(msg)) < 2000


def test_bad_cell_size_is_refused():
    with pytest.raises(ValueError, match="cell size: expected a positive number"):
        RadioMapFeed(object(), cell_size=-0.25)


@pytest.mark.slow
def test_edit_recomputes_and_streams_a_new_map(tmp_path, raw_viewer, wire):
    from isac_twin import Twin
    from isac_twin.live.server import LiveServer
    from isac_twin.scene.synthetic import two_ap_lab

    folder = two_ap_lab(tmp_path / "lab", furniture={"desk": ((2.0, 2.5, 0.0), (3.5, 3.5, 0.75))},
                        tracer={"samples_per_src": 10000, "max_depth": 1})
    twin = Twin.from_scene(folder, seed=0)
    feed = RadioMapFeed(twin, cell_size=0.5, samples_per_tx=50_000)
    first = feed.prime()
    srv = LiveServer(twin, "127.0.0.1", 0, rate_hz=0, running=False, on_step=feed)
    feed.publish = srv.publish
    srv.start()
    try:
        srv.publish(first)
        v = raw_viewer(srv.address)
        v.hello()
        got = v.until(lambda m: m["type"] == "radiomap")     # joined after it was published
        assert got == first and got["scene_hash"] == twin.scene.content_hash()
        assert got["shape"] == [9, 13]                        # 6.2 x 4.2 m box at 0.5 m
        v.send(wire.command("step"))
        v.until(lambda m: m["type"] == "state")
        assert feed.computed == 1                             # nothing changed: no new map
        v.send(wire.edit("move", "desk", position=(4.5, 1.0, 0.375)))
        v.send(wire.command("step"))
        new = v.until(lambda m: m["type"] == "radiomap")
        assert feed.computed == 2 and new["scene_hash"] == twin.scene.content_hash()
        assert new["scene_hash"] != first["scene_hash"] and new["step"] == 1
        old_ap1 = np.array([math.nan if x is None else x for x in first["layers"][0]["values"]])
        new_ap1 = np.array([math.nan if x is None else x for x in new["layers"][0]["values"]])
        assert np.nanmax(np.abs(new_ap1 - old_ap1)) > 3.0     # the desk's shadow moved
    finally:
        srv.stop()
