"""addon/radiomap_view.py under headless bpy: the map plane, its image, the legend and the
labels from a ``radiomap`` message; and end to end from ``isac-twin serve --radiomap``."""

from __future__ import annotations

import time

import pytest

bpy = pytest.importorskip("bpy")

pytestmark = pytest.mark.blender


@pytest.fixture
def scene(blank_scene):
    from addon import live_view

    p = blank_scene.isac_live
    p.radiomap_layer, p.radiomap_layers, p.show_radiomap = "", "", True
    yield bpy.context.scene
    live_view.clear(bpy.context.scene)


def _msg():
    # 2 rows x 3 columns, cell 0.5 m; cell (iy=0, ix=1) has no value
    return {"type": "radiomap", "scene_hash": "h1", "height": 0.25, "origin": [0.25, 0.25],
            "cell_size": 0.5, "shape": [2, 3],
            "layers": [{"name": "AP1", "unit": "dBm", "vmin": -80.0, "vmax": -20.0,
                        "values": [-20.0, None, -50.0, -80.0, -35.0, -65.0]},
                       {"name": "sinr", "unit": "dB", "vmin": 0.0, "vmax": 40.0,
                        "values": [40.0, None, 20.0, 0.0, 10.0, 30.0]}],
            "tx": [{"name": "AP1", "position": [0.0, 0.5, 2.0]}]}


def _pixel(img, ix, iy):
    w = img.size[0]
    px = list(img.pixels)
    k = 4 * (iy * w + ix)
    return px[k:k + 4]


def test_plane_image_legend_and_labels(scene):
    from addon import legend
    from addon import radiomap_view as rv
    from addon.live_view import LiveView

    view = LiveView()
    rv.apply_radiomap(scene, _msg(), view)
    p = scene.isac_live
    assert view.radiomap["scene_hash"] == "h1"
    assert p.radiomap_layer == "AP1" and p.radiomap_layers == "AP1,sinr"  # no 'best' here
    plane = bpy.data.objects[rv.MAP]
    xs = sorted({round(v.co.x, 6) for v in plane.data.vertices})
    ys = sorted({round(v.co.y, 6) for v in plane.data.vertices})
    assert xs == [0.0, 1.5] and ys == [0.0, 1.0]
    assert {round(v.co.z, 6) for v in plane.data.vertices} == {0.25}
    img = bpy.data.images[rv.MAP]
    assert tuple(img.size) == (3, 2)
    assert _pixel(img, 0, 0) == pytest.approx([*rv.map_color(1.0), 1.0], abs=3e-3)   # -20 dBm
    assert _pixel(img, 0, 1) == pytest.approx([*rv.map_color(0.0), 1.0], abs=3e-3)   # -80 dBm
    assert _pixel(img, 1, 1) == pytest.approx([*rv.map_color(0.75), 1.0], abs=3e-3)  # -35
    assert _pixel(img, 1, 0)[3] == 0.0                                              # no ray
    assert bpy.data.objects[rv.LEGEND].location is not None
    texts = {n: bpy.data.objects[rv.LEGEND + n].data.body for n in
             ("_Title", "_Max", "_Mid", "_Min")}
    assert texts == {"_Title": "AP1 RSS (dBm)", "_Max": "-20", "_Mid": "-50", "_Min": "-80"}
    legend_y = max(v.co.y for v in bpy.data.objects[rv.LEGEND].data.vertices)
    assert legend_y < 0.0                                                # in front of the map
    assert tuple(bpy.data.images[rv.LEGEND].size) == (legend.BAR_PIXELS, 1)
    assert bpy.data.objects["ISAC_Live_AP_AP1_Label"].data.body == "AP1"
    assert list(bpy.data.objects["ISAC_Live_AP_AP1"].location)[:2] == pytest.approx([0, 0.5])

    # another layer: same objects, new colours and scale
    assert rv.select_layer(scene, view, "sinr") == "sinr" and p.radiomap_layer == "sinr"
    assert bpy.data.objects[rv.LEGEND + "_Title"].data.body == "sinr SINR (dB)"
    assert bpy.data.objects[rv.LEGEND + "_Max"].data.body == "40"
    assert _pixel(img, 2, 0) == pytest.approx([*rv.map_color(0.5), 1.0], abs=3e-3)
    with pytest.raises(KeyError, match=r"no layer 'AP7' \(layers: AP1, sinr\)"):
        rv.select_layer(scene, view, "AP7")
    with pytest.raises(KeyError, match="no radio map received yet"):
        rv.select_layer(scene, LiveView(), "AP1")

    # the panel's toggle hides map and legend in viewport and render (AP labels stay)
    p.show_radiomap = False
    objs = rv.radiomap_objects(scene)
    assert len(objs) == 6 and all(o.hide_render and o.hide_viewport for o in objs)
    rv.apply_radiomap(scene, dict(_msg(), scene_hash="h2"), view)        # a recomputed map
    assert all(o.hide_render for o in rv.radiomap_objects(scene))        # stays hidden
    assert not bpy.data.objects["ISAC_Live_AP_AP1_Label"].hide_render
    p.show_radiomap = True
    assert not any(o.hide_render for o in rv.radiomap_objects(scene))
    assert bpy.data.objects[rv.MAP]["isac_scene_hash"] == "h2"


def test_a_resized_map_replaces_the_image(scene):
    from addon import radiomap_view as rv
    from addon.live_view import LiveView

    view = LiveView()
    rv.apply_radiomap(scene, _msg(), view)
    m = _msg()
    m["shape"] = [1, 2]
    for lay in m["layers"]:
        lay["values"] = lay["values"][:2]
    rv.apply_radiomap(scene, m, view)
    assert tuple(bpy.data.images[rv.MAP].size) == (2, 1)
    xs = sorted({round(v.co.x, 6) for v in bpy.data.objects[rv.MAP].data.vertices})
    assert xs == [0.0, 1.0]


@pytest.mark.slow
def test_engine_streams_a_map_that_blender_shows(scene, tmp_path):
    from addon import live
    from addon import radiomap_view as rv
    from isac_twin.scene.synthetic import two_ap_lab

    folder = two_ap_lab(tmp_path / "lab", tracer={"samples_per_src": 10000, "max_depth": 1})
    eng = live.EngineProcess("", str(folder), ("--rate", "0", "--paused", "--radiomap", "0.5",
                                               "--radiomap-samples", "50000"))
    s = live.LiveSession(scene, engine=eng)
    try:
        end = time.monotonic() + 60
        while time.monotonic() < end and not s.applied["radiomap"]:
            s.tick()
            time.sleep(0.02)
        assert s.applied["radiomap"] == 1, eng.log_tail()
        p = scene.isac_live
        assert p.radiomap_layers == "AP1,AP2,best,sinr" and p.radiomap_layer == "best"
        assert tuple(bpy.data.images[rv.MAP].size) == (13, 9)  # 6.2 x 4.2 m at 0.5 m
        assert bpy.data.objects[rv.LEGEND + "_Title"].data.body == "best server RSS (dBm)"
        assert {"ISAC_Live_AP_AP1_Label", "ISAC_Live_AP_AP2_Label"} <= set(bpy.data.objects.keys())
    finally:
        s.close()
