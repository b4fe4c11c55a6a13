"""What one twin step produces: the record every consumer reads.

The twin (``engine/twin/twin.py``) returns a :class:`StepResult` from each step;
the live link, the recorder and the figures read it and never reach into the
twin's internals. Edits and commands flow the other way as :class:`Edit` and
:class:`Command`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..raytrace.base import LinkPaths


@dataclass
class RobotState:
    """A robot at the end of a step.

    Attributes:
        name: device name.
        pose: ``[x, y, z, roll, pitch, yaw]`` of base_link in the world (m, rad): the truth.
        velocity: ``[v, omega]``: forward speed (m/s) and yaw rate (rad/s).
        odometry: ``[x, y, yaw]`` the robot's own odometry estimate (m, rad), or None.
        estimate: ``[x, y, z]`` the localization estimate (m), or None.
    """

    name: str
    pose: np.ndarray
    velocity: np.ndarray
    odometry: np.ndarray | None = None
    estimate: np.ndarray | None = None


@dataclass
class LinkState:
    """One link at the end of a step.

    Attributes:
        tx, rx: device names.
        paths: the traced paths (None when the link was not traced this step).
        snr_db: mean received SNR over the resource set, dB.
        rate_bps: achievable (Shannon, log-det) rate, bit/s.
        mcs_rate_bps: the rate a modem reaches through the ``[link_adaptation]``
            MCS table with the EVM floor (engine/phy/mcs.py), bit/s.
        mcs: ``[S]`` MCS table index per stream (-1: below the lowest entry).
    """

    tx: str
    rx: str
    paths: LinkPaths | None
    snr_db: float = float("nan")
    rate_bps: float = float("nan")
    mcs_rate_bps: float = float("nan")
    mcs: tuple = ()


@dataclass
class StepResult:
    """Everything a step produced.

    Attributes:
        step: step index (0-based).
        time_s: simulated time at the end of the step, s.
        robots: ``name -> RobotState``.
        links: ``(tx, rx) -> LinkState``.
        timings_s: wall time per stage of Algorithm 1, s.
        scene_hash: content hash of the scene the step was traced in.
        signals: ``(tx, rx) -> isac_twin.phy.network.LinkSignal``, the full PHY state
            (channels, precoders, powers) when the PHY ran.
        sensing: the radar's ``isac_twin.sensing.estimator.SensingStep`` (detections
            per sensing link, confirmed tracks) delivered this step, else None:
            the frame of this step with ``Twin(sync_sensing=True)``, by default a
            frame sensed ``latency`` steps earlier (its ``step`` and ``time_s``
            say which; ``isac_twin.sensing.worker``).
    """

    step: int
    time_s: float
    robots: dict[str, RobotState] = field(default_factory=dict)
    links: dict[tuple[str, str], LinkState] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    scene_hash: str = ""
    signals: dict = field(default_factory=dict, repr=False)
    sensing: object = field(default=None, repr=False)


@dataclass(frozen=True)
class Edit:
    """A scene edit applied between steps.

    Attributes:
        op: ``"move"`` (object or device to ``position`` / ``orientation``),
            ``"material"`` (object to ``material`` / ``thickness``),
            ``"remove"`` (object or device), ``"add"`` (object from ``mesh_file``
            with ``material``).
        target: object or device name.
        position: ``[3]`` m, for move/add.
        orientation: ``[roll, pitch, yaw]`` rad, for move.
        material: ITU type, for material/add.
        thickness: m, for material/add.
        mesh_file: PLY path, for add (relative to the scene folder, or inside an
            asset folder).
        mesh_data: the PLY file's bytes, for add (what a live viewer sends; the
            twin stores it in a folder of its own).
    """

    op: str
    target: str
    position: tuple[float, float, float] | None = None
    orientation: tuple[float, float, float] | None = None
    material: str | None = None
    thickness: float | None = None
    mesh_file: str | None = None
    mesh_data: bytes | None = field(default=None, repr=False)


@dataclass(frozen=True)
class Command:
    """A command to the twin: ``run``, ``pause``, ``step``, ``reset``,
    ``set_path`` (``robot``, ``path`` spec), ``set_goal`` (``robot``, ``goal`` [2] m),
    ``teleop`` (``robot``, ``linear`` m/s, ``angular`` rad/s)."""

    op: str
    args: dict = field(default_factory=dict)
