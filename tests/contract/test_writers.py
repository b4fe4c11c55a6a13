"""The contract's scene-folder writers (stdlib only, no bpy): float formatting, TOML, PLY."""

from __future__ import annotations

import math
import tomllib

import pytest


@pytest.mark.parametrize("x, text", [
    (0.2, "0.2"), (2.4e9, "2400000000.0"), (78125.0, "78125.0"), (-0.0, "0.0"),
    (0.5, "0.5"), (math.pi / 2, "1.5707964"), (1e-7, "1e-07"), (20, "20.0"),
])
def test_fmt_float_is_float32_shortest(x, text):
    from isac_twin.contract.writers.numbers import fmt_float, to_f32

    assert fmt_float(x) == text
    assert to_f32(float(text)) == to_f32(x)


def test_fmt_float_rejects_non_finite():
    from isac_twin.contract.writers.numbers import fmt_float

    with pytest.raises(ValueError):
        fmt_float(math.nan)


def test_toml_round_trip_and_escapes():
    from isac_twin.contract.writers.twin_toml import dumps

    data = {"schema": 1, "flag": True,
            "scene": {"name": 'a "quoted"\\name\n', "f": 2.4e9},
            "devices": [{"name": "A", "pos": [0.0, 1.5, 2.0], "array": {"rows": 4}},
                        {"name": "B", "pos": [1.0, 0.0, 0.0], "array": {"rows": 1}}],
            "links": [{"tx": "A", "rx": "B"}]}
    text = dumps(data)
    assert tomllib.loads(text) == data
    assert dumps(data) == text
    assert text.index("[[devices]]") < text.index("[devices.array]") < text.index("[[links]]")


def test_ply_round_trip(tmp_path):
    from isac_twin.contract.writers.geometry import WorldMesh, read_ply, write_ply

    mesh = WorldMesh("tri", [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.5], [0, 1, 2], 0.5)
    write_ply(tmp_path / "tri.ply", mesh)
    back = read_ply(tmp_path / "tri.ply")
    assert back.vertices == mesh.vertices and back.triangles == mesh.triangles
    data = (tmp_path / "tri.ply").read_bytes()
    assert data.startswith(b"ply\nformat binary_little_endian 1.0\n")
    assert len(data) == data.index(b"end_header\n") + 11 + 3 * 12 + 13
