"""The add-on's live view and client pieces, headless bpy, no engine process."""

from __future__ import annotations

import math
import socket
import threading
import time

import pytest

bpy = pytest.importorskip("bpy")

pytestmark = pytest.mark.blender


@pytest.fixture
def scene(blank_scene):
    return blank_scene


def _paths(n_links=2, per_link=3):
    links = []
    for k in range(n_links):
        paths = [{"points": [[0, 0, 2], [4, 3, 0.25]], "types": [], "power_db": -50.0,
                  "tau_s": 1e-8}]
        for i in range(per_link - 1):
            paths.append({"points": [[0, 0, 2], [8, 1 + i, 1], [4, 3, 0.25]], "types": [1],
                          "power_db": -60.0 - 10 * i, "tau_s": 3e-8})
        links.append({"tx": f"AP{k}", "rx": "robot1", "num_paths": per_link, "paths": paths})
    return {"type": "paths", "step": 7, "links": links}


def test_ray_arrays_colour_modes(addon_module):
    from addon import live_view

    sizes, pos, col, rad = live_view.ray_arrays(_paths(), "POWER")
    assert sizes.tolist() == [2, 3, 3] * 2 and pos.shape == (16, 3) and col.shape == (16, 4)
    assert rad.tolist() == pytest.approx([live_view.RAY_RADIUS_M] * 16)
    assert col[:, 3].tolist() == [1.0] * 16
    assert pos[2].tolist() == [0, 0, 2] and pos[3].tolist() == [8, 1, 1]
    lo, hi = live_view.RAY_SCALE_DB                     # -50 dB on the fixed scale
    assert col[0].tolist() == pytest.approx(live_view.power_color((-50.0 - lo) / (hi - lo)))
    sizes, pos, col, _ = live_view.ray_arrays(_paths(), "TYPE", max_paths=2)
    assert sizes.tolist() == [2, 3] * 2
    # second path: tx (white), specular vertex (blue), rx (white)
    assert col[2].tolist() == pytest.approx(live_view.TYPE_COLORS[0])
    assert col[3].tolist() == pytest.approx(live_view.TYPE_COLORS[1])
    assert col[4].tolist() == pytest.approx(live_view.TYPE_COLORS[0])


def _packed(wire, msg):
    """The ``rays`` message (wire 1.3) of a ``paths`` message, as the add-on's decoder
    delivers it (packed fields as bytes)."""
    import struct

    links = []
    for lk in msg["links"]:
        ps = lk["paths"]
        pts = [c for p in ps for q in p["points"] for c in q]
        links.append(wire.rays_link(
            lk["tx"], lk["rx"], lk["num_paths"], sizes=bytes(len(p["points"]) for p in ps),
            points=struct.pack(f"<{len(pts)}f", *pts),
            types=bytes(t for p in ps for t in p["types"]),
            power_db=struct.pack(f"<{len(ps)}f", *(p["power_db"] for p in ps)),
            tau_s=struct.pack(f"<{len(ps)}f", *(p["tau_s"] for p in ps))))
    (got,) = wire.Decoder("e2v").feed(wire.encode({"type": "rays", "step": msg["step"],
                                                   "links": links}))
    return got


@pytest.mark.parametrize("mode, cap, width, opacity", [
    ("POWER", 0, False, False), ("TYPE", 2, True, True), ("POWER", 1, True, False),
    ("TYPE", 0, False, True)])
def test_packed_rays_draw_what_the_json_paths_draw(addon_module, mode, cap, width, opacity):
    """1.3: the packed form gives the same curves, points, colours and radii as the JSON
    form of the same message, also when the cap must pick paths out of order."""
    import numpy as np

    from addon import live_view
    from addon.contract import wire

    msg = _paths(2, 4)
    msg["links"][1]["paths"].reverse()                  # out of order: the cap sorts
    a = live_view.ray_arrays(msg, mode, cap, width_by_power=width, opacity_by_power=opacity)
    b = live_view.ray_arrays(_packed(wire, msg), mode, cap, width_by_power=width,
                             opacity_by_power=opacity)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-6)
    assert len(a[0]) == (8 if cap == 0 else 2 * cap)


def test_a_rays_message_rebuilds_the_rays_object(scene):
    """The ``rays`` message applied (what a 1.3 engine sends): the hair curves hold its
    polylines; the next message of the same curve sizes moves the points in place."""
    import numpy as np

    from addon import live_view
    from addon.contract import wire

    view = live_view.LiveView()
    scene.isac_live.max_paths_per_link = 0
    msg = _packed(wire, _paths(2, 3))
    live_view.apply_message(scene, msg, view)
    cv = bpy.data.objects[live_view.RAYS].data
    got = np.array([p.position[:] for p in cv.points])
    np.testing.assert_allclose(got, live_view.ray_arrays(_paths(2, 3))[1])
    assert [c.points_length for c in cv.curves] == [2, 3, 3] * 2
    assert scene.isac_live.num_rays == 6 and scene.isac_live.paths_step == 7
    moved = _paths(2, 3)
    moved["links"][0]["paths"][1]["points"][1] = [7.5, 2.0, 1.25]
    live_view.apply_message(scene, _packed(wire, moved), view)
    assert cv.points[3].position[:] == pytest.approx((7.5, 2.0, 1.25))
    assert view.rays_built == 2


def test_strongest_paths_per_link(addon_module):
    from addon import live_view

    paths = [{"power_db": v, "k": i} for i, v in enumerate([-70.0, -50.0, -90.0, -60.0])]
    assert [p["k"] for p in live_view.strongest_paths(paths, 2)] == [1, 3]
    assert [p["k"] for p in live_view.strongest_paths(paths, 9)] == [1, 3, 0, 2]
    assert live_view.strongest_paths(paths, 0) is paths            # 0: all, as sent
    # a message out of order: the cap keeps the strongest, not the first
    msg = _paths(1, 3)
    msg["links"][0]["paths"].reverse()                  # -70, -60, -50 dB
    sizes, _, col, _ = live_view.ray_arrays(msg, "POWER", max_paths=1)
    lo, hi = live_view.RAY_SCALE_DB
    assert sizes.tolist() == [2]
    assert col[0].tolist() == pytest.approx(live_view.power_color((-50.0 - lo) / (hi - lo)))


def test_ray_width_and_opacity_by_power(scene):
    from addon import live_view

    lo, hi = live_view.RAY_SCALE_DB
    r0, r1 = live_view.RAY_RADIUS_RANGE_M
    assert live_view.ray_style(hi + 5) == (r1, 1.0)
    assert live_view.ray_style(lo - 5, opacity=True) == (r0, live_view.RAY_ALPHA_MIN)
    r, a = live_view.ray_style((lo + hi) / 2, opacity=True)
    assert r == pytest.approx((r0 + r1) / 2) and a == pytest.approx(
        (1 + live_view.RAY_ALPHA_MIN) / 2)
    assert live_view.ray_style(-45.0, width=False) == (live_view.RAY_RADIUS_M, 1.0)
    sizes, _, col, rad = live_view.ray_arrays(_paths(1, 3), "TYPE", width_by_power=True,
                                              opacity_by_power=True)
    # -50 dB (2 points), -60 dB and -70 dB (3 points each): thinner and fainter as they weaken
    assert sizes.tolist() == [2, 3, 3]
    assert rad[0] > rad[2] > rad[5] and rad[0] == rad[1] and rad[2] == rad[4]
    assert col[0, 3] > col[2, 3] > col[5, 3] and col[0, 3] == col[1, 3]
    # applied: the rays object's radius attribute and a material mixing by the alpha
    p = scene.isac_live
    p.ray_width_by_power, p.ray_opacity_by_power = True, True
    live_view.apply_paths(scene, _paths(1, 3), live_view.LiveView())
    cv = bpy.data.objects[live_view.RAYS].data
    got = [d.value for d in cv.attributes["radius"].data]
    assert got == pytest.approx(rad)
    alphas = [d.color[3] for d in cv.attributes[live_view.RAY_COLOR_ATTR].data]
    assert alphas[0] == pytest.approx(live_view.ray_style(-50.0, opacity=True)[1])
    nt = cv.materials[0].node_tree
    mix = nt.nodes["alpha_mix"]
    assert mix.inputs["Fac"].links[0].from_socket.name == "Alpha"
    p.ray_opacity_by_power = False
    live_view.apply_paths(scene, _paths(1, 3), live_view.LiveView())
    assert {d.color[3] for d in cv.attributes[live_view.RAY_COLOR_ATTR].data} == {1.0}


@pytest.mark.parametrize("maxlen", [1, 2, 5])
def test_a_trail_keeps_the_last_points_like_a_bounded_deque(addon_module, maxlen):
    """:class:`live_view.Trail` against ``collections.deque(maxlen=...)``: the same points
    in the same order after every append, as one contiguous float32 array."""
    import collections

    from addon import live_view

    tr, ref = live_view.Trail(maxlen), collections.deque(maxlen=maxlen)
    for k in range(3 * maxlen + 2):
        p = (k + 0.5, -2.0 * k, 0.25)
        tr.append(p)
        ref.append(p)
        assert list(tr) == list(ref) and len(tr) == len(ref)
        a = tr.array()
        assert a.shape == (len(ref), 3) and a.flags["C_CONTIGUOUS"] and a.dtype == "float32"


def test_a_full_trail_moves_its_points(scene):
    """Every trail is a curve of one hair-curves object; a trail at its full length is
    updated in place (the same curves): its last point is the newest pose."""
    from addon import live_view

    view = live_view.LiveView(trail_length=3)
    for step in range(6):
        live_view.apply_state(scene, {"type": "state", "step": step, "time_s": 0.0, "robots": [
            {"name": "robot1", "pose": [float(step), 2, 0, 0, 0, 0], "velocity": [0, 0],
             "estimate": [step + 0.5, 2.1, 0.0]}]}, view)
        cv = bpy.data.objects[live_view.TRAILS].data
        if step == 0:
            assert len(cv.curves) == 0                   # one point: no line yet
            continue
        assert [round(p[0], 6) for p in live_view.trail_points(view, "robot1_trail")] == [
            float(k) for k in range(max(0, step - 2), step + 1)]
        assert live_view.trail_points(view, "robot1_estimate_trail")[-1] == pytest.approx(
            (step + 0.5, 2.1, 0.0))
        if step == 2:   # both trails full from here: a rebuild would reset this radius
            cv.attributes["radius"].data[0].value = 0.123
    assert view.trail_layout == [("robot1_trail", 3), ("robot1_estimate_trail", 3)]
    assert len(cv.curves) == 2
    assert cv.attributes["radius"].data[0].value == pytest.approx(0.123)   # moved in place
    colours = [c for d in cv.attributes[live_view.TRAIL_COLOR_ATTR].data for c in d.color]
    assert colours == pytest.approx([*live_view.TRAIL_COLORS["truth"]] * 3
                                    + [*live_view.TRAIL_COLORS["estimate"]] * 3)
    assert cv.materials[0].node_tree.nodes["Attribute"].attribute_name == "trail_color"


def test_paths_state_metrics_are_applied(scene):
    from addon import live_view

    view = live_view.LiveView()
    live_view.apply_message(scene, _paths(), view)
    rays = bpy.data.objects[live_view.RAYS]
    assert rays.type == "CURVES" and len(rays.data.curves) == 6 and len(rays.data.points) == 16
    assert scene.isac_live.num_rays == 6 and scene.isac_live.paths_step == 7
    data = rays.data
    live_view.apply_message(scene, _paths(1, 1), view)  # rebuilt in place, not appended
    assert len(rays.data.curves) == 1 and rays.data == data
    for step in range(3):
        live_view.apply_message(scene, {
            "type": "state", "step": step, "time_s": 0.1 * step, "robots": [{
                "name": "robot1", "pose": [1 + 0.1 * step, 2, 0, 0, 0, math.pi / 2],
                "velocity": [0.1, 0], "estimate": [1.05 + 0.1 * step, 2.02, 0]}]}, view)
    bot = bpy.data.objects["ISAC_Live_robot1"]
    assert tuple(round(x, 6) for x in bot.location) == (1.2, 2.0, 0.0)
    assert bot.rotation_euler.z == pytest.approx(math.pi / 2)
    assert len(bot.data.polygons) > 30  # body + wheels + nose
    assert bpy.data.objects["ISAC_Live_robot1_estimate"].location.x == pytest.approx(1.25)
    assert len(live_view.trail_points(view, "robot1_trail")) == 3
    live_view.apply_message(scene, {"type": "metrics", "step": 2, "links": [
        {"tx": "AP1", "rx": "robot1", "snr_db": 31.5, "rate_bps": 2.5e8, "num_paths": 40,
         "los": True}, {"tx": "AP2", "rx": "robot1", "snr_db": None, "rate_bps": None}]}, view)
    rows = scene.isac_live.links
    assert [(r.tx, round(r.snr_db, 1), r.num_paths, r.los) for r in rows[:1]] == [
        ("AP1", 31.5, 40, True)]
    assert math.isnan(rows[1].snr_db)
    live_view.clear(scene)
    assert "ISAC Live" not in bpy.data.collections


def test_edit_tracker_move_rotate_material_remove(scene):
    from mathutils import Vector

    from addon import live_view, materials, modelling
    from addon.contract import wire

    box = modelling.add_furniture("table", (2.0, 1.0, 0.0), 0.0, scene=scene)
    materials.tag_objects([box], "wood", 0.05)
    bpy.context.view_layer.update()
    lo = Vector([min(c[i] for c in box.bound_box) for i in range(3)])
    hi = Vector([max(c[i] for c in box.bound_box) for i in range(3)])
    centre = box.matrix_world @ ((lo + hi) / 2)
    tr = live_view.EditTracker()
    tr.baseline(scene, {box.name}, set())
    assert tr.tracked == [box.name] and tr.poll(scene) == []
    box.location.x += 1.0
    bpy.context.view_layer.update()
    (e,) = tr.poll(scene)
    assert e["op"] == "move" and e["target"] == box.name
    assert e["position"] == pytest.approx([centre.x + 1.0, centre.y, centre.z])
    assert e["orientation"] == pytest.approx([0, 0, 0], abs=1e-6)
    assert tr.poll(scene) == []  # sent once
    box.rotation_euler.z = 0.5
    bpy.context.view_layer.update()
    (e,) = tr.poll(scene)
    assert e["orientation"][2] == pytest.approx(0.5)
    box.isac.itu_material = "metal"
    (e,) = tr.poll(scene)
    assert (e["op"], e["material"], e["thickness"]) == ("material", "metal", pytest.approx(0.05))
    bpy.data.objects.remove(box)
    (e,) = tr.poll(scene)
    assert (e["op"], e["target"]) == ("remove", "Table")
    assert tr.poll(scene) == []
    rack = modelling.add_furniture("rack", (1.0, 1.0, 0.0), 0.0, scene=scene)  # tagged metal
    bpy.context.view_layer.update()
    (e,) = tr.poll(scene)
    assert (e["op"], e["target"], e["material"]) == ("add", rack.name, "metal")
    mesh = wire.edit_mesh(e)  # the mesh travels in the message, not as a host path
    assert mesh.startswith(b"ply") and "mesh_file" not in e
    assert tr.poll(scene) == [] and rack.name in tr.tracked


def test_live_panel_draws_from_properties_only(scene):
    calls = []

    class Stub:
        def _child(self, *a, **k):
            return self

        row = column = box = _child

        def prop(self, data, name, **k):
            calls.append(("prop", name))

        def operator(self, idname, **k):
            calls.append(("operator", idname))
            return type("P", (), {})()

        def label(self, text="", **k):
            calls.append(("label", text))

    scene.isac_live.links.add().tx = "AP1"
    panel = bpy.types.ISAC_PT_live
    panel.draw(type("P", (), {"layout": Stub()})(), bpy.context)
    ops = {c[1] for c in calls if c[0] == "operator"}
    assert {"isac.live_connect", "isac.live_disconnect", "isac.live_start_engine",
            "isac.live_command"} <= ops
    assert any("AP1 ->" in c[1] for c in calls if c[0] == "label")
    scene.isac_live.links.clear()
    from addon import properties

    prefs = properties.ISAC_AddonPreferences
    assert prefs.is_registered and prefs.bl_idname == "addon"  # == the add-on's package
    assert "engine_python" in prefs.__annotations__
    assert properties.addon_preferences() is None  # registered from a script, not enabled


def _fake_engine(major: int):
    """A one-shot server that answers a hello with protocol ``major``.0."""
    from addon.contract import wire

    ls = socket.socket()
    ls.bind(("127.0.0.1", 0))
    ls.listen(1)
    ls.settimeout(10)

    def serve():
        try:
            c, _ = ls.accept()
            c.settimeout(5)
            c.recv(4096)
            c.sendall(wire.encode(dict(wire.hello("engine"), protocol=[major, 0])))
            time.sleep(0.5)
            c.close()
        except OSError:
            pass
        ls.close()

    threading.Thread(target=serve, daemon=True).start()
    return ls.getsockname()[1]


def test_client_refuses_an_engine_of_another_major_version(addon_module):
    from addon import live

    c = live.LiveClient("127.0.0.1", _fake_engine(99), backoff_s=(0.05, 0.1))
    c.connect()
    end = time.monotonic() + 10
    while c.state != live.REFUSED and time.monotonic() < end:
        c.tick()
        time.sleep(0.01)
    assert c.state == live.REFUSED and "incompatible" in c.last_error


def test_client_backs_off_while_nothing_listens(addon_module):
    from addon import live

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens here now
    c = live.LiveClient("127.0.0.1", port, backoff_s=(0.05, 0.2))
    c.connect()
    end = time.monotonic() + 30  # only against a hang
    while c._failures < 3 and time.monotonic() < end:
        assert c.tick() == []
        # tick never waits on the network: a socket it holds is non-blocking
        assert c._sock is None or not c._sock.getblocking()
        time.sleep(0.005)
    assert c.state in (live.WAITING, live.CONNECTING) and c._failures >= 3
    # the backoff doubles from its first delay up to its cap
    assert c._next_attempt - time.monotonic() <= 0.2
    c.send(live.wire.command("run"))  # queued while disconnected, not lost
    assert len(c.outbox) == 1
    c.disconnect()
    assert c.state == live.IDLE


def test_radar_detections_and_tracks_are_drawn(scene):
    """Engine StepResult with a radar step -> state message (validated by the wire
    format) -> detection and track markers plus a track trail in Blender."""
    import numpy as np

    from addon import live_view
    from addon.contract import wire
    from isac_twin import RobotState, StepResult
    from isac_twin.live.protocol import state_message
    from isac_twin.sensing.estimator import SensingStep
    from isac_twin.sensing.radar import Detection
    from isac_twin.sensing.tracker import Track

    view = live_view.LiveView()
    for step in range(2):
        d1 = Detection("AP2->AP1", 7.1, 0.2, -1.6, 0.3, 1.9, 18.0, 40, 3,
                       position=np.array([5.5, 3.1 + 0.1 * step, 0.096]))
        d2 = Detection("AP2->AP1", 9.0, 0.0, 0.0, np.nan, np.nan, 12.0, 51, 0)  # not located
        res = StepResult(step=step, time_s=0.5 * step)
        res.robots["robot1"] = RobotState("robot1", np.array([5.5, 3.0, 0, 0, 0, 1.57]),
                                          np.array([0.2, 0.1]))
        res.sensing = SensingStep(detections={"AP2->AP1": [d1, d2]}, tracks=[
            Track(id=4, x=np.array([5.45, 3.05 + 0.1 * step, 0.0, 0.2]), P=np.eye(4),
                  confirmed=True)])
        msg = state_message(res)
        assert wire.validate(msg, "e2v") is None
        assert [d["position"] is None for d in msg["detections"]] == [False, True]
        live_view.apply_message(scene, msg, view)
    dets = bpy.data.objects["ISAC_Live_Detections"].data
    assert len(dets.vertices) == 6  # one octahedron: the located detection only
    centre = sum((v.co for v in dets.vertices), start=dets.vertices[0].co * 0) / 6
    assert tuple(round(x, 4) for x in centre) == (5.5, 3.2, 0.096)
    tracks = bpy.data.objects["ISAC_Live_Tracks"].data
    assert len(tracks.vertices) == 6
    assert len(live_view.trail_points(view, "track_4_trail")) == 2
    # a state without radar fields keeps the last radar picture
    live_view.apply_message(scene, {"type": "state", "step": 3, "time_s": 1.5,
                                    "robots": []}, view)
    assert len(bpy.data.objects["ISAC_Live_Detections"].data.vertices) == 6
    # bad radar fields are refused by the wire format, naming the field
    bad = dict(msg, tracks=[{"id": 1, "position": [1.0]}])
    assert "tracks" in wire.validate(bad, "e2v")
    live_view.clear(scene)


def test_no_remote_connection_while_online_access_is_off(scene):
    """Issue 22: Blender's online-access setting is honoured: a remote engine is refused
    with the reason in the panel (this bpy module runs with online access off); an
    engine on this machine is always reachable."""
    from addon import live

    assert bpy.app.online_access is False
    with pytest.raises(ValueError, match="online access is off"):
        live.open_session(scene, "192.0.2.7", 8765)
    assert scene.isac_live.connection == "refused"
    assert "online access is off" in scene.isac_live.last_error
    assert live.network_refusal("127.0.0.1") is None and live.network_refusal("::1") is None
    assert live.network_refusal("localhost") is None
    assert live.network_refusal("192.0.2.7", online_access=True) is None
    assert live.session() is None  # nothing was opened


def test_edit_tracker_resends_every_edit_since_the_baseline(scene):
    """After an engine restart (issue 22): moved, re-materialed, removed and added objects
    are all sent again by the next poll, and only once."""
    from addon import live_view, materials, modelling

    a = modelling.add_furniture("table", (2.0, 1.0, 0.0), 0.0, scene=scene)
    b = modelling.add_furniture("chair", (1.0, 2.0, 0.0), 0.0, scene=scene)
    c = modelling.add_furniture("chair", (3.0, 2.0, 0.0), 0.0, scene=scene)
    materials.tag_objects([a, b, c], "wood", 0.05)
    bpy.context.view_layer.update()
    from addon.exporter import safe_name

    tr = live_view.EditTracker()
    tr.baseline(scene, {safe_name(o.name) for o in (a, b, c)}, set())
    a.location.x += 1.0
    materials.tag_objects([b], "metal", 0.01)
    c_name = safe_name(c.name)  # the wire name
    bpy.data.objects.remove(c)
    rack = modelling.add_furniture("rack", (1.0, 1.0, 0.0), 0.0, scene=scene)  # tagged metal
    bpy.context.view_layer.update()
    first = {(e["op"], e["target"]) for e in tr.poll(scene)}
    assert first == {("move", a.name), ("material", b.name), ("remove", c_name),
                     ("add", rack.name)}
    assert tr.poll(scene) == []
    names = tr.resend()
    assert set(names) == {a.name, b.name, c_name, rack.name}
    again = tr.poll(scene)
    assert {(e["op"], e["target"]) for e in again} == first
    assert next(e for e in again if e["op"] == "add")["mesh_ply"]
    assert tr.poll(scene) == []


def test_ray_colour_is_a_fixed_db_scale(addon_module):
    """The same path power gets the same colour whatever the strongest path of the message
    (failed before: colours were relative to the strongest path)."""
    from addon import live_view

    a = _paths(1, 3)                                  # powers -50, -60, -70 dB
    b = _paths(1, 3)
    b["links"][0]["paths"][0]["power_db"] = -80.0     # strongest is now -60 dB
    _, _, ca, _ = live_view.ray_arrays(a, "POWER")
    _, _, cb, _ = live_view.ray_arrays(b, "POWER")
    # path 1 (-60 dB) starts at point 2 in both
    assert ca[2].tolist() == cb[2].tolist()
    lo, hi = live_view.RAY_SCALE_DB
    assert ca[2].tolist() == pytest.approx(live_view.power_color((-60.0 - lo) / (hi - lo)))


def test_rays_legend_follows_the_colour_mode(scene):
    from addon import live_view

    view = live_view.LiveView()
    live_view.apply_scene(scene, {"type": "scene", "name": "s", "content_hash": "h",
                                  "frequency_hz": 2.4e9, "links": [],
                                  "devices": [{"name": "AP1", "kind": "access_point",
                                               "role": "tx", "position": [0, 3, 2],
                                               "array": [4, 8]},
                                              {"name": "robot1", "kind": "robot", "role": "rx",
                                               "position": [4, 3, 0]}],
                                  "objects": [{"name": "W", "material": "concrete",
                                               "thickness": 0.2, "bounds_min": [-0.2, -0.3, 0],
                                               "bounds_max": [8, 6, 3]}]}, view)
    assert view.extent == (-0.2, -0.3, 8, 6)
    # array sizes from the scene message (wire 1.2); a 1.1 scene without them: the name
    assert bpy.data.objects["ISAC_Live_AP_AP1_Label"].data.body == "AP1 4x8"
    assert list(bpy.data.objects["ISAC_Live_AP_AP1"].location)[:2] == [0, 3]
    # a radio map's transmitter list marks the AP again without erasing the array size
    from addon import legend

    legend.mark_access_point(scene, "AP1", (0, 3, 2))
    assert bpy.data.objects["ISAC_Live_AP_AP1_Label"].data.body == "AP1 4x8"
    # an AP on a wall labels itself towards the room's middle (not inside the wall)
    legend.mark_access_point(scene, "AP9", (8.0, 3.0, 2.0), toward=(4.0, 3.0))
    lab9 = bpy.data.objects["ISAC_Live_AP_AP9_Label"]
    assert list(lab9.location) == pytest.approx([8.0 - legend.AP_LABEL_OFFSET_M, 3.0, 2.05])
    assert lab9.data.align_x == "RIGHT" and lab9.data.body == "AP9"
    assert not lab9.visible_shadow                      # no shadow copy of a label on a wall
    lab = bpy.data.objects["ISAC_Live_robot1_Label"]
    assert lab.data.body == "robot1" and list(lab.location)[:2] == pytest.approx([4.15, 3.15])
    live_view.apply_state(scene, {"type": "state", "step": 0, "time_s": 0.0, "robots": [
        {"name": "robot1", "pose": [5, 2, 0, 0, 0, 1], "velocity": [0, 0]}]}, view)
    assert list(lab.location)[:2] == pytest.approx([5.15, 2.15])      # follows the robot
    p = scene.isac_live
    p.ray_color_mode = "POWER"
    live_view.apply_paths(scene, _paths(), view)
    bar = bpy.data.objects[live_view.RAYS_LEGEND]
    texts = {k: bpy.data.objects[live_view.RAYS_LEGEND + k].data.body
             for k in ("_Title", "_Min", "_Max")}
    assert texts == {"_Title": "ray path gain (dB)", "_Min": "-110", "_Max": "-40"}
    assert max(v.co.y for v in bar.data.vertices) < -0.3 and not bar.hide_render
    p.ray_color_mode = "TYPE"
    live_view.apply_paths(scene, _paths(), view)
    assert bar.hide_render and bpy.data.objects[live_view.RAYS_LEGEND + "_Title"].hide_render
    p.ray_color_mode = "POWER"


def test_link_metrics_as_text_in_the_scene(scene):
    from addon import live_view

    view = live_view.LiveView()
    view.extent = (0.0, 0.0, 8.0, 6.0)
    live_view.apply_metrics(scene, {"type": "metrics", "step": 4, "links": [
        {"tx": "AP1", "rx": "robot1", "snr_db": 35.24, "rate_bps": 1.34e9,
         "mcs_rate_bps": 6.23e8, "los": True},
        {"tx": "AP2", "rx": "robot1", "snr_db": None, "rate_bps": None}]}, view)
    obj = bpy.data.objects[live_view.METRICS_TEXT]
    assert obj.data.body.splitlines() == [
        "step 4", "AP1 -> robot1: SNR 35.2 dB, 1340 Mbit/s (MCS 623 Mbit/s), LOS",
        "AP2 -> robot1: SNR -, -"]
    assert obj.location.y > 6.0


def test_the_panel_clears_a_stale_connection_error_on_reconnect(scene):
    """While no engine listens the panel shows "cannot connect"; once one answers the
    session reconnects and the panel shows no error (before, the old error stayed),
    while an engine's rejection arriving after that stays until the next reconnect."""
    from addon import live
    from addon.contract import wire

    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # nothing listens here yet
    s = live.LiveSession(scene, "127.0.0.1", port)
    s.client.backoff_s = (0.05, 0.1)
    end = time.monotonic() + 10
    while "cannot connect" not in scene.isac_live.last_error and time.monotonic() < end:
        s.tick()
        time.sleep(0.01)
    assert "cannot connect" in scene.isac_live.last_error

    ls = socket.socket()
    ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    ls.bind(("127.0.0.1", port))
    ls.listen(1)
    ls.settimeout(10)
    stop = threading.Event()

    def serve():
        c, _ = ls.accept()
        c.settimeout(5)
        c.recv(4096)
        c.sendall(wire.encode(wire.hello("engine"))
                  + wire.encode({"type": "scene", "name": "x", "content_hash": "h",
                                 "frequency_hz": 2.4e9, "objects": [], "devices": [],
                                 "links": []}))
        stop.wait(10)
        c.sendall(wire.encode(wire.error("rejected", "edit move 'Box': target: no object",
                                         ref="Box")))
        time.sleep(1.0)
        c.close()
        ls.close()

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        end = time.monotonic() + 10
        while not (s.client.connected and s.applied["scene"]) and time.monotonic() < end:
            s.tick()
            time.sleep(0.01)
        assert s.client.connected and s.applied["scene"] == 1
        assert scene.isac_live.last_error == ""
        stop.set()
        end = time.monotonic() + 10
        while not s.applied["error"] and time.monotonic() < end:
            s.tick()
            time.sleep(0.01)
        for _ in range(3):
            s.tick()
        assert scene.isac_live.last_error == "rejected: edit move 'Box': target: no object"
    finally:
        stop.set()
        s.client.disconnect()
        t.join(5)
