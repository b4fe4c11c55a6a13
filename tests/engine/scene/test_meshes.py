"""engine/scene/meshes.py: the PLY reader accepts what Mitsuba's PLY loader accepts (the
independent reference: Mitsuba loads the same files when the scene is traced)."""

import pytest

from isac_twin.errors import MeshError
from isac_twin.scene.meshes import parse_ply

HEADER = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
          "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
          "end_header\n")


@pytest.mark.parametrize("body, ok", [
    ("0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", True),
    ("0 0 0\n1 0 0\n0 1 0\n3 0 1 2", True),               # no final newline
    ("0 0 0 1 0 0\n0 1 0\n3 0 1 2\n", True),               # lines do not matter to Mitsuba
    ("0 0 0 7 7\n1 0 0\n0 1 0\n3 0 1 2\n", False),         # extra tokens on a vertex line
    ("0 0 0\n1 0 0\n0 1 0\n3 0 1 2 5\n", False),           # extra tokens after the face
    ("0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n9\n", False),           # a token after the last element
    ("0 0 0\n1 0 0\n0 1\n3 0 1 2\n", False),               # a vertex short of a coordinate
    ("0 0 0\n1 0 0\n0 1 0\n3 0 1\n", False),               # a face short of an index
])
def test_ascii_ply_is_accepted_exactly_when_mitsuba_loads_it(tmp_path, body, ok):
    """Before, the reader went by lines and accepted a vertex line with extra tokens,
    which Mitsuba refuses ("trailing tokens"); an ``add`` edit with such a mesh passed
    validation and failed inside the twin's step."""
    import mitsuba as mi

    import isac_twin  # noqa: F401  (points Dr.Jit at its LLVM before mitsuba loads)

    mi.set_variant("llvm_ad_mono_polarized")
    blob = (HEADER + body).encode()
    path = tmp_path / "m.ply"
    path.write_bytes(blob)
    try:
        mi.load_dict({"type": "ply", "filename": str(path)})
        mitsuba_ok = True
    except RuntimeError:
        mitsuba_ok = False
    assert mitsuba_ok is ok  # the reference says so
    if ok:
        assert parse_ply(blob, "m.ply").faces.tolist() == [[0, 1, 2]]
    else:
        with pytest.raises(MeshError, match="m.ply"):
            parse_ply(blob, "m.ply")
