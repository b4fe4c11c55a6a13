"""The wire format (addon/contract/wire.py): framing, validation, every fault, versioning."""

from __future__ import annotations

import json
import logging

import pytest


def _paths_msg():
    return {"type": "paths", "step": 3, "links": [{
        "tx": "AP1", "rx": "robot1", "num_paths": 2, "paths": [
            {"points": [[0, 0, 2], [1, 1, 1]], "types": [], "power_db": -50.0, "tau_s": 1e-8},
            {"points": [[0, 0, 2], [3, 0, 1], [1, 1, 1]], "types": [1], "power_db": -60.0,
             "tau_s": 2e-8}]}]}


def _rays_msg(wire, **change):
    """``_paths_msg`` packed (wire 1.3); ``change`` replaces a link field's bytes (or count)."""
    import struct

    fields = dict(sizes=bytes([2, 3]),
                  points=struct.pack("<15f", 0, 0, 2, 1, 1, 1, 0, 0, 2, 3, 0, 1, 1, 1, 1),
                  types=bytes([1]), power_db=struct.pack("<2f", -50.0, -60.0),
                  tau_s=struct.pack("<2f", 1e-8, 2e-8))
    count = change.pop("count", None)
    fields.update(change)
    link = wire.rays_link("AP1", "robot1", 2, **fields)
    if count is not None:
        link["count"] = count
    return {"type": "rays", "step": 3, "links": [link]}


def _received(wire, msg):
    """``msg`` as :class:`wire.Decoder` delivers it (a ``rays`` link's packed fields as bytes)."""
    import base64
    import copy

    if msg["type"] != "rays":
        return msg
    msg = copy.deepcopy(msg)
    for lk in msg["links"]:
        for f in wire.RAYS_FIELDS:
            lk[f] = base64.b64decode(lk[f])
    return msg


def _radiomap_msg():
    return {"type": "radiomap", "scene_hash": "ab" * 32, "height": 0.25, "origin": [0.1, 0.1],
            "cell_size": 0.25, "shape": [2, 3], "step": 4,
            "layers": [{"name": "AP1", "unit": "dBm", "vmin": -80.0, "vmax": -20.0,
                        "values": [-30.5, -40, None, -50.0, -60.0, -70.0]}],
            "tx": [{"name": "AP1", "position": [0, 0, 2]}]}


def _all_messages(wire):
    return [
        wire.hello("engine", "isac-twin", capabilities=["state"]),
        wire.hello("viewer", "blender", token="secret"),
        wire.error("rejected", "edit move: unknown object 'x'", ref="x"),
        {"type": "scene", "name": "lab", "content_hash": "ab" * 32, "frequency_hz": 2.4e9,
         "objects": [{"name": "Wall", "material": "concrete", "thickness": 0.2,
                      "bounds_min": [0, 0, 0], "bounds_max": [1, 1, 1]}],
         "devices": [{"name": "AP1", "kind": "access_point", "role": "tx",
                      "position": [0, 0, 2], "orientation": [0, 0, 0], "model": None,
                      "array": [4, 8]}],
         "links": [["AP1", "robot1"]]},
        {"type": "state", "step": 0, "time_s": 0.1, "scene_hash": "x",
         "robots": [{"name": "robot1", "pose": [1, 2, 0, 0, 0, 1.5], "velocity": [0.2, 0],
                     "odometry": [1, 2, 1.5], "estimate": None}]},
        _paths_msg(),
        _rays_msg(wire),
        {"type": "metrics", "step": 3, "links": [{"tx": "AP1", "rx": "robot1", "snr_db": 20.5,
                                                  "rate_bps": 1e8, "num_paths": 2}]},
        {"type": "status", "running": True, "step": 4, "rate_hz": 10.0, "viewers": 1},
        _radiomap_msg(),
        wire.edit("move", "Table_1", position=(1, 2, 0.4), orientation=(0, 0, 0.5)),
        wire.edit("material", "Table_1", material="metal", thickness=0.01),
        wire.edit("remove", "Chair_1"),
        wire.edit("add", "Box", position=(1, 1, 0), material="wood", mesh_file="/tmp/b.ply"),
        wire.command("run"), wire.command("teleop", robot="robot1", linear=0.1, angular=0.2),
    ]


def test_every_message_type_round_trips(wire):
    msgs = _all_messages(wire)
    assert {m["type"] for m in msgs} == set(wire.MESSAGES)
    stream = b"".join(wire.encode(m) for m in msgs)
    dec = wire.Decoder()
    assert dec.feed(stream) == [_received(wire, m) for m in msgs]
    assert not dec.rejections and dec.buffered == 0


def test_scene_message_carries_every_devices_array(wire, box_scene_dir):
    """1.2: ``devices[].array`` is ``[rows, cols]`` of the device's ``[devices.array]``."""
    from isac_twin import load_scene
    from isac_twin.live.protocol import scene_message

    scene = load_scene(box_scene_dir, load_sionna=False)
    msg = scene_message(scene)
    assert wire.validate(msg, "e2v") is None
    want = {d.name: [d.array.rows, d.array.cols] for d in scene.config.devices}
    assert {d["name"]: d["array"] for d in msg["devices"]} == want
    assert wire.PROTOCOL_VERSION >= (1, 2)


def test_byte_by_byte_and_split_frames(wire):
    msgs = _all_messages(wire)
    stream = b"".join(wire.encode(m) for m in msgs)
    dec = wire.Decoder()
    out = []
    for i in range(len(stream)):
        out += dec.feed(stream[i:i + 1])
    assert out == [_received(wire, m) for m in msgs]


def test_engine_and_addon_share_one_definition(wire):
    from pathlib import Path

    from isac_twin.live import protocol

    addon = Path(__file__).resolve().parents[3] / "addon"
    assert Path(wire.__file__).resolve() == addon / "contract" / "wire.py"
    assert wire.__name__ == "isac_twin.contract.wire" and protocol.wire is wire


@pytest.mark.parametrize("payload, kind, reason", [
    (b"{not json", "malformed", "not UTF-8 JSON"),
    (b"\xff\xfe\x00", "malformed", "not UTF-8 JSON"),
    (b"[1, 2, 3]", "invalid", "must be a JSON object"),
    (b'{"step": 1}', "invalid", "field 'type' missing"),
    (b'{"type": "teleport"}', "unknown_type", "unknown message type 'teleport'"),
    (b'{"type": "state", "step": "one", "time_s": 0, "robots": []}', "invalid",
     "field 'step' must be an integer"),
    (b'{"type": "state", "step": 1, "time_s": 0}', "invalid", "field 'robots' missing"),
    (b'{"type": "state", "step": 1, "time_s": 0, "robots": [{"name": "r", "pose": [1, 2],'
     b' "velocity": [0, 0]}]}', "invalid", "a list of 6 finite numbers"),
    (b'{"type": "edit", "op": "explode", "target": "x"}', "invalid", "field 'op' must be one of"),
    (b'{"type": "edit", "op": "move", "target": "x", "position": [1, "a", 3]}', "invalid",
     "field 'position' must be a list of 3 finite numbers"),
    (b'{"type": "command", "op": "run", "args": []}', "invalid", "field 'args' must be an object"),
    (b'{"type": "hello", "protocol": [1, 0], "role": "viewer", "capabilities": "all"}',
     "invalid", "field 'capabilities' must be a list"),
    (b'{"type": "scene", "name": "s", "content_hash": "h", "frequency_hz": 1e9, "objects": [],'
     b' "links": [], "devices": [{"name": "AP1", "kind": "access_point", "role": "tx",'
     b' "position": [0, 0, 2], "array": [4, 8.5]}]}', "invalid",
     "field 'array' must be a list of 2 integers, got [4, 8.5]"),
])
def test_faults_are_rejected_with_a_reason_and_the_stream_survives(wire, caplog, payload,
                                                                    kind, reason):
    good = wire.command("pause")
    dec = wire.Decoder(peer="fuzz")
    with caplog.at_level(logging.WARNING):
        out = dec.feed(wire.frame_raw(payload) + wire.encode(good))
    assert out == [good]
    assert dict(dec.rejections) == {kind: 1}
    assert reason in dec.reasons[-1]
    assert any(reason in r.getMessage() and "fuzz" in r.getMessage() for r in caplog.records)


def test_oversized_frame_is_skipped_even_when_it_arrives_in_pieces(wire):
    dec = wire.Decoder(max_frame=100)
    big = wire.frame_raw(b"x" * 5000)
    good = wire.command("step")
    stream = wire.encode(good) + big + wire.encode(good)
    out = []
    for i in range(0, len(stream), 7):
        out += dec.feed(stream[i:i + 7])
    assert out == [good, good]
    assert dict(dec.rejections) == {"oversized": 1}
    assert "5000 bytes exceeds the maximum of 100" in dec.reasons[0]


def test_direction_is_enforced(wire):
    dec = wire.Decoder("v2e")
    assert dec.feed(wire.encode({"type": "status", "running": True, "step": 1})) == []
    assert "not accepted in direction v2e" in dec.reasons[0]
    dec = wire.Decoder("e2v")
    assert dec.feed(wire.encode(wire.command("run"))) == []


def test_paths_point_count_must_match_interactions(wire):
    msg = _paths_msg()
    msg["links"][0]["paths"][1]["types"] = [1, 1]
    assert "3 points for 2 interactions" in wire.validate(msg)


def test_encode_refuses_invalid_nan_and_oversized(wire):
    with pytest.raises(wire.WireError, match="field 'step' missing"):
        wire.encode({"type": "paths", "links": []})
    nan = {"type": "status", "running": True, "step": 1, "rate_hz": float("nan")}
    with pytest.raises(wire.WireError, match="'rate_hz' must be a finite number, got NaN"):
        wire.encode(nan)
    with pytest.raises(wire.WireError, match="cannot encode"):
        wire.encode(nan, check=False)
    with pytest.raises(wire.WireError, match="exceeds the maximum"):
        wire.encode(wire.error("x", "y" * 1000), max_frame=100)
    assert wire.finite_or_none(float("inf")) is None and wire.finite_or_none(2) == 2.0


def test_version_check(wire):
    ok = wire.hello("viewer")
    assert wire.check_version(ok) is None
    assert wire.check_version(dict(ok, protocol=[wire.PROTOCOL_VERSION[0], 99])) is None
    why = wire.check_version(dict(ok, protocol=[wire.PROTOCOL_VERSION[0] + 1, 0]))
    assert "incompatible" in why and "major versions differ" in why


def test_frames_are_compact_json(wire):
    frame = wire.encode(wire.command("run"))
    n = int.from_bytes(frame[:4], "big")
    assert n == len(frame) - 4
    assert json.loads(frame[4:]) == {"type": "command", "op": "run", "args": {}}


# --------------------------------------------------------------------------- attacks (issue 22)
# Each payload once crashed a reader (RecursionError, ValueError, OverflowError escaping
# Decoder.feed or check_version) or was accepted with a non-finite number in it.

_DEEP = b"[" * 2000 + b"]" * 2000
_ATTACKS = {
    "deep array": _DEEP,
    "deep object": b'{"a":' * 2000 + b"1" + b"}" * 2000,
    "deep field in a hello": (b'{"type": "hello", "protocol": [1, 0], "role": "viewer", '
                              b'"name": "x", "capabilities": ' + _DEEP + b"}"),
    "too deep for the schema": b'{"type": "command", "op": "run", "args": ' + b'{"a":' * 40
                               + b"1" + b"}" * 40 + b"}",
    "NaN version": b'{"type": "hello", "protocol": [NaN, 0], "role": "viewer"}',
    "Infinity version": b'{"type": "hello", "protocol": [Infinity, 0], "role": "viewer"}',
    "-Infinity version": b'{"type": "hello", "protocol": [1, -Infinity], "role": "viewer"}',
    "1e400 version": b'{"type": "hello", "protocol": [1e400, 0], "role": "viewer"}',
    "huge int version": b'{"type": "hello", "protocol": [' + b"9" * 5000 + b', 0], '
                        b'"role": "viewer"}',
    "float version": b'{"type": "hello", "protocol": [1.5, 0], "role": "viewer"}',
    "1e400 position": b'{"type": "edit", "op": "move", "target": "x", "position": [1e400, 0, 0]}',
    "huge int position": (b'{"type": "edit", "op": "move", "target": "x", "position": ['
                          + b"1" * 400 + b', 0, 0]}'),
    "NaN thickness": b'{"type": "edit", "op": "material", "target": "x", "thickness": NaN}',
}


@pytest.mark.parametrize("name", list(_ATTACKS))
def test_attack_frames_are_rejected_and_the_stream_survives(wire, name):
    good = wire.command("pause")
    dec = wire.Decoder("v2e", peer="attacker")
    out = dec.feed(wire.frame_raw(_ATTACKS[name]) + wire.encode(good))
    assert out == [good]
    assert sum(dec.rejections.values()) == 1 and dec.buffered == 0
    assert dec.feed(wire.encode(good)) == [good]  # nothing left behind in the buffer


def test_every_accepted_hello_has_a_checkable_version(wire):
    for proto in ([1, 0], [2, 7], [0, 0]):
        (msg,) = wire.Decoder("v2e").feed(wire.frame_raw(json.dumps(
            {"type": "hello", "protocol": proto, "role": "viewer"}).encode()))
        assert (wire.check_version(msg) is None) == (proto[0] == wire.PROTOCOL_VERSION[0])



def test_the_engine_stream_is_parsed_fast_but_still_totally(wire):
    """e2v (the add-on reading ``paths``) skips the strict per-number parse; NaN/Infinity,
    deep nesting and an overflowing scalar field are refused all the same."""
    good = wire.command("pause")
    status = b'{"type": "status", "running": true, "step": 1, "rate_hz": %s}'
    for payload in (status % b"NaN", status % b"1e400", status % b"-Infinity", _DEEP * 1):
        dec = wire.Decoder("e2v")
        assert dec.max_depth is None
        dec.direction = None  # accept the v2e command that follows
        assert dec.feed(wire.frame_raw(payload) + wire.encode(good)) == [good]
        assert sum(dec.rejections.values()) == 1 and dec.buffered == 0


@pytest.mark.parametrize("change, match", [
    ({"shape": [2, 2]}, r"layer 'AP1': 6 values for shape \[2, 2\] \(expected 4\)"),
    ({"shape": [0, 3]}, r"'shape' must be \[ny, nx\] with both >= 1"),
    ({"cell_size": 0}, r"'cell_size' must be > 0"),
    ({"layers": [{"name": "AP1", "unit": "dBm", "vmin": 0, "vmax": 1,
                  "values": ["x"] * 6}]}, r"a list of numbers or null"),
])
def test_radiomap_faults_are_named(wire, change, match):
    why = wire.validate(dict(_radiomap_msg(), **change))
    assert why is not None and why.startswith("radiomap") and __import__("re").search(match, why)
    dec = wire.Decoder("e2v")
    assert dec.feed(wire.frame_raw(json.dumps(dict(_radiomap_msg(), **change)).encode())) == []
    assert dec.rejections["invalid"] == 1


_GOOD_PATH = {"points": [[0, 0, 2], [1.5, 2, 0.25]], "types": [], "power_db": -50.0,
              "tau_s": 1e-8}


@pytest.mark.parametrize("paths", [
    [], [_GOOD_PATH] * 3, "x", [_GOOD_PATH, 5], [dict(_GOOD_PATH, points=[[0, 0]])],
    [dict(_GOOD_PATH, points=[[0, 0, True]])], [dict(_GOOD_PATH, types=[1.0])],
    [dict(_GOOD_PATH, power_db=float("nan"))], [dict(_GOOD_PATH, tau_s="1")],
    [{k: v for k, v in _GOOD_PATH.items() if k != "types"}], [dict(_GOOD_PATH, points=5)],
    [_GOOD_PATH, dict(_GOOD_PATH, power_db=True)],
])
def test_fast_paths_check_agrees_with_the_generic_one(wire, paths):
    """The flat loop that checks a link's paths answers exactly what the field-by-field
    check answers (None or the same reason)."""
    assert wire._paths_list(paths) == wire._paths_generic(paths)


def test_packed_rays_carry_the_same_polylines_as_paths(wire):
    """1.3: a ``rays`` message decodes to the arrays it was built from, and reads back as
    the ``paths`` message of the same polylines (float32 precision)."""
    msg = _rays_msg(wire)
    (got,) = wire.Decoder("e2v").feed(wire.encode(msg))
    link = got["links"][0]
    assert link["count"] == 2 and link["sizes"] == bytes([2, 3]) and link["types"] == b"\x01"
    back = wire.rays_as_paths(got)
    want = _paths_msg()
    assert back["step"] == want["step"] and len(back["links"][0]["paths"]) == 2
    for a, b in zip(back["links"][0]["paths"], want["links"][0]["paths"]):
        assert a["points"] == b["points"] and a["types"] == b["types"]
        assert a["power_db"] == b["power_db"] and a["tau_s"] == pytest.approx(b["tau_s"])
    assert wire.validate(back) is None
    assert wire.rays_as_paths(msg) == back          # base64 or bytes alike
    # a link without rays (count 0) is valid too
    empty = _rays_msg(wire, sizes=b"", points=b"", types=b"", power_db=b"", tau_s=b"")
    assert wire.validate(empty) is None and wire.rays_as_paths(empty)["links"][0]["paths"] == []


@pytest.mark.parametrize("change, match", [
    (dict(points=b"\x00" * 56), "field 'points' holds 56 bytes, expected 60 (15 float32)"),
    (dict(points=b"\x00" * 64), "field 'points' holds 64 bytes, expected 60"),
    (dict(points=b"\x00" * 12 + b"\x00\x00\xc0\x7f" + b"\x00" * 44),
     "field 'points' value 3 is nan (expected finite numbers)"),
    (dict(power_db=b"\x00\x00\x80\x7f" + b"\x00" * 4),
     "field 'power_db' value 0 is inf (expected finite numbers)"),
    (dict(tau_s=b"\x00" * 4), "field 'tau_s' holds 4 bytes, expected 8"),
    (dict(count=3), "field 'count' must be 0..num_paths (2), got 3"),
    (dict(count=1), "field 'sizes' holds 2 paths, expected count = 1"),
    (dict(count=-1), "field 'count' must be 0..num_paths (2), got -1"),
    (dict(sizes=bytes([1, 4])), "field 'sizes' path 0 has 1 points (at least 2: tx, rx)"),
    (dict(types=b""), "field 'types' holds 0 interactions, expected 1"),
    (dict(types=bytes([3])), "field 'types' holds interaction code 3"),
])
def test_malformed_packed_rays_are_refused_naming_the_field(wire, change, match):
    """Wrong lengths, NaN/inf, counts that disagree, bad codes: one rejection naming the
    field; the next frame still arrives."""
    bad = _rays_msg(wire, **change)
    r = wire.validate(bad)
    assert r is not None and r.startswith("rays: link 0 (AP1->robot1): ") and match in r
    with pytest.raises(wire.WireError, match="rays: link 0"):
        wire.encode(bad)
    dec = wire.Decoder("e2v")
    out = dec.feed(wire.encode(bad, check=False) + wire.encode(_rays_msg(wire)))
    assert len(out) == 1 and out[0]["links"][0]["count"] == 2
    assert dict(dec.rejections) == {"invalid": 1} and match in dec.reasons[0]
    with pytest.raises(ValueError, match="rays: link 0"):
        wire.rays_as_paths(bad)


def test_packed_rays_that_are_not_base64_are_refused(wire):
    msg = _rays_msg(wire)
    msg["links"][0]["points"] = "not*base64"
    assert "field 'points' is not base64" in wire.validate(msg)
    msg["links"][0]["points"] = 12
    assert "field 'points' must be a base64 string, got 12" in wire.validate(msg)


def test_engine_packs_the_strongest_paths_like_its_json_form(wire):
    """``protocol.link_rays`` (1.3) against ``protocol.link_polylines`` (1.2) on a hand-made
    link: 4 paths of 0-2 interactions, capped at the 3 strongest."""
    from types import SimpleNamespace

    import numpy as np

    from isac_twin.live.protocol import link_polylines, link_rays

    lp = SimpleNamespace(
        tx="AP1", rx="robot1", num_paths=4, power=np.array([1e-7, 1e-5, 1e-9, 1e-6]),
        tau=np.array([3e-8, 1e-8, 5e-8, 2e-8]),
        interactions=np.array([[1, 4], [0, 0], [8, 0], [2, 0]], np.int32),
        vertices=np.array([[[1, 2, 3], [4, 5, 1]], [[0, 0, 0], [0, 0, 0]],
                           [[7, 1, 2], [0, 0, 0]], [[3.5, 0.25, 1], [0, 0, 0]]], float),
        tx_position=np.array([0.05, 3.0, 2.0]), rx_position=np.array([5.5, 3.0, 0.25]))
    packed = {"type": "rays", "step": 1, "links": [link_rays(lp, 3)]}
    assert wire.validate(packed) is None and packed["links"][0]["count"] == 3
    back = wire.rays_as_paths(packed)["links"][0]
    want = link_polylines(lp, 3)
    assert back["num_paths"] == want["num_paths"] == 4
    for a, b in zip(back["paths"], want["paths"], strict=True):
        assert a["types"] == b["types"]
        np.testing.assert_allclose(a["points"], b["points"], atol=1e-6)
        assert a["power_db"] == pytest.approx(b["power_db"], abs=1e-4)
        assert a["tau_s"] == pytest.approx(b["tau_s"], rel=1e-6)
    assert [len(p["types"]) for p in back["paths"]] == [0, 1, 2]     # strongest first
    assert wire.validate({"type": "rays", "step": 1, "links": [link_rays(lp, 0)]}) is None
