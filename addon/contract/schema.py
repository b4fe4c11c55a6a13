# SPDX-License-Identifier: Apache-2.0
"""The scene-folder vocabulary: the one definition the add-on and the engine share.

Standard library only (no ``bpy``, no numpy), like :mod:`.wire`: the add-on
imports it as ``.contract.schema`` (its enum properties are built from it), the
engine as ``isac_twin.contract.schema`` (``isac_twin.scene.config`` checks
``twin.toml`` against it, ``isac_twin.robots`` takes the robot bodies from it).

What lives here is what both sides must agree on for a scene folder
(``docs/config.md``) to mean the same thing: the names a key may take, the
defaults the exporter leaves out and the engine fills in, and the robots'
bodies. How each side uses them (Blender enum items, config checks, the
kinematics) stays with that side. The live link's own vocabulary (edit and
command ops) is in :mod:`wire`.

The order of every table below is part of the contract: Blender stores an
enum property in a .blend file as its item's index, so reordering or
inserting in the middle would change saved scenes. Append only.
"""

from __future__ import annotations

from dataclasses import dataclass

#: ``schema`` of ``twin.toml``: the format version the exporter writes and the engine reads.
TWIN_TOML_SCHEMA = 1

#: Device kinds of ``twin.toml`` -> (label, description). The add-on's enum
#: identifiers are these upper-cased, after its own "NONE" (scene geometry).
DEVICE_KINDS: dict[str, tuple[str, str]] = {
    "access_point": ("Access point", "Radio access point (not exported as geometry)"),
    "robot": ("Robot", "Mobile robot carrying an antenna array (not exported as geometry)"),
}

#: Device roles -> (label, description).
ROLES: dict[str, tuple[str, str]] = {
    "tx": ("Tx", "Transmitter"),
    "rx": ("Rx", "Receiver"),
    "txrx": ("Tx/Rx", "Transmitter and receiver"),
}

#: Antenna element patterns (Sionna RT's names) -> (label, description).
PATTERNS: dict[str, tuple[str, str]] = {
    "iso": ("Isotropic", ""),
    "dipole": ("Short dipole", ""),
    "hw_dipole": ("Half-wave dipole", ""),
    "tr38901": ("3GPP TR 38.901", ""),
}
DEFAULT_PATTERN = "iso"

#: Antenna polarizations (Sionna RT's names) -> (label, description).
POLARIZATIONS: dict[str, tuple[str, str]] = {
    "V": ("V", "Vertical"),
    "H": ("H", "Horizontal"),
    "VH": ("VH", "Dual: vertical and horizontal"),
    "cross": ("Cross", "Dual: +/-45 degrees"),
}
DEFAULT_POLARIZATION = "V"
#: Slant angle of each port of an element, degrees from vertical (Sionna's
#: ``polarization_registry``): one port, or two for the dual polarizations.
POLARIZATION_SLANTS_DEG: dict[str, tuple[float, ...]] = {
    "V": (0.0,), "H": (90.0,), "VH": (0.0, 90.0), "cross": (-45.0, 45.0)}
#: Polarizations with two antenna ports per element.
DUAL_POLARIZATIONS = ("VH", "cross")

#: Element spacing of a planar array when ``twin.toml`` leaves it out, wavelengths.
DEFAULT_ELEMENT_SPACING = 0.5

#: Directions of a circular robot path -> (label, description).
PATH_DIRECTIONS: dict[str, tuple[str, str]] = {
    "ccw": ("Counter-clockwise", ""),
    "cw": ("Clockwise", ""),
}
DEFAULT_PATH_DIRECTION = "ccw"


@dataclass(frozen=True)
class RobotBody:
    """The body of one robot model: its size, wheels and speed limits.

    Dimensions are ROBOTIS' TurtleBot3 e-Manual figures (overall size) and URDFs
    (wheels); the limits are the OpenCR firmware's (``turtlebot3_node``).

    Attributes:
        label: name shown in the add-on.
        size: overall ``(length, width, height)`` of the base, m (x forward, z up);
            the radar's target cuboid and the add-on's display size.
        wheel_radius: m.
        wheel_width: m.
        wheel_separation: distance between the wheels' contact points, m.
        footprint_radius: radius of a circle enclosing the base, m (keep-out margin
            of room checks; at least half the diagonal of ``length x width``).
        max_linear: firmware limit on ``|v|``, m/s ("the model's limit" of a path speed).
        max_angular: firmware limit on ``|w|``, rad/s.
    """

    label: str
    size: tuple[float, float, float]
    wheel_radius: float
    wheel_width: float
    wheel_separation: float
    footprint_radius: float
    max_linear: float
    max_angular: float


#: Robot models -> bodies (``twin.toml`` ``devices[].model``, ``robot.toml`` ``[robot] model``).
ROBOT_MODELS: dict[str, RobotBody] = {
    "burger": RobotBody("TurtleBot3 Burger", size=(0.138, 0.178, 0.192), wheel_radius=0.033,
                        wheel_width=0.018, wheel_separation=0.160, footprint_radius=0.113,
                        max_linear=0.211, max_angular=2.63),
    "waffle": RobotBody("TurtleBot3 Waffle", size=(0.281, 0.306, 0.141), wheel_radius=0.033,
                        wheel_width=0.018, wheel_separation=0.287, footprint_radius=0.208,
                        max_linear=0.266, max_angular=1.85),
}
DEFAULT_ROBOT_MODEL = "burger"

#: Array centre in base_link when a robot's ``antenna_offset`` is left out, m.
DEFAULT_ANTENNA_OFFSET = (0.0, 0.0, 0.25)


#: ``scene.xml`` bsdf plugin of an ITU-R P.2040 material (``type`` + ``thickness``).
ITU_MATERIAL_PLUGIN = "itu-radio-material"
#: ``scene.xml`` bsdf plugin of a custom radio material: Sionna RT's own ``RadioMaterial``
#: (plain Sionna loads it with these values), written as ``id="mat-<name>"``.
CUSTOM_MATERIAL_PLUGIN = "radio-material"
#: Prefix of every material's bsdf id in ``scene.xml``.
MATERIAL_ID_PREFIX = "mat-"


@dataclass(frozen=True)
class MaterialProperty:
    """One property of a custom radio material (a ``<float name=...>`` of its bsdf).

    Attributes:
        unit: SI unit ("" for a ratio).
        lower, upper: accepted range; ``lower_open``: the lower bound itself is refused.
        description: what it is.
    """

    unit: str
    lower: float
    upper: float
    lower_open: bool
    description: str

    def check(self, value) -> str | None:
        """``None`` when ``value`` is accepted, else what was expected (one phrase)."""
        try:
            v = float(value)
        except (TypeError, ValueError):
            return f"expected a number, got {value!r}"
        ok_lo = v > self.lower if self.lower_open else v >= self.lower
        if not (v == v and ok_lo and v <= self.upper):  # v == v: not NaN
            lo = "(" if self.lower_open else "["
            return f"expected a value in {lo}{self.lower:g}, {self.upper:g}] {self.unit}".rstrip() \
                + f", got {value!r}"
        return None


#: The custom radio material's properties, in the order the exporter writes them. Values
#: are those at the scene's carrier frequency (a custom material has no frequency model).
CUSTOM_MATERIAL_PROPERTIES: dict[str, MaterialProperty] = {
    "relative_permittivity": MaterialProperty("", 1.0, 1.0e4, False,
                                              "relative permittivity (real part) at the carrier"),
    "conductivity": MaterialProperty("S/m", 0.0, 1.0e8, False, "conductivity at the carrier"),
    "thickness": MaterialProperty("m", 0.0, 10.0, True, "slab thickness"),
}

#: Characters a custom material's name may use (it is part of a bsdf id and a Blender name).
MATERIAL_NAME_CHARS = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-."


#: Most waypoints of a robot's polyline path (twin.toml ``[devices.path]``, the live
#: link's ``set_path``): a path is checked against the room when it is set, on the
#: thread that steps the twin.
MAX_WAYPOINTS = 1000

#: Longest object or device name, characters (Blender 5 names hold at most 255 bytes).
MAX_NAME_CHARS = 255


def name_problem(name) -> str | None:
    """Why ``name`` cannot name an object or a device (None: it can). A name is a
    string of printable characters (no line break, control character such as an ANSI
    escape, or lone surrogate, which would forge log lines or fail to encode),
    not only spaces, at most :data:`MAX_NAME_CHARS` characters."""
    if not isinstance(name, str):
        return f"expected a string, got {type(name).__name__}"
    if not name.strip():
        return f"expected a name, got the empty name {name!r}"
    if len(name) > MAX_NAME_CHARS:
        return f"{len(name)} characters, beyond the limit of {MAX_NAME_CHARS}"
    for i, c in enumerate(name):
        if not c.isprintable() and c != " ":
            return (f"character {i} ({c!r}) is not printable (line breaks, control "
                    "characters and lone surrogates are refused)")
    return None


def custom_material_problems(name: str, values: dict, itu_names=()) -> list[str]:
    """What is wrong with custom material ``name`` of properties ``values``
    (``{property: value}``, every key of :data:`CUSTOM_MATERIAL_PROPERTIES`); ``[]`` when
    nothing is. ``itu_names``: the ITU material names, which a custom name may not take."""
    out = []
    if not name or any(c not in MATERIAL_NAME_CHARS for c in name):
        out.append(f"custom material {name!r}: the name must be non-empty and use only "
                   "letters, digits, '_', '-', '.'")
    elif name in itu_names:
        out.append(f"custom material {name!r}: the name is an ITU material's; choose another")
    for key, prop in CUSTOM_MATERIAL_PROPERTIES.items():
        if key not in values:
            out.append(f"custom material {name!r}: {key} is missing ({prop.description}, "
                       f"{prop.unit or 'ratio'})")
            continue
        err = prop.check(values[key])
        if err:
            out.append(f"custom material {name!r}: {key}: {err}")
    for key in values:
        if key not in CUSTOM_MATERIAL_PROPERTIES:
            out.append(f"custom material {name!r}: unknown property {key!r} (expected "
                       f"{', '.join(CUSTOM_MATERIAL_PROPERTIES)})")
    return out
