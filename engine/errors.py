"""One error hierarchy (cf. Gymnasium's ``error.py``).

Every error the engine raises on purpose derives from :class:`IsacTwinError` (the
root, shared with the add-on contract) and keeps the built-in base it always had
(``ValueError`` for bad input, ``RuntimeError`` for a device or solver that failed),
so ``except ValueError`` around a call keeps working. Messages name the file, key,
byte or object and what was expected; the command line prints such an error as one
line and exits with status 2 (:mod:`isac_twin.cli`).

::

    IsacTwinError
    +-- ContractError (ValueError)       scene-folder vocabulary, live-link messages
    |   +-- WireError                    a live-link message that cannot be sent
    +-- ConfigError (ValueError)         twin.toml / scene folder / robot.toml
    |   +-- MeshError                    a mesh file
    |   +-- RobotConfigError             robot.toml of the robot runtime
    +-- PathError (ValueError)           a robot path spec
    +-- SpeedLimitError (ValueError)     a command beyond the robot's limits
    +-- BusError (ValueError)            wrong use of the topic bus
    +-- SensingError (ValueError)        a sensing ([[sensing]]) setup or input
    +-- DatabaseMismatchError (ValueError)  a fingerprint database of another scene
    +-- CalibrationError (ValueError)    calibration input
    +-- UsageError (ValueError)          a command-line option or argument of ``isac-twin``
    +-- TruncationError (RuntimeError)   the solver's path buffer overflowed
    +-- DeviceError (RuntimeError)       a device answered wrongly or not at all
        +-- DeviceTimeout
        +-- OakDUnavailable              depthai is not installed
        +-- OakDNotFound                 no OAK device attached
"""

from __future__ import annotations

from .contract.errors import ContractError, IsacTwinError
from .contract.wire import WireError

__all__ = ["IsacTwinError", "ContractError", "WireError", "ConfigError", "MeshError",
           "RobotConfigError", "PathError", "SpeedLimitError", "BusError", "SensingError",
           "DatabaseMismatchError", "CalibrationError", "UsageError", "TruncationError",
           "DeviceError", "DeviceTimeout", "OakDUnavailable", "OakDNotFound"]


class ConfigError(IsacTwinError, ValueError):
    """A configuration or scene-folder file is invalid.

    The message always starts with the file name and the key or object.
    """


class MeshError(ConfigError):
    """A mesh file is missing, truncated or not a PLY the engine can read."""


class RobotConfigError(ConfigError):
    """A bad robot.toml (message names file, key and reason)."""


class PathError(IsacTwinError, ValueError):
    """A path is malformed, leaves the room, or cannot be followed by the robot."""


class SpeedLimitError(IsacTwinError, ValueError):
    """A command asked explicitly for a speed or rate the robot cannot reach."""


class BusError(IsacTwinError, ValueError):
    """Invalid use of the bus: wrong or unknown message type, unknown node or topic."""


class SensingError(IsacTwinError, ValueError):
    """Invalid sensing setup or input; the message names the sensing link."""


class DatabaseMismatchError(IsacTwinError, ValueError):
    """A database does not belong to this scene / frequency / AP layout.

    The message names what differs and what to do (rebuild)."""


class CalibrationError(IsacTwinError, ValueError):
    """Bad calibration input (unknown material/object, bad shapes, bad bounds)."""


class UsageError(IsacTwinError, ValueError):
    """A command-line option or argument of ``isac-twin`` is invalid, or what it names
    cannot be used (the message names the option and what was expected)."""


class TruncationError(IsacTwinError, RuntimeError):
    """The solver hit its path-buffer cap (``max_num_paths_per_src``): paths
    would have been dropped silently."""


class DeviceError(IsacTwinError, RuntimeError):
    """A device answered wrongly or not at all (message names port and field)."""


class DeviceTimeout(DeviceError):
    """No (valid) answer within the allowed time."""


class OakDUnavailable(DeviceError):
    """depthai is not installed."""


class OakDNotFound(DeviceError):
    """No OAK device is attached (or the requested one is not)."""
