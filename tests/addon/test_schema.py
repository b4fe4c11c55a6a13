"""addon/contract/schema.py is the one definition of the scene-folder vocabulary.

Three kinds of check: the add-on's registered enums are the schema's tables (in
order: a .blend stores the index); every value the add-on offers goes through
export and the engine's loader end to end (or is refused there in one line);
and no module of the add-on or the engine holds a literal copy of a table or a
robot's dimensions again (an AST scan, so a copy that reappears fails here).
"""

from __future__ import annotations

import ast
import math
from pathlib import Path

import pytest

bpy = pytest.importorskip("bpy")

pytestmark = pytest.mark.blender

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def schema():
    from addon.contract import schema as s

    return s


def _enum(rna, key):
    prop = rna.properties[key]
    return [item.identifier for item in prop.enum_items], prop.default


def test_object_enums_are_the_schema_tables(addon_module, schema):
    rna = addon_module.properties.ISAC_ObjectProps.bl_rna
    for key, table, default in (("pattern", schema.PATTERNS, schema.DEFAULT_PATTERN),
                                ("polarization", schema.POLARIZATIONS,
                                 schema.DEFAULT_POLARIZATION),
                                ("robot_model", schema.ROBOT_MODELS, schema.DEFAULT_ROBOT_MODEL),
                                ("role", schema.ROLES, "tx"),
                                ("path_direction", schema.PATH_DIRECTIONS,
                                 schema.DEFAULT_PATH_DIRECTION)):
        assert _enum(rna, key) == (list(table), default), key
    kinds, _ = _enum(rna, "device_kind")
    assert kinds == ["NONE"] + [k.upper() for k in schema.DEVICE_KINDS]
    assert tuple(rna.properties["antenna_offset"].default_array) == pytest.approx(
        schema.DEFAULT_ANTENNA_OFFSET)
    for key in ("vertical_spacing", "horizontal_spacing"):
        assert rna.properties[key].default == pytest.approx(schema.DEFAULT_ELEMENT_SPACING)
    labels = {i.identifier: i.name for i in rna.properties["robot_model"].enum_items}
    assert labels == {k: b.label for k, b in schema.ROBOT_MODELS.items()}


def test_operator_enums_are_the_schema_tables(addon_module, schema):
    rna = bpy.ops.isac.add_robot.get_rna_type()
    assert _enum(rna, "model") == (list(schema.ROBOT_MODELS), schema.DEFAULT_ROBOT_MODEL)
    assert _enum(rna, "pattern") == (list(schema.PATTERNS), schema.DEFAULT_PATTERN)
    assert _enum(rna, "polarization") == (list(schema.POLARIZATIONS),
                                          schema.DEFAULT_POLARIZATION)
    assert _enum(rna, "role")[0] == list(schema.ROLES)
    # the live panel's command buttons are wire commands
    from addon.contract import wire

    ops, _ = _enum(bpy.ops.isac.live_command.get_rna_type(), "op")
    assert set(ops) <= set(wire.COMMAND_OPS)


def _lab(scene, **robot):
    from addon import devices, modelling

    modelling.create_room(4.0, 3.0, 2.5, 0.2, name="Room", scene=scene)
    devices.add_access_point("AP1", (0.2, 1.5, 2.0), scene=scene)
    bot = devices.add_robot("robot1", (2.0, 1.5, 0.0), **robot, scene=scene)
    devices.add_link(scene, "AP1", "robot1")
    return bot


def _export_and_load(scene, folder):
    from addon.exporter import export_scene
    from isac_twin import load_config

    export_scene(scene, folder, interchange=False)
    return load_config(folder / "twin.toml")


def test_every_offered_value_loads_in_the_engine(addon_module, reset_scene, schema, tmp_path):
    """Each pattern, polarization, robot model and path direction the add-on offers is
    exported and either accepted by the engine (and modelled by it) or refused at load
    with one line naming the key."""
    from isac_twin import ConfigError
    from isac_twin.raytrace.antenna_patterns import PATTERNS as MODELLED_PATTERNS
    from isac_twin.robots.kinematics import robot_spec
    from isac_twin.scene.config import MODELLED_POLARIZATIONS

    rna = addon_module.properties.ISAC_ObjectProps.bl_rna
    cases = [("pattern", v) for v in _enum(rna, "pattern")[0]]
    cases += [("polarization", v) for v in _enum(rna, "polarization")[0]]
    cases += [("robot_model", v) for v in _enum(rna, "robot_model")[0]]
    cases += [("path_direction", v) for v in _enum(rna, "path_direction")[0]]
    accepted = {}
    for i, (key, value) in enumerate(cases):
        scene = reset_scene()
        bot = _lab(scene)
        if key == "path_direction":
            from addon import devices

            devices.set_circle_path(bot, (2.0, 1.5), 0.5, direction=value)
        else:
            setattr(bot.isac, key, value)
        folder = tmp_path / f"{i}"
        try:
            cfg = _export_and_load(scene, folder)
        except ConfigError as exc:
            msg = str(exc)
            assert key == "polarization" and value not in MODELLED_POLARIZATIONS, msg
            assert "\n" not in msg and "devices[1] (robot1).array.polarization" in msg, msg
            continue
        robot = cfg.devices[1]
        got = {"pattern": robot.array.pattern, "polarization": robot.array.polarization,
               "robot_model": robot.model,
               "path_direction": (robot.path or {}).get("direction")}[key]
        assert got == value, (key, value)
        accepted.setdefault(key, []).append(value)
        if key == "robot_model":
            spec, body = robot_spec(value), schema.ROBOT_MODELS[value]
            assert (spec.wheel_radius, spec.wheel_separation, spec.footprint_radius,
                    spec.max_linear, spec.max_angular) == (
                body.wheel_radius, body.wheel_separation, body.footprint_radius,
                body.max_linear, body.max_angular)
        if key == "pattern":
            assert value in MODELLED_PATTERNS
        assert robot.antenna_offset == pytest.approx(schema.DEFAULT_ANTENNA_OFFSET)
    assert accepted["pattern"] == list(schema.PATTERNS)
    assert accepted["robot_model"] == list(schema.ROBOT_MODELS)
    assert accepted["polarization"] == [p for p in schema.POLARIZATIONS
                                        if p in MODELLED_POLARIZATIONS]
    # and the engine accepts nothing the add-on does not offer
    from isac_twin.scene import config

    assert set(config.PATTERNS) == set(_enum(rna, "pattern")[0])
    assert set(config.POLARIZATIONS) == set(_enum(rna, "polarization")[0])
    assert set(config.ROBOT_MODELS) == set(_enum(rna, "robot_model")[0])
    assert set(config.ROLES) == set(_enum(rna, "role")[0])
    assert {k.upper() for k in config.DEVICE_KINDS} == set(_enum(rna, "device_kind")[0]) - {"NONE"}
    reset_scene()


def test_robot_bodies_are_consistent(schema):
    for model, body in schema.ROBOT_MODELS.items():
        length, width, height = body.size
        half_diagonal = math.hypot(length, width) / 2
        assert half_diagonal <= body.footprint_radius < half_diagonal + 0.01, model
        assert 0 < body.wheel_radius < height and 0 < body.wheel_separation < width, model
        assert body.max_linear > 0 and body.max_angular > 0, model


# ----------------------------------------------------------------------- no copy reappears


def _vocabularies(schema, wire) -> dict[str, frozenset]:
    return {
        "schema.DEVICE_KINDS": frozenset(schema.DEVICE_KINDS),
        "schema.ROLES": frozenset(schema.ROLES),
        "schema.PATTERNS": frozenset(schema.PATTERNS),
        "schema.POLARIZATIONS": frozenset(schema.POLARIZATIONS),
        "schema.DUAL_POLARIZATIONS": frozenset(schema.DUAL_POLARIZATIONS),
        "schema.ROBOT_MODELS": frozenset(schema.ROBOT_MODELS),
        "schema.PATH_DIRECTIONS": frozenset(schema.PATH_DIRECTIONS),
        "wire.EDIT_OPS": frozenset(wire.EDIT_OPS),
        "wire.COMMAND_OPS": frozenset(wire.COMMAND_OPS),
    }


def _significant_digits(x: float) -> int:
    return len(f"{abs(x):.12g}".replace(".", "").lstrip("0").split("e")[0])


def _body_numbers(schema) -> dict[float, str]:
    """Every robot dimension or limit precise enough (>= 3 significant digits) that
    finding it as a literal elsewhere is a copy, not a coincidence."""
    out = {}
    for model, b in schema.ROBOT_MODELS.items():
        for name in ("size", "wheel_radius", "wheel_width", "wheel_separation",
                     "footprint_radius", "max_linear", "max_angular"):
            v = getattr(b, name)
            for x in (v if isinstance(v, tuple) else (v,)):
                if _significant_digits(x) >= 3:
                    out[x] = f"{model}.{name}"
    return out


#: Literal tables keyed by a schema vocabulary that are not copies of it (with why).
ALLOWED = {
    ("engine/devices/opencr.py", "MODEL_INFORMATION"):
        "the OpenCR firmware's model numbers (its control table), keyed by model",
}


def _assigned_name(parents, node) -> str:
    while node in parents:
        node = parents[node]
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            tgt = node.targets[0] if isinstance(node, ast.Assign) else node.target
            return ast.unparse(tgt)
    return ""


def _copies(path: Path, rel: str, vocab: dict, numbers: dict, offset) -> list[str]:
    tree = ast.parse(path.read_text(), rel)
    parents: dict = {}  # child -> parent, built on the first match only
    found = []
    for node in ast.walk(tree):
        strings = None
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            elts = node.elts
            # a string, or the identifier of an enum item ("iso", "Isotropic", "")
            heads = [e.elts[0] if isinstance(e, ast.Tuple) and e.elts else e for e in elts]
            strings = {e.value for e in heads if isinstance(e, ast.Constant)
                       and isinstance(e.value, str)}
            consts = [e.value for e in elts if isinstance(e, ast.Constant)]
            if len(consts) == len(elts) == len(offset) and all(
                    type(c) in (int, float) for c in consts) and \
                    tuple(float(c) for c in consts) == offset:
                found.append(f"{rel}:{node.lineno}: {ast.unparse(node)} copies "
                             "schema.DEFAULT_ANTENNA_OFFSET")
        elif isinstance(node, ast.Dict) and all(isinstance(v, ast.Constant) or
                                                isinstance(v, (ast.Tuple, ast.List))
                                                for v in node.values):
            strings = {k.value for k in node.keys if isinstance(k, ast.Constant)
                       and isinstance(k.value, str)}
        elif isinstance(node, ast.Constant) and type(node.value) is float \
                and node.value in numbers:
            found.append(f"{rel}:{node.lineno}: {node.value} copies "
                         f"schema.ROBOT_MODELS {numbers[node.value]}")
        if strings:
            for name, values in vocab.items():
                if not values <= strings:
                    continue
                if not parents:
                    parents.update((c, p) for p in ast.walk(tree)
                                   for c in ast.iter_child_nodes(p))
                if (rel, _assigned_name(parents, node)) not in ALLOWED:
                    found.append(f"{rel}:{node.lineno}: {ast.unparse(node)[:70]} copies {name}")
    return found


def test_no_module_copies_the_schema(schema):
    from addon.contract import wire

    vocab = _vocabularies(schema, wire)
    numbers = _body_numbers(schema)
    assert "burger.size" in numbers.values()  # the scan looks for the sizes
    offset = tuple(float(x) for x in schema.DEFAULT_ANTENNA_OFFSET)
    found = []
    for top in ("addon", "engine"):
        for path in sorted((ROOT / top).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if rel == "addon/contract/schema.py":
                continue
            v = {k: s for k, s in vocab.items()
                 if not (rel == "addon/contract/wire.py" and k.startswith("wire."))}
            found += _copies(path, rel, v, numbers, offset)
    assert not found, "copies of the shared schema (use addon/contract/schema.py):\n" + "\n".join(found)


def test_the_scan_finds_a_copy(schema, tmp_path):
    """The scan is not vacuous: each kind of copy it looks for is found."""
    from addon.contract import wire

    f = tmp_path / "m.py"
    f.write_text('MODELS = ("burger", "waffle")\nSIZE = (0.138, 0.178, 0.192)\n'
                 'OFFSET = [0.0, 0.0, 0.25]\nOPS = {"move": 1, "material": 2, "remove": 3, '
                 '"add": 4}\nOK = ("tx", "txrx")\n'
                 'ITEMS = [("V", "V", ""), ("H", "H", ""), ("VH", "VH", ""), ("cross", "X", "")]\n')
    found = _copies(f, "m.py", _vocabularies(schema, wire), _body_numbers(schema),
                    tuple(schema.DEFAULT_ANTENNA_OFFSET))
    got = sorted((int(s.split(":")[1]), s.split(" copies ")[1]) for s in found)
    assert got == [(1, "schema.ROBOT_MODELS"), (2, "schema.ROBOT_MODELS burger.size"),
                   (2, "schema.ROBOT_MODELS burger.size"), (2, "schema.ROBOT_MODELS burger.size"),
                   (3, "schema.DEFAULT_ANTENNA_OFFSET"), (4, "wire.EDIT_OPS"),
                   (6, "schema.DUAL_POLARIZATIONS"), (6, "schema.POLARIZATIONS")], found


def test_allowed_tables_cover_every_model(schema):
    """The one table keyed by model that is allowed (the firmware's model numbers)
    still names every model, so a model added to the schema cannot miss it."""
    opencr = pytest.importorskip("isac_twin.devices.opencr")
    assert set(opencr.MODEL_INFORMATION) == set(schema.ROBOT_MODELS)
