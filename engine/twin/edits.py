"""Live edits of a twin's room and devices: validated when queued, applied before a step.

:class:`SceneEditor` is the twin's collaborator for :class:`~.state.Edit` records
(``add``, ``move``, ``material``, ``remove``): :meth:`SceneEditor.validate` checks an
edit completely against the twin as it is now, :meth:`SceneEditor.queue` validates
and queues it, and :meth:`SceneEditor.apply_pending` applies the queue at the start
of the next :meth:`~isac_twin.twin.twin.Twin.step` (so the next trace sees it). A
``move`` of an access point changes the twin's ``ap_poses``; a ``move`` of a robot
teleports it; the other edits change the scene. Meshes an ``add`` edit sends as
bytes are stored in a private folder removed with the editor (and so with its twin).
"""

from __future__ import annotations

import hashlib
import logging
import re
import shutil
import tempfile
import weakref
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..contract import schema, wire
from ..errors import MeshError
from ..scene.meshes import confine, parse_ply, read_ply
from ..scene.twin_scene import BOUNDS_TOLERANCE_M
from .state import Edit

__all__ = ["MAX_EDIT_MESH_BYTES", "EditResult", "SceneEditor", "public_reason"]

log = logging.getLogger(__name__)

#: Largest mesh an ``add`` edit may name, bytes.
MAX_EDIT_MESH_BYTES = 32 * 1024 * 1024

#: ``on_result(edit, error)``: ``error`` None when the edit was applied, else why not
EditResult = Callable[[Edit, "str | None"], None]

# an absolute path (POSIX or a Windows drive) in a message: a token starting with
# / or X:\ that holds a further separator; not "m/s" or "1/2" (a word before the /)
_ABS_PATH = re.compile(r"(?<![\w.])(?:[A-Za-z]:)?[\\/](?:[^\s'\"\\/]+[\\/])+([^\s'\"\\/]*)")


def _short(name) -> str:
    """``repr`` of a name for a message, cut to 64 characters (a name may be refused
    for its length; repr escapes what is not printable)."""
    text = str(name)
    return repr(text) if len(text) <= 64 else repr(text[:64]) + f"... ({len(text)} characters)"


def public_reason(exc: BaseException | str) -> str:
    """The text of an error as a remote sender may read it: every absolute path is
    cut to its last component (``.../name.ply``), so a rejection reveals nothing of
    the host's folders; one line."""
    text = exc if isinstance(exc, str) else (str(exc) or type(exc).__name__)
    text = _ABS_PATH.sub(lambda m: ".../" + m.group(1), text)
    return " ".join(text.split())


class SceneEditor:
    """The edit queue of one twin, and the one validation and application of edits.

    Args:
        twin: the :class:`~isac_twin.twin.twin.Twin` that owns this editor. It is
            held weakly (the twin holds the editor), and read as it is at each
            call: its ``scene``, ``config``, ``agents`` (rebuilt by a reset),
            ``ap_poses``, ``asset_dirs``, ``sensing_worker`` and ``stale_databases``.
    """

    def __init__(self, twin) -> None:
        self._twin = weakref.proxy(twin)
        #: edits validated and queued, applied before the next step
        self.pending: list[Edit] = []
        self._replies: list[EditResult | None] = []  # one per pending edit
        self._upload_dir: Path | None = None

    def _names_after_queue(self) -> set[str]:
        """The objects' names as the queued edits will leave them (in order)."""
        names = set(self._twin.scene.objects)
        for e in self.pending:
            if e.op == "add":
                names.add(e.target)
            elif e.op == "remove":
                names.discard(e.target)
        return names

    def validate(self, edit: Edit) -> None:
        """Check an edit completely against the twin as it is now, with the edits
        queued before it applied (objects they add or remove).

        The one validation of edits: :meth:`queue` calls it before queuing,
        so the live server (which queues through ``Twin.apply_edit``) answers a bad
        edit at once and the twin never meets it in a step.

        Raises:
            ValueError: naming the edit (op and target) and the field at fault.
        """
        tw = self._twin
        what = f"edit {edit.op} {_short(edit.target)}"
        if edit.op not in wire.EDIT_OPS:
            raise ValueError(f"{what}: op: expected one of {', '.join(wire.EDIT_OPS)}")
        objects = self._names_after_queue()
        devices = set(tw.ap_poses) | set(tw.agents)

        def triple(field, value, margin=None):
            try:
                v = np.asarray(value, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):
                v = np.zeros(0)
            if v.shape != (3,) or not np.isfinite(v).all():
                raise ValueError(f"{what}: {field}: expected 3 finite numbers, got {value!r}")
            if margin is None:
                return
            lo = np.asarray(tw.scene.bounds_min, float) - margin
            hi = np.asarray(tw.scene.bounds_max, float) + margin
            if not (np.all(v >= lo) and np.all(v <= hi)):
                where = ("the room's extent" if margin == 0 else
                         f"the room's extent grown by {margin:.3g} m")
                raise ValueError(f"{what}: {field}: {v.tolist()} lies outside {where} "
                                 f"{np.round(lo, 3).tolist()}..{np.round(hi, 3).tolist()} m")

        def material(required):
            if edit.material is None and not required:
                return
            if edit.thickness is not None and not (np.isfinite(edit.thickness)
                                                   and edit.thickness > 0):
                raise ValueError(f"{what}: thickness: expected a finite value > 0 m, "
                                 f"got {edit.thickness!r}")
            # an ITU material defined at the carrier or a custom one of the scene
            tw.scene.check_material(edit.material, edit.thickness, what)

        if edit.op == "add":
            why = schema.name_problem(edit.target)
            if why is not None:
                raise ValueError(f"{what}: target: {why}")
            if edit.target in objects or edit.target in devices:
                raise ValueError(f"{what}: target: an object or device of that name exists")
            if bool(edit.mesh_file) == (edit.mesh_data is not None):
                raise ValueError(f"{what}: mesh_file/mesh_data: give exactly one for add")
            material(required=True)
            if edit.mesh_data is None:
                self._check_mesh(what, edit.mesh_file)
            elif len(edit.mesh_data) > MAX_EDIT_MESH_BYTES:
                raise ValueError(f"{what}: mesh_data: {len(edit.mesh_data)} bytes exceeds "
                                 f"the limit of {MAX_EDIT_MESH_BYTES}")
            else:
                try:
                    parse_ply(edit.mesh_data, f"mesh_data of {edit.target!r}")
                except MeshError as exc:
                    raise ValueError(f"{what}: {exc}") from None
            return
        if edit.op == "move":
            if edit.target not in objects and edit.target not in devices:
                raise ValueError(f"{what}: target: no object or device of that name")
            if edit.position is None and edit.orientation is None:
                raise ValueError(f"{what}: position/orientation: give at least one")
            if edit.position is not None:
                # Devices stay in the room. An object may move out (a wall moved
                # outwards grows the room), by at most the room's diagonal.
                diag = float(np.linalg.norm(np.subtract(tw.scene.bounds_max,
                                                        tw.scene.bounds_min)))
                triple("position", edit.position,
                       margin=BOUNDS_TOLERANCE_M if edit.target in devices else diag)
            if edit.orientation is not None:
                triple("orientation", edit.orientation)
            return
        if edit.target not in objects:
            raise ValueError(f"{what}: target: no object of that name")
        if edit.op == "material":
            material(required=True)

    def _check_mesh(self, what: str, mesh_file: str) -> None:
        """An ``add`` edit's mesh: a readable PLY inside the scene folder (relative path)
        or an asset folder (absolute), a regular file of at most
        :data:`MAX_EDIT_MESH_BYTES`. One message whatever the reason, so an edit
        reveals nothing about the host's files (the reason is logged)."""
        tw = self._twin
        try:
            path = confine(mesh_file, tw.config.scene.file.parent, roots=tw.asset_dirs)
            read_ply(path, MAX_EDIT_MESH_BYTES)
        except MeshError as exc:
            log.info("%s: mesh_file refused: %s", what, exc)
            raise ValueError(
                f"{what}: mesh_file: expected a PLY file inside the scene folder (a relative "
                f"path) or an asset folder, at most {MAX_EDIT_MESH_BYTES} bytes") from None

    def queue(self, edit: Edit, on_result: EditResult | None = None) -> None:
        """Validate an edit (:meth:`validate`) and queue it; it is applied before
        the next step (the next trace sees it). A bad edit raises here and queues
        nothing; the edits already queued are untouched.

        Args:
            on_result: called once the edit was applied (``error`` None) or failed
                when applied (``error``: ``"edit OP 'TARGET': not applied: why"``,
                no host path in it), on the thread that steps the twin.
        """
        self.validate(edit)
        self.pending.append(edit)
        self._replies.append(on_result)

    def apply_pending(self) -> None:
        """Apply the queued edits in order, each on its own (the twin calls this as a
        step starts), after the radar frame still out on the twin's scene, if any,
        has been traced; then warn about every database the edits made stale.

        An edit that fails (validated when queued, but its mesh changed since, Mitsuba
        refused it, or an edit before it failed) is skipped and answered; whatever
        it raised, the other edits apply and the step goes on."""
        tw = self._twin
        edits, self.pending = self.pending, []
        replies, self._replies = self._replies, []
        if edits and tw.sensing_worker is not None and tw.sensing_worker.shares_scene:
            tw.sensing_worker.wait()  # the radar frame out traces this scene
        for e, reply in zip(edits, replies):
            error = None
            try:
                self._apply_one(e)
            except Exception as exc:  # noqa: BLE001 - one edit must not stop the twin
                log.error("edit %s %r not applied: %s: %s", e.op, e.target,
                          type(exc).__name__, exc)
                error = f"edit {e.op} {_short(e.target)}: not applied: {self._why(e, exc)}"
            if reply is not None:
                try:
                    reply(e, error)
                except Exception:  # noqa: BLE001 - a sender's callback must not either
                    log.exception("edit %s %r: its result callback failed", e.op, e.target)
        if edits:
            for name in tw.stale_databases():
                log.warning("database %s was built before this edit of the room and is "
                            "stale: rebuild it (e.g. `isac-twin grid`)", name)

    def _why(self, e: Edit, exc: Exception) -> str:
        """Why an edit failed, as its sender may read it."""
        if isinstance(exc, KeyError):
            return "target: no object or device of that name (an edit before it failed?)"
        if e.op == "add" and e.mesh_file is not None and isinstance(exc, (OSError, MeshError)):
            # like the validation: one message whatever the host's files said
            return ("mesh_file: expected a PLY file inside the scene folder (a relative "
                    f"path) or an asset folder, at most {MAX_EDIT_MESH_BYTES} bytes")
        return f"{type(exc).__name__}: {public_reason(exc)}"

    def _apply_one(self, e: Edit) -> None:
        tw = self._twin
        if e.op == "move" and e.target in tw.ap_poses:
            self._move_access_point(e)
        elif e.op == "move" and e.target in tw.agents:
            self._teleport_robot(e)
        elif e.op == "move":
            tw.scene.move_object(e.target, e.position, e.orientation)
        elif e.op == "material":
            tw.scene.set_material(e.target, e.material, e.thickness)
        elif e.op == "remove":
            tw.scene.remove_object(e.target)
        elif e.op == "add":
            if e.mesh_data is not None:
                path = self._store_mesh(e.mesh_data)
            else:
                path = confine(e.mesh_file, tw.config.scene.file.parent,
                               roots=tw.asset_dirs)
            tw.scene.add_object(e.target, path, e.material, e.thickness)
        log.info("applied edit %s %s; scene hash now %s", e.op, e.target,
                 tw.scene.content_hash()[:12])

    def _store_mesh(self, data: bytes) -> Path:
        """Write a mesh sent as bytes to the editor's own folder (private, removed with
        the editor, i.e. with its twin); the file is named by its SHA-256."""
        if self._upload_dir is None:
            self._upload_dir = Path(tempfile.mkdtemp(prefix="isac-twin-meshes-"))
            weakref.finalize(self, shutil.rmtree, self._upload_dir, True)
        path = self._upload_dir / f"{hashlib.sha256(data).hexdigest()}.ply"
        path.write_bytes(data)
        return path

    def _move_access_point(self, e: Edit) -> None:
        tw = self._twin
        pos, ori = tw.ap_poses[e.target]
        new_pos = tuple(map(float, e.position)) if e.position is not None else pos
        new_ori = tuple(map(float, e.orientation)) if e.orientation is not None else ori
        if not (np.isfinite(new_pos).all() and np.isfinite(new_ori).all()):
            raise ValueError(f"move {e.target!r}: position/orientation must be finite")
        if not tw.scene.contains(new_pos):
            raise ValueError(f"move {e.target!r}: {list(new_pos)} lies outside the room")
        tw.ap_poses[e.target] = (new_pos, new_ori)

    def _teleport_robot(self, e: Edit) -> None:
        tw = self._twin
        robot = tw.agents[e.target].robot
        pose = robot.state.pose.copy()
        if e.position is not None:
            pose[:3] = e.position
        if e.orientation is not None:
            pose[3:6] = e.orientation
        if not np.isfinite(pose).all() or not tw.scene.contains(pose[:3]):
            raise ValueError(f"move {e.target!r}: pose {pose.tolist()} is not finite or "
                             "lies outside the room")
        robot.reset(pose, t=robot.state.t)
