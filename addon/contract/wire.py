# SPDX-License-Identifier: Apache-2.0
"""The live link's wire format: the one definition the add-on and the engine share.

Standard library only (no ``bpy``, no numpy): the engine imports it as
``isac_twin.contract.wire``, the add-on as ``.contract.wire``.
See ``docs/wire.md`` for the prose version of everything below.

Framing:
    Every message is one *frame*: a 4-byte big-endian unsigned length ``n``
    followed by ``n`` bytes of UTF-8 JSON encoding one object with a string
    field ``"type"``. Frames longer than :data:`MAX_FRAME_BYTES` are refused
    by the sender and skipped by the receiver (the announced bytes are
    discarded, the connection survives).

Parsing is total and bounded: a payload nested deeper than :data:`MAX_DEPTH`,
holding ``NaN``/``Infinity``, a float that overflows (``1e400``) or an integer
of more than :data:`MAX_INT_DIGITS` digits is rejected like any malformed
frame; no payload makes :meth:`Decoder.feed` raise or keep bytes it consumed.
Every number a valid message holds is finite.

Packed rays (1.3):
    A ``rays`` message is the ``paths`` message with each link's polylines packed as
    little-endian binary arrays, base64 in JSON strings (decoding 500 rays from JSON
    lists dominated the viewer's cost per state). :class:`Decoder` checks them (lengths,
    counts, finiteness, interaction codes) and hands them on as ``bytes``; see
    :func:`rays_link` and :func:`unpack_rays`. The engine sends ``rays`` instead of
    ``paths`` to viewers whose ``hello`` lists the capability ``"rays"``.

Versioning:
    Both peers open with ``hello`` carrying ``protocol: [major, minor]``. A
    peer with another *major* version is refused with an ``error`` message
    (code ``"version"``) naming both versions; minor versions only add
    optional fields and message types, which old peers reject one by one
    (counted, logged) without dropping the connection.

Units: SI (m, s, Hz, W or dB/dBm where named so), angles in rad, world frame
Z up. Poses are ``[x, y, z, roll, pitch, yaw]``.
"""

from __future__ import annotations

import base64
import binascii
import json
import logging
import math
import struct
import sys
from array import array
from collections import Counter

from .errors import ContractError

log = logging.getLogger(__name__)

#: Protocol version ``(major, minor)``: bump major for incompatible changes.
PROTOCOL_VERSION = (1, 3)
#: Largest frame payload a peer sends or accepts, bytes.
MAX_FRAME_BYTES = 8 * 1024 * 1024
#: Deepest nesting of arrays/objects a payload may have (the deepest message, ``paths``,
#: needs 7).
MAX_DEPTH = 16
#: Longest integer literal accepted, digits (larger values are no coordinate or count).
MAX_INT_DIGITS = 18
#: Default cap on ray polylines per link in a ``paths`` message (strongest first).
DEFAULT_MAX_PATHS_PER_LINK = 250

_HEADER = struct.Struct(">I")
HEADER_BYTES = _HEADER.size

#: Edit operations (``isac_twin.twin.state.Edit.op``).
EDIT_OPS = ("move", "material", "remove", "add")
#: Command operations (``isac_twin.twin.state.Command.op``).
COMMAND_OPS = ("run", "pause", "step", "reset", "set_path", "set_goal", "teleop")
#: Sionna interaction codes (``isac_twin.raytrace.base``): none, specular, diffuse, refraction,
#: diffraction.
INTERACTION_NAMES = {0: "none", 1: "specular", 2: "diffuse", 4: "refraction", 8: "diffraction"}
#: The hello capability of a viewer that takes packed ``rays`` instead of ``paths`` (1.3).
RAYS_CAPABILITY = "rays"
#: The packed arrays of a ``rays`` link: field -> (array typecode, items per path or point,
#: what it holds). ``sizes``: points per path (interactions + 2, uint8); ``points``:
#: ``[P, 3]`` float32 m; ``types``: interaction codes of the interior points (uint8);
#: ``power_db``, ``tau_s``: per path, float32.
RAYS_FIELDS = ("sizes", "points", "types", "power_db", "tau_s")
_RAYS_CODES = frozenset(k for k in INTERACTION_NAMES if k)


class WireError(ContractError):
    """A message that cannot be sent (invalid or too large)."""


# --------------------------------------------------------------------------- field checks
# Each check returns None when ``v`` is fine, else a short description of what was expected.


_NUMS = (int, float)  # exact types: bool is not a number here


def _is_num(v) -> bool:
    """A finite number (``inf - inf`` is NaN, ``NaN != NaN``)."""
    return type(v) is int or (type(v) is float and v - v == 0.0)


def _vec(n: int):
    def check(v):
        if type(v) is list and len(v) == n and all(_is_num(x) for x in v):
            return None
        return f"a list of {n} finite numbers"
    return check


def _points(v):
    """A polyline: a list of [x, y, z] (the hot path of ``paths`` validation)."""
    nums = _NUMS
    if type(v) is list and all(type(q) is list and len(q) == 3 and type(q[0]) in nums
                               and type(q[1]) in nums and type(q[2]) in nums for q in v):
        return None
    return "a list of [x, y, z] points"


def _intvec(n: int):
    def check(v):
        if type(v) is list and len(v) == n and all(type(x) is int for x in v):
            return None
        return f"a list of {n} integers"
    return check


def _grid_values(v):
    """A flat map layer: numbers, null where there is no value."""
    nums = _NUMS
    if type(v) is list and all(x is None or type(x) in nums for x in v):
        return None
    return "a list of numbers or null"


def _packed(v):
    """A packed array: base64 text on the wire, ``bytes`` once :class:`Decoder` unpacked it."""
    return None if type(v) in (str, bytes) else "a base64 string"


def _ints(v):
    if type(v) is list and all(type(x) is int for x in v):
        return None
    return "a list of integers"


def _opt(check):
    def c(v):
        return None if v is None else check(v)
    return c


def _str(v):
    return None if isinstance(v, str) else "a string"


def _int(v):
    return None if isinstance(v, int) and not isinstance(v, bool) else "an integer"


def _num(v):
    return None if _is_num(v) else "a finite number"


def _bool(v):
    return None if isinstance(v, bool) else "true or false"


def _dict(v):
    return None if isinstance(v, dict) else "an object"


def _one_of(*choices):
    def c(v):
        return None if v in choices else f"one of {', '.join(map(repr, choices))}"
    return c


def _list_of(check):
    def c(v):
        if not isinstance(v, list):
            return "a list"
        for i, item in enumerate(v):
            r = check(item)
            if r is not None:
                return f"a list whose items are {r} (item {i})"
        return None
    return c


def _record(spec):
    def c(v):
        if not isinstance(v, dict):
            return "an object"
        r = _check_fields(v, spec)
        return None if r is None else f"an object with {r}"
    return c


def _check_fields(msg: dict, spec: dict) -> str | None:
    for name, (check, required) in spec.items():
        if name not in msg:
            if required:
                return f"field {name!r} missing"
            continue
        r = check(msg[name])
        if r is not None:
            return f"field {name!r} must be {r}, got {_short(msg[name])}"
    return None


def _short(v) -> str:
    try:
        s = json.dumps(v) if not isinstance(v, bytes) else repr(v)
    except (TypeError, ValueError, RecursionError):
        s = f"a {type(v).__name__}"
    return s if len(s) <= 60 else s[:57] + "..."


_R, _O = True, False  # required, optional

_ROBOT = {
    "name": (_str, _R), "pose": (_vec(6), _R), "velocity": (_vec(2), _R),
    "odometry": (_opt(_vec(3)), _O), "estimate": (_opt(_vec(3)), _O),
}
_PATH = {
    "points": (_points, _R), "types": (_ints, _R),
    "power_db": (_num, _R), "tau_s": (_num, _R),
}
_paths_generic = _list_of(_record(_PATH))


def _paths_list(v):
    """``paths`` of a link: the generic check's result, by a flat loop over the hot case
    (every path well-formed: 500 rays are checked in a third of the time); anything odd
    goes to the generic check for its message."""
    if type(v) is not list:
        return _paths_generic(v)
    nums, is_num = _NUMS, _is_num
    for p in v:
        if type(p) is not dict:
            return _paths_generic(v)
        pts, ts = p.get("points"), p.get("types")
        if (type(pts) is not list or type(ts) is not list or not is_num(p.get("power_db"))
                or not is_num(p.get("tau_s"))):
            return _paths_generic(v)
        for q in pts:
            if not (type(q) is list and len(q) == 3 and type(q[0]) in nums
                    and type(q[1]) in nums and type(q[2]) in nums):
                return _paths_generic(v)
        for t in ts:
            if type(t) is not int:
                return _paths_generic(v)
    return None


_LINK_PATHS = {
    "tx": (_str, _R), "rx": (_str, _R), "num_paths": (_int, _R),
    "paths": (_paths_list, _R),
}
#: a ``rays`` link (1.3): ``count`` paths packed in base64 strings (bytes once decoded)
_LINK_RAYS = {
    "tx": (_str, _R), "rx": (_str, _R), "num_paths": (_int, _R), "count": (_int, _R),
    **{f: (_packed, _R) for f in RAYS_FIELDS},
}
_LINK_METRICS = {
    "tx": (_str, _R), "rx": (_str, _R), "snr_db": (_opt(_num), _R),
    "rate_bps": (_opt(_num), _R), "num_paths": (_int, _O), "los": (_bool, _O),
    "strongest_db": (_opt(_num), _O), "total_db": (_opt(_num), _O),
    "mcs_rate_bps": (_opt(_num), _O),
}
#: a radar detection of a ``[[sensing]]`` link (``position`` None: not located)
_DETECTION = {"link": (_str, _R), "position": (_opt(_vec(3)), _R), "snr_db": (_num, _O)}
#: a confirmed radar track (m, m/s, map frame)
_TRACK = {"id": (_int, _R), "position": (_vec(2), _R), "velocity": (_vec(2), _O)}
_OBJECT = {
    "name": (_str, _R), "material": (_str, _R), "thickness": (_num, _R),
    "bounds_min": (_vec(3), _O), "bounds_max": (_vec(3), _O),
}
#: one quantity of a ``radiomap`` (row-major ``[ny * nx]``, null: no ray reached the cell)
_MAP_LAYER = {
    "name": (_str, _R), "unit": (_str, _R), "vmin": (_num, _R), "vmax": (_num, _R),
    "values": (_grid_values, _R),
}
_MAP_TX = {"name": (_str, _R), "position": (_vec(3), _R)}
_DEVICE = {
    "name": (_str, _R), "kind": (_str, _R), "role": (_str, _R), "position": (_vec(3), _R),
    "orientation": (_vec(3), _O), "model": (_opt(_str), _O),
    # 1.2: the antenna array as ``[rows, cols]`` (the viewer labels devices with it)
    "array": (_intvec(2), _O),
}

#: ``type -> (directions, field spec)``; directions: "e2v" engine -> viewer, "v2e" back.
MESSAGES: dict[str, tuple[frozenset, dict]] = {
    "hello": (frozenset({"e2v", "v2e"}), {
        "protocol": (_intvec(2), _R), "role": (_one_of("engine", "viewer"), _R),
        "name": (_str, _O), "capabilities": (_list_of(_str), _O), "token": (_str, _O),
    }),
    "error": (frozenset({"e2v", "v2e"}), {
        "code": (_str, _R), "message": (_str, _R), "fatal": (_bool, _O), "ref": (_str, _O),
    }),
    "scene": (frozenset({"e2v"}), {
        "name": (_str, _R), "content_hash": (_str, _R), "frequency_hz": (_num, _R),
        "objects": (_list_of(_record(_OBJECT)), _R),
        "devices": (_list_of(_record(_DEVICE)), _R),
        "links": (_list_of(_list_of(_str)), _R),
    }),
    "state": (frozenset({"e2v"}), {
        "step": (_int, _R), "time_s": (_num, _R), "scene_hash": (_str, _O),
        "robots": (_list_of(_record(_ROBOT)), _R), "sent_at": (_num, _O),
        "detections": (_list_of(_record(_DETECTION)), _O),
        "tracks": (_list_of(_record(_TRACK)), _O),
    }),
    "paths": (frozenset({"e2v"}), {
        "step": (_int, _R), "links": (_list_of(_record(_LINK_PATHS)), _R),
    }),
    "rays": (frozenset({"e2v"}), {
        "step": (_int, _R), "links": (_list_of(_record(_LINK_RAYS)), _R),
    }),
    "metrics": (frozenset({"e2v"}), {
        "step": (_int, _R), "links": (_list_of(_record(_LINK_METRICS)), _R),
    }),
    "radiomap": (frozenset({"e2v"}), {
        "scene_hash": (_str, _R), "height": (_num, _R), "origin": (_vec(2), _R),
        "cell_size": (_num, _R), "shape": (_list_of(_int), _R),
        "layers": (_list_of(_record(_MAP_LAYER)), _R), "tx": (_list_of(_record(_MAP_TX)), _O),
        "step": (_int, _O),
    }),
    "status": (frozenset({"e2v"}), {
        "running": (_bool, _R), "step": (_int, _R), "rate_hz": (_num, _O),
        "edits_applied": (_int, _O), "viewers": (_int, _O), "message": (_str, _O),
    }),
    "edit": (frozenset({"v2e"}), {
        "op": (_one_of(*EDIT_OPS), _R), "target": (_str, _R),
        "position": (_opt(_vec(3)), _O), "orientation": (_opt(_vec(3)), _O),
        "material": (_opt(_str), _O), "thickness": (_opt(_num), _O),
        "mesh_file": (_opt(_str), _O), "mesh_ply": (_opt(_str), _O),
    }),
    "command": (frozenset({"v2e"}), {
        "op": (_one_of(*COMMAND_OPS), _R), "args": (_dict, _O),
    }),
}

#: Engine -> viewer messages that only matter in their latest version (the server
#: coalesces them per viewer: a slow viewer gets the newest, drops are counted).
COALESCED_TYPES = ("state", "paths", "rays", "metrics", "status", "radiomap")


def validate(msg, direction: str | None = None, *, unpack: bool = False) -> str | None:
    """Why ``msg`` is not a valid message (None when it is).

    Args:
        msg: the decoded JSON value.
        direction: ``"e2v"`` or ``"v2e"`` to also check who may send it; None = either.
        unpack: a valid ``rays`` message's packed fields are replaced by their ``bytes``
            (what :class:`Decoder` delivers; the check decodes them anyway).
    """
    if not isinstance(msg, dict):
        return f"a message must be a JSON object, got {type(msg).__name__}"
    t = msg.get("type")
    if not isinstance(t, str):
        return "field 'type' missing or not a string"
    if t not in MESSAGES:
        return f"unknown message type {t!r}"
    dirs, spec = MESSAGES[t]
    if direction is not None and direction not in dirs:
        return f"message type {t!r} is not accepted in direction {direction}"
    r = _check_fields(msg, spec)
    if r is not None:
        return f"{t}: {r}"
    if t == "paths":
        for lk in msg["links"]:
            for i, p in enumerate(lk["paths"]):
                if len(p["points"]) != len(p["types"]) + 2:
                    return (f"paths: link {lk['tx']}->{lk['rx']} path {i}: {len(p['points'])} "
                            f"points for {len(p['types'])} interactions (expected n + 2)")
    if t == "rays":
        unpacked = []
        for i, lk in enumerate(msg["links"]):
            try:
                unpacked.append(_unpack_link(lk))
            except ValueError as exc:
                return f"rays: link {i} ({lk['tx']}->{lk['rx']}): {exc}"
        if unpack:
            for lk, arrays in zip(msg["links"], unpacked):
                lk.update(arrays)
    if t == "radiomap":
        shape = msg["shape"]
        if len(shape) != 2 or min(shape) < 1:
            return f"radiomap: field 'shape' must be [ny, nx] with both >= 1, got {shape}"
        if not msg["cell_size"] > 0:
            return f"radiomap: field 'cell_size' must be > 0, got {msg['cell_size']}"
        for lay in msg["layers"]:
            if len(lay["values"]) != shape[0] * shape[1]:
                return (f"radiomap: layer {lay['name']!r}: {len(lay['values'])} values for "
                        f"shape {shape} (expected {shape[0] * shape[1]})")
    return None


# --------------------------------------------------------------------------- packed rays


def _b64(lk: dict, field: str) -> bytes:
    v = lk[field]
    if type(v) is bytes:
        return v
    try:
        return base64.b64decode(v, validate=True)
    except (binascii.Error, ValueError):
        raise ValueError(f"field {field!r} is not base64") from None


def _floats(data: bytes, field: str, n: int) -> array:
    """``n`` little-endian float32 from ``data``; refuses a wrong length or a NaN/inf."""
    if len(data) != 4 * n:
        raise ValueError(f"field {field!r} holds {len(data)} bytes, expected {4 * n} "
                         f"({n} float32)")
    a = array("f")
    a.frombytes(data)
    if sys.byteorder != "little":
        a.byteswap()
    # the float64 sum of float32 values cannot overflow: it is finite iff every value is
    if not math.isfinite(sum(a)):
        bad = next(i for i, x in enumerate(a) if not math.isfinite(x))
        raise ValueError(f"field {field!r} value {bad} is {a[bad]} (expected finite numbers)")
    return a


def _unpack_link(lk: dict) -> dict:
    """The five packed arrays of a ``rays`` link as ``bytes``, checked against each other.

    Raises:
        ValueError: naming the field: not base64, a length that does not match ``count``
            and ``sizes``, a path of fewer than 2 points, an unknown interaction code, a
            non-finite number, ``count`` > ``num_paths``.
    """
    count = lk["count"]
    if count < 0 or count > lk["num_paths"]:
        raise ValueError(f"field 'count' must be 0..num_paths ({lk['num_paths']}), got {count}")
    out = {f: _b64(lk, f) for f in RAYS_FIELDS}
    sizes = out["sizes"]
    if len(sizes) != count:
        raise ValueError(f"field 'sizes' holds {len(sizes)} paths, expected count = {count}")
    if count and min(sizes) < 2:
        i = next(i for i, n in enumerate(sizes) if n < 2)
        raise ValueError(f"field 'sizes' path {i} has {sizes[i]} points (at least 2: tx, rx)")
    n_points = sum(sizes)
    _floats(out["points"], "points", 3 * n_points)
    types = out["types"]
    if len(types) != n_points - 2 * count:
        raise ValueError(f"field 'types' holds {len(types)} interactions, expected "
                         f"{n_points - 2 * count} (sizes - 2 per path)")
    if not _RAYS_CODES.issuperset(types):
        bad = next(t for t in types if t not in _RAYS_CODES)
        raise ValueError(f"field 'types' holds interaction code {bad} (expected one of "
                         f"{sorted(_RAYS_CODES)})")
    _floats(out["power_db"], "power_db", count)
    _floats(out["tau_s"], "tau_s", count)
    return out


def rays_link(tx: str, rx: str, num_paths: int, *, sizes: bytes, points: bytes, types: bytes,
              power_db: bytes, tau_s: bytes) -> dict:
    """One link of a ``rays`` message from its packed arrays (the engine builds them with
    numpy): ``sizes`` uint8 ``[C]`` points per path (interactions + 2), ``points`` float32
    little-endian ``[P, 3]`` m (tx -> interaction vertices -> rx per path, P = sum of
    sizes), ``types`` uint8 ``[P - 2 C]`` interaction codes, ``power_db`` float32 ``[C]``
    (``10 log10 |a|^2``), ``tau_s`` float32 ``[C]`` s; C paths of the ``num_paths`` the
    tracer found."""
    b64 = base64.b64encode
    return {"tx": tx, "rx": rx, "num_paths": int(num_paths), "count": len(sizes),
            "sizes": b64(bytes(sizes)).decode("ascii"),
            "points": b64(bytes(points)).decode("ascii"),
            "types": b64(bytes(types)).decode("ascii"),
            "power_db": b64(bytes(power_db)).decode("ascii"),
            "tau_s": b64(bytes(tau_s)).decode("ascii")}


def rays_as_paths(msg: dict) -> dict:
    """A valid ``rays`` message (packed fields base64 or bytes) as the equivalent ``paths``
    message (lists; float32 values widened to float). For tests and for tools that read the
    JSON form; the add-on reads the arrays with numpy instead.

    Raises:
        ValueError: a packed field is malformed (naming the link and field).
    """
    links = []
    for i, lk in enumerate(msg["links"]):
        try:
            arr = _unpack_link(lk)
        except ValueError as exc:
            raise ValueError(f"rays: link {i} ({lk['tx']}->{lk['rx']}): {exc}") from None
        pts = _floats(arr["points"], "points", len(arr["points"]) // 4)
        pdb = _floats(arr["power_db"], "power_db", lk["count"])
        tau = _floats(arr["tau_s"], "tau_s", lk["count"])
        paths, p, t = [], 0, 0
        for j, n in enumerate(arr["sizes"]):
            paths.append({"points": [list(pts[3 * k:3 * k + 3]) for k in range(p, p + n)],
                          "types": list(arr["types"][t:t + n - 2]),
                          "power_db": pdb[j], "tau_s": tau[j]})
            p, t = p + n, t + n - 2
        links.append({"tx": lk["tx"], "rx": lk["rx"], "num_paths": lk["num_paths"],
                      "paths": paths})
    return {"type": "paths", "step": msg["step"], "links": links}


# --------------------------------------------------------------------------- encode / decode


def encode(msg: dict, *, check: bool = True, max_frame: int = MAX_FRAME_BYTES) -> bytes:
    """One frame (header + JSON) for ``msg``.

    Raises:
        WireError: the message is invalid (when ``check``), holds NaN/inf, or is too large.
    """
    if check:
        r = validate(msg)
        if r is not None:
            raise WireError(r)
    try:
        payload = json.dumps(msg, separators=(",", ":"), allow_nan=False).encode("utf-8")
    except (TypeError, ValueError) as exc:
        raise WireError(f"{msg.get('type', '?')}: cannot encode: {exc}") from exc
    if len(payload) > max_frame:
        raise WireError(f"{msg.get('type')}: frame of {len(payload)} bytes exceeds the maximum "
                        f"of {max_frame}")
    return _HEADER.pack(len(payload)) + payload


class _Refused(ValueError):
    """A JSON literal the wire does not carry (non-finite or absurdly long number)."""


def _parse_constant(name: str):
    raise _Refused(f"{name} is not a finite number")


def _parse_float(text: str) -> float:
    x = float(text)
    if not math.isfinite(x):
        raise _Refused(f"number {text[:20]}{'...' if len(text) > 20 else ''} overflows a float")
    return x


def _parse_int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise _Refused(f"integer of {len(text.lstrip('-'))} digits (at most {MAX_INT_DIGITS})")
    return int(text)


_STRICT = json.JSONDecoder(parse_constant=_parse_constant, parse_float=_parse_float,
                           parse_int=_parse_int)
_LENIENT = json.JSONDecoder(parse_constant=_parse_constant)


def loads(text: str, max_depth: int | None = MAX_DEPTH):
    """``json.loads`` that refuses ``NaN``/``Infinity`` and cannot raise anything but
    ``ValueError``; unless ``max_depth`` is None it also refuses overflowing floats
    (``1e400``), integers longer than :data:`MAX_INT_DIGITS` digits and nesting deeper
    than ``max_depth``.

    With ``max_depth=None`` (the add-on reading the engine's large ``paths`` messages)
    numbers are converted by the C parser alone: strict parsing doubles the decode time
    of a 500-ray message; the schema then checks the finiteness of every scalar field.

    Raises:
        ValueError: what was refused (never ``RecursionError`` or ``OverflowError``).
    """
    try:
        value = (_LENIENT if max_depth is None else _STRICT).decode(text)
    except RecursionError:
        raise ValueError("nested too deeply") from None
    if max_depth is None:
        return value
    stack = [(value, 1)]
    while stack:  # iterative: the depth check itself cannot recurse
        v, d = stack.pop()
        items = v.values() if type(v) is dict else v if type(v) is list else None
        if items is None:
            continue
        if d > max_depth:
            raise ValueError(f"nested deeper than {max_depth} levels")
        stack.extend((x, d + 1) for x in items if type(x) in (dict, list))
    return value


def frame_raw(payload: bytes) -> bytes:
    """Frame arbitrary bytes (tests use it to send malformed payloads)."""
    return _HEADER.pack(len(payload)) + payload


class Decoder:
    """Incremental frame decoder: feed bytes as they arrive, get valid messages out.

    Faults never raise and never lose the stream: a malformed payload, an
    unknown type, a missing or ill-typed field is one rejection (logged with
    its reason, counted in :attr:`rejections` by kind); an oversized frame is
    skipped by discarding exactly the announced number of bytes.

    Args:
        direction: ``"e2v"`` (decode what an engine sends) or ``"v2e"``; None = any.
        max_frame: largest payload accepted, bytes.
        peer: name used in log messages.
        max_depth: deepest nesting accepted (None = only Python's own recursion limit).
            Default :data:`MAX_DEPTH`, except for ``"e2v"``: the engine's stream holds the
            large ``paths`` messages, whose field-by-field validation never descends into
            unexpected values, so the add-on skips the walk (it would double the decode
            time of a 500-ray message).
    """

    def __init__(self, direction: str | None = None, *, max_frame: int = MAX_FRAME_BYTES,
                 peer: str = "peer", max_depth: int | None | str = "auto"):
        self.direction = direction
        self.max_depth = ((None if direction == "e2v" else MAX_DEPTH) if max_depth == "auto"
                          else max_depth)
        self.max_frame = int(max_frame)
        self.peer = peer
        self._buf = bytearray()
        self._pos = 0  # bytes of the buffer consumed by the current feed()
        self._skip = 0
        #: Rejections by kind: ``oversized``, ``malformed``, ``unknown_type``, ``invalid``.
        self.rejections: Counter = Counter()
        #: The last rejections' reasons (newest last, at most 20).
        self.reasons: list[str] = []
        self.frames = 0

    @property
    def buffered(self) -> int:
        """Bytes held waiting for the rest of a frame."""
        return len(self._buf)

    def _reject(self, kind: str, reason: str) -> None:
        self.rejections[kind] += 1
        self.reasons = (self.reasons + [reason])[-20:]
        log.warning("wire: rejected a frame from %s (%s): %s", self.peer, kind, reason)

    def feed(self, data: bytes, *, limit: int | None = None) -> list[dict]:
        """Consume ``data``; return the complete, valid messages it finished.

        Args:
            limit: return after this many messages; the bytes after the last one
                stay buffered, for the next call (``feed(b"")`` goes on), so the
                caller can change :attr:`max_frame` in between (a server raising it
                once the peer's ``hello`` was accepted).
        """
        out: list[dict] = []
        self._buf += data
        self._pos = 0
        try:
            return self._frames(out, limit)
        finally:  # consumed frames leave the buffer whatever happened while parsing them
            del self._buf[:self._pos]

    def _frames(self, out: list[dict], limit: int | None = None) -> list[dict]:
        buf = self._buf
        pos = 0
        n_buf = len(buf)
        while limit is None or len(out) < limit:
            if self._skip:
                k = min(self._skip, n_buf - pos)
                pos += k
                self._pos = pos
                self._skip -= k
                if self._skip:
                    break
                continue
            if n_buf - pos < HEADER_BYTES:
                break
            (n,) = _HEADER.unpack_from(buf, pos)
            if n > self.max_frame:
                self.frames += 1
                self._reject("oversized", f"frame of {n} bytes exceeds the maximum of "
                                          f"{self.max_frame}; skipping it")
                pos += HEADER_BYTES
                self._pos = pos
                self._skip = n
                continue
            if n_buf - pos - HEADER_BYTES < n:
                break
            payload = bytes(buf[pos + HEADER_BYTES:pos + HEADER_BYTES + n])
            pos += HEADER_BYTES + n
            self._pos = pos
            self.frames += 1
            msg = self._parse(payload)
            if msg is not None:
                out.append(msg)
        return out

    def _parse(self, payload: bytes) -> dict | None:
        try:
            msg = loads(payload.decode("utf-8"), self.max_depth)
        except (UnicodeDecodeError, ValueError) as exc:
            self._reject("malformed", f"not UTF-8 JSON: {exc}")
            return None
        try:
            r = validate(msg, self.direction, unpack=True)
        except Exception as exc:  # noqa: BLE001 - a frame must never break the reader
            r = f"could not be checked ({type(exc).__name__})"
        if r is None:
            return msg
        kind = "unknown_type" if r.startswith("unknown message type") else "invalid"
        self._reject(kind, r)
        return None


# --------------------------------------------------------------------------- builders


def finite_or_none(x) -> float | None:
    """``float(x)``, or None when it is NaN/inf/None (JSON has no NaN)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def hello(role: str, name: str = "", *, capabilities=(), token: str | None = None) -> dict:
    """The opening message of either peer."""
    msg = {"type": "hello", "protocol": list(PROTOCOL_VERSION), "role": role, "name": name,
           "capabilities": list(capabilities)}
    if token is not None:
        msg["token"] = token
    return msg


def check_version(msg: dict) -> str | None:
    """Why a peer's ``hello`` is incompatible with this side (None when it is compatible)."""
    major, minor = msg["protocol"]  # integers (validated)
    if major != PROTOCOL_VERSION[0]:
        return (f"protocol version {major}.{minor} is incompatible with "
                f"{PROTOCOL_VERSION[0]}.{PROTOCOL_VERSION[1]} (major versions differ)")
    return None


def error(code: str, message: str, *, fatal: bool = False, ref: str | None = None) -> dict:
    """An error report; ``fatal`` means the sender closes the connection next."""
    msg = {"type": "error", "code": code, "message": message, "fatal": bool(fatal)}
    if ref is not None:
        msg["ref"] = ref
    return msg


def edit(op: str, target: str, *, position=None, orientation=None, material=None,
         thickness=None, mesh_file=None, mesh_ply: bytes | None = None) -> dict:
    """A scene edit (mirrors ``isac_twin.twin.state.Edit``); see docs/wire.md for ``move`` semantics.

    An ``add`` names its mesh by ``mesh_file`` (a path relative to the engine's scene
    folder) or carries it: ``mesh_ply``, the PLY file's bytes (sent base64-encoded).
    """
    msg = {"type": "edit", "op": op, "target": target}
    for k, v in (("position", position), ("orientation", orientation)):
        if v is not None:
            msg[k] = [float(x) for x in v]
    if material is not None:
        msg["material"] = str(material)
    if thickness is not None:
        msg["thickness"] = float(thickness)
    if mesh_file is not None:
        msg["mesh_file"] = str(mesh_file)
    if mesh_ply is not None:
        msg["mesh_ply"] = base64.b64encode(bytes(mesh_ply)).decode("ascii")
    return msg


def edit_mesh(msg: dict) -> bytes | None:
    """The PLY bytes an ``edit`` message carries (None without ``mesh_ply``).

    Raises:
        ValueError: ``mesh_ply`` is not base64.
    """
    text = msg.get("mesh_ply")
    if text is None:
        return None
    try:
        return base64.b64decode(text, validate=True)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"edit {msg.get('op')} {msg.get('target')!r}: mesh_ply: expected "
                         f"base64 ({exc})") from None


def command(op: str, **args) -> dict:
    """A command (mirrors ``isac_twin.twin.state.Command``): run, pause, step, reset, set_path,
    set_goal, teleop."""
    return {"type": "command", "op": op, "args": dict(args)}
