"""The scene-folder vocabulary: the one definition the add-on and the engine share.

Standard library only (no ``bpy``, no numpy), like :mod:`wire`: the add-on
imports it as ``.schema`` (its enum properties are built from it), the engine
loads this file through ``engine/addon_shared.py`` (``engine.config`` checks
``twin.toml`` against it, ``engine.robots`` takes the robot bodies from it).
A built engine wheel carries a copy made at build time from this file
(``setup.py``); there is no second source.

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
