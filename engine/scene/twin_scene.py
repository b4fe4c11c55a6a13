"""The twin's scene: a validated scene folder, loaded into Sionna RT.

:func:`load_scene` reads ``twin.toml`` and ``scene.xml``, checks every object
(material known and defined at the carrier frequency, mesh present and
readable) and every device (inside the room, in free space: not in a wall or
furniture, above the floor; robots' paths too, see :mod:`isac_twin.scene.room`), and
only then builds the
Sionna scene, so a bad folder fails with a message naming the file and the
object instead of deep inside Mitsuba.
"""

from __future__ import annotations

import hashlib
import logging
import math
import weakref
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..contract import schema
from ..errors import ConfigError, MeshError
from ..utils.files import read_regular_file
from .config import TwinConfig, load_config
from .meshes import confine, read_ply
from .room import check_placement

log = logging.getLogger(__name__)

#: Thickest material layer accepted, m (a wall's, not a building's).
MAX_THICKNESS_M = 10.0
#: Largest scene.xml read, bytes.
MAX_SCENE_XML_BYTES = 64 * 1024 * 1024

#: Metres a device may stand outside the union of the meshes' bounding boxes
#: (an AP mounted flush on a wall's outer face is still "in the room").
BOUNDS_TOLERANCE_M = 0.05


#: The Sionna scenes loaded in this process (:func:`register_scene`), held weakly.
_LIVE_SCENES: weakref.WeakSet = weakref.WeakSet()


def register_scene(sc) -> None:
    """Note a loaded ``sionna.rt.Scene`` (``TwinScene.sionna`` does, on load): a frozen
    Dr.Jit call that dispatches over radio materials must reach every live scene's
    objects (``isac_twin.raytrace.chains.live_scene_objects``)."""
    _LIVE_SCENES.add(sc)


def live_sionna_scenes() -> list:
    """The live registered Sionna scenes, in one order (by ``id``)."""
    return sorted(_LIVE_SCENES, key=id)


def itu_materials() -> dict[str, dict[tuple[float, float], tuple]]:
    """Sionna's ITU-R P.2040 table: ``name -> {(f_min_GHz, f_max_GHz): (a, b, c, d)}``."""
    from sionna.rt.radio_materials.itu import ITU_MATERIALS_PROPERTIES

    return ITU_MATERIALS_PROPERTIES


def itu_bands(name: str) -> list[tuple[float, float]]:
    """Frequency bands (GHz) in which ITU material ``name`` is defined."""
    return sorted(itu_materials()[name])


def itu_defined_at(name: str, frequency_hz: float) -> bool:
    """Whether ITU material ``name`` has parameters at ``frequency_hz``."""
    f = frequency_hz / 1e9
    return any(lo <= f <= hi for lo, hi in itu_bands(name))


@dataclass(frozen=True)
class ObjectInfo:
    """One object of the scene folder.

    Attributes:
        name: Sionna's object name (the shape id without ``mesh-``).
        material: ITU material type, e.g. ``"concrete"``, or the name of one of the
            scene's custom radio materials (:attr:`TwinScene.custom_materials`).
        thickness: material thickness, m.
        mesh_file: absolute path of the PLY.
        bounds_min, bounds_max: world bounding box ``[3]``, m.
        mesh_sha256: hash of the mesh file's bytes.
    """

    name: str
    material: str
    thickness: float
    mesh_file: Path
    bounds_min: tuple[float, float, float]
    bounds_max: tuple[float, float, float]
    mesh_sha256: str


@dataclass
class TwinScene:
    """A loaded scene folder: configuration, objects, and the Sionna scene.

    Attributes:
        config: the validated ``twin.toml``.
        objects: ``name -> ObjectInfo`` in file order.
        bounds_min, bounds_max: the room's extent (union of all objects), m.
        custom_materials: the custom radio materials of ``scene.xml``, ``name ->
            {"relative_permittivity": eps_r, "conductivity": S/m, "thickness": m}``
            (``schema.CUSTOM_MATERIAL_PROPERTIES``); objects and edits may name them.
    """

    config: TwinConfig
    objects: dict[str, ObjectInfo]
    bounds_min: np.ndarray
    bounds_max: np.ndarray
    _sionna: object = field(default=None, repr=False)
    #: name -> ``[x, y, z, roll, pitch, yaw]`` of objects moved since load
    object_poses: dict[str, np.ndarray] = field(default_factory=dict)
    #: incremented by every edit; consumers re-derive cached geometry when it changes
    revision: int = 0
    _hash: tuple[int, str] | None = field(default=None, repr=False)
    custom_materials: dict[str, dict[str, float]] = field(default_factory=dict)
    #: every edit applied since load, in order, as ``(method name, args)``: a
    #: replica of the scene loaded from the same folder replays them
    #: (:meth:`replay`; the radar's process, ``isac_twin.sensing.process``)
    edits: list[tuple[str, tuple]] = field(default_factory=list)

    @property
    def sionna(self):
        """The ``sionna.rt.Scene`` (loaded on first use, ``merge_shapes=False``)."""
        if self._sionna is None:
            import sionna.rt as rt

            sc = rt.load_scene(str(self.config.scene.file), merge_shapes=False)
            sc.frequency = self.config.scene.frequency_hz
            register_scene(sc)
            self._sionna = sc
        return self._sionna

    def content_hash(self) -> str:
        """SHA-256 over what shapes the radio channel: geometry, poses and materials.

        Two folders with the same meshes and materials hash the same; a moved,
        rotated, added or removed object, or a changed material, changes it.
        The carrier frequency is kept separately in databases' metadata.
        """
        if self._hash is not None and self._hash[0] == self.revision:
            return self._hash[1]  # every step and every grid lookup asks; edits bump revision
        h = hashlib.sha256()
        for name in sorted(self.objects):
            o = self.objects[name]
            h.update(f"{name}\0{o.material}\0{o.thickness!r}\0{o.mesh_sha256}\n".encode())
            if o.material in self.custom_materials:
                props = self.custom_materials[o.material]
                h.update(repr(sorted(props.items())).encode())
            pose = self.object_poses.get(name)
            if pose is not None:
                h.update(np.asarray(pose, np.float64).round(9).tobytes())
        self._hash = (self.revision, h.hexdigest())
        return self._hash[1]

    # ------------------------------------------------------------------ edits

    def _object(self, name: str, what: str):
        if name not in self.objects:
            raise KeyError(f"{what}: no object named {name!r} in scene "
                           f"{self.config.scene.name!r} (objects: {', '.join(self.objects)})")
        return self.sionna.objects[name]

    def move_object(self, name: str, position=None, orientation=None) -> None:
        """Move and/or rotate an object.

        Args:
            name: object name.
            position: new centre ``[3]`` (m) in Sionna's sense: the centre of the
                object's bounding box as loaded, translated.
            orientation: ``[roll, pitch, yaw]`` (rad) relative to the mesh as exported.

        Raises:
            KeyError: unknown object. ValueError: non-finite values.
        """
        obj = self._object(name, "move_object")
        cur = self.object_poses.get(name)
        if cur is None:
            cur = np.concatenate([np.asarray(obj.position.numpy()).reshape(3), np.zeros(3)])
        new = np.array(cur, dtype=np.float64)
        for sl, val, label in ((slice(0, 3), position, "position"),
                               (slice(3, 6), orientation, "orientation")):
            if val is None:
                continue
            v = np.asarray(val, dtype=np.float64).reshape(-1)
            if v.shape != (3,) or not np.isfinite(v).all():
                raise ValueError(f"move_object({name!r}): {label} must be 3 finite numbers, "
                                 f"got {val!r}")
            new[sl] = v
        import mitsuba as mi

        if orientation is not None:
            r, p, y = new[3:]
            obj.orientation = mi.Point3f(float(y), float(p), float(r))  # Sionna: yaw, pitch, roll
        if position is not None:
            obj.position = mi.Point3f(*map(float, new[:3]))
        self.object_poses[name] = new
        self.revision += 1
        self.edits.append(("move_object", (name, _plain(position), _plain(orientation))))

    def define_material(self, name: str, values: dict) -> None:
        """Add custom radio material ``name`` (``{"relative_permittivity",
        "conductivity" (S/m), "thickness" (m)}`` at the carrier) that objects may then be
        given with :meth:`set_material`; redefining one in use is refused.

        Raises:
            ValueError: a bad name or value (``schema.custom_material_problems``), or
                ``name`` is already defined.
        """
        problems = schema.custom_material_problems(name, values, itu_materials())
        if problems:
            raise ValueError(f"define_material: {problems[0]}")
        if name in self.custom_materials:
            raise ValueError(f"define_material: custom material {name!r} exists")
        self.custom_materials[name] = {k: float(values[k])
                                       for k in schema.CUSTOM_MATERIAL_PROPERTIES}
        self.edits.append(("define_material", (name, dict(self.custom_materials[name]))))

    def check_material(self, material: str, thickness: float | None, what: str) -> float:
        """Validate ``material`` (an ITU type defined at the carrier, or one of
        :attr:`custom_materials`) with ``thickness`` (m; ``None``: the custom material's,
        else 0.1 m); return the thickness to use.

        Raises:
            ValueError: unknown material, ITU material undefined at the carrier, a
                non-positive thickness, or a custom material given another thickness.
        """
        custom = self.custom_materials.get(material)
        if custom is not None:
            own = float(custom["thickness"])
            if thickness is not None and not math.isclose(float(thickness), own, rel_tol=1e-6):
                raise ValueError(f"{what}: thickness: custom material {material!r} has its own "
                                 f"thickness "
                                 f"{own:g} m; got {thickness!r}")
            return own
        f = self.config.scene.frequency_hz
        if material not in itu_materials():
            have = ", ".join(sorted(self.custom_materials)) or "none"
            raise ValueError(f"{what}: material: unknown material {material!r}: expected an ITU "
                             f"material or a custom one of the scene ({have})")
        if not itu_defined_at(material, f):
            raise ValueError(f"{what}: material: {material!r} is not defined "
                             f"at {f / 1e9:g} GHz")
        thickness = 0.1 if thickness is None else float(thickness)
        if not (math.isfinite(thickness) and thickness > 0):
            raise ValueError(f"{what}: thickness: must be > 0 m, got {thickness}")
        return thickness

    def _radio_material(self, material: str, thickness: float):
        """The Sionna radio material for ``material`` (validated), shared when it exists."""
        import sionna.rt as rt

        custom = self.custom_materials.get(material)
        if custom is not None:
            # Sionna names a material loaded from scene.xml by its bsdf id without "mat-"
            return self.sionna.get(material) or rt.RadioMaterial(
                material, relative_permittivity=float(custom["relative_permittivity"]),
                conductivity=float(custom["conductivity"]), thickness=float(custom["thickness"]))
        mat_name = f"{material}-{thickness:g}"
        return self.sionna.get(mat_name) or rt.ITURadioMaterial(mat_name, material, thickness)

    def set_material(self, name: str, material: str, thickness: float | None = None) -> None:
        """Give an object another material: an ITU type (and thickness, m; default the
        object's) or one of :attr:`custom_materials` (its own thickness).

        Raises:
            KeyError: unknown object. ValueError: see :meth:`check_material`.
        """
        obj = self._object(name, "set_material")
        info = self.objects[name]
        if thickness is None and material not in self.custom_materials:
            thickness = info.thickness
        thickness = self.check_material(material, thickness, f"set_material({name!r})")
        obj.radio_material = self._radio_material(material, thickness)
        self.objects[name] = replace(info, material=material, thickness=thickness)
        self.revision += 1
        self.edits.append(("set_material", (name, material, thickness)))

    def remove_object(self, name: str) -> None:
        """Remove an object from the scene (the next trace no longer sees it)."""
        self._object(name, "remove_object")
        self.sionna.edit(remove=[name])
        del self.objects[name]
        self.object_poses.pop(name, None)
        self.revision += 1
        self.edits.append(("remove_object", (name,)))

    def add_object(self, name: str, mesh_file: str | Path, material: str,
                   thickness: float | None = None) -> None:
        """Add an object from a PLY file in world coordinates; ``material`` an ITU type
        (``thickness`` m, default 0.1) or a custom material of the scene.

        Raises:
            ValueError: the name exists, the mesh is unreadable, or the material invalid.
        """
        if name in self.objects:
            raise ValueError(f"add_object: an object named {name!r} already exists")
        thickness = self.check_material(material, thickness, f"add_object({name!r})")
        mesh_file = Path(mesh_file).resolve()
        try:
            mesh = read_ply(mesh_file)
        except MeshError as exc:
            raise ValueError(f"add_object({name!r}): {exc}") from exc
        import sionna.rt as rt

        mat = self._radio_material(material, thickness)
        self.sionna.edit(add=[rt.SceneObject(fname=str(mesh_file), name=name,
                                             radio_material=mat)])
        lo, hi = mesh.bounds
        self.objects[name] = ObjectInfo(
            name=name, material=material, thickness=float(thickness), mesh_file=mesh_file,
            bounds_min=tuple(lo.tolist()), bounds_max=tuple(hi.tolist()),
            mesh_sha256=mesh.sha256)
        self.revision += 1
        self.edits.append(("add_object", (name, str(mesh_file), material, float(thickness))))

    def replay(self, edits) -> None:
        """Apply ``edits`` (entries of another scene's :attr:`edits`, made on a
        scene loaded from the same folder) in order, so this scene becomes that
        one's replica.

        Raises:
            ValueError: an entry that is not one of the edit methods.
        """
        for i, entry in enumerate(edits):
            name, args = entry
            if name not in _EDIT_METHODS:
                raise ValueError(f"replay: edits[{i}]: {name!r} is not an edit "
                                 f"(expected one of {', '.join(_EDIT_METHODS)})")
            getattr(self, name)(*args)

    def contains(self, point, tol: float = BOUNDS_TOLERANCE_M) -> bool:
        """Whether ``point`` ``[3]`` (m) lies inside the room's bounding box."""
        p = np.asarray(point, dtype=float)
        return bool(np.all(p >= self.bounds_min - tol) and np.all(p <= self.bounds_max + tol))


#: The :class:`TwinScene` methods that change the scene (logged in ``TwinScene.edits``).
_EDIT_METHODS = ("move_object", "define_material", "set_material", "remove_object",
                 "add_object")


def _plain(v):
    """``None`` or a list of floats (an edit's vector, as logged)."""
    return None if v is None else [float(x) for x in np.asarray(v, np.float64).reshape(-1)]


#: What the exporter writes inside a ``<bsdf>`` and a ``<shape>`` (tag, name); anything
#: else (a ``<transform>`` the room checks would ignore, a property Mitsuba refuses) is
#: refused at load with one line.
_BSDF_CHILDREN = {("string", "type"), ("float", "thickness")}
_SHAPE_CHILDREN = {("string", "filename"), ("boolean", "face_normals")}


def _parse_scene_xml(xml_path: Path, frequency_hz: float) -> dict[str, ObjectInfo]:
    if not xml_path.exists() and not xml_path.is_symlink():
        raise ConfigError(f"{xml_path}: scene file not found")
    blob = read_regular_file(xml_path, MAX_SCENE_XML_BYTES, error=ConfigError,
                             what="a Mitsuba scene XML file")
    try:
        root = ET.fromstring(blob)
    except ET.ParseError as exc:
        raise ConfigError(f"{xml_path}: not valid XML: {exc}") from exc
    if root.tag != "scene":
        raise ConfigError(f"{xml_path}: root element is <{root.tag}>, expected <scene>")

    table = itu_materials()
    mats: dict[str, tuple[str, float]] = {}
    custom: dict[str, dict[str, float]] = {}
    for b in root.iter("bsdf"):
        bid = b.get("id", "")
        if b.get("type") == schema.CUSTOM_MATERIAL_PLUGIN:
            name, props = _custom_bsdf(xml_path, b, table)
            custom[name] = props
            mats[bid] = (name, props["thickness"])
            continue
        if b.get("type") != schema.ITU_MATERIAL_PLUGIN:
            raise ConfigError(f"{xml_path}: bsdf {bid!r}: type {b.get('type')!r} is not "
                              f"supported (expected {schema.ITU_MATERIAL_PLUGIN!r} or "
                              f"{schema.CUSTOM_MATERIAL_PLUGIN!r})")
        for c in b:
            if (c.tag, c.get("name")) not in _BSDF_CHILDREN:
                raise ConfigError(f"{xml_path}: bsdf {bid!r}: <{c.tag} name="
                                  f"{c.get('name')!r}> is not supported (expected "
                                  "<string name=\"type\"> and <float name=\"thickness\">)")
        vals = {c.get("name"): c.get("value") for c in b}
        mtype = vals.get("type")
        if mtype not in table:
            raise ConfigError(f"{xml_path}: bsdf {bid!r}: unknown ITU material {mtype!r} "
                              f"(known: {', '.join(sorted(table))})")
        try:
            thick = float(vals.get("thickness", "0.1"))
        except ValueError as exc:
            raise ConfigError(f"{xml_path}: bsdf {bid!r}: thickness "
                              f"{vals.get('thickness')!r} is not a number") from exc
        if not (math.isfinite(thick) and 0 < thick <= MAX_THICKNESS_M):
            raise ConfigError(f"{xml_path}: bsdf {bid!r}: thickness must be in "
                              f"(0, {MAX_THICKNESS_M:g}] m, got {thick}")
        mats[bid] = (mtype, thick)

    objects: dict[str, ObjectInfo] = {}
    for s in root.iter("shape"):
        sid = s.get("id", "")
        name = sid[5:] if sid.startswith("mesh-") else sid
        why = schema.name_problem(name)
        if why is not None:
            raise ConfigError(f"{xml_path}: shape {sid[:80]!r}: name: {why}")
        if s.get("type") != "ply":
            raise ConfigError(f"{xml_path}: shape {name!r}: type {s.get('type')!r} "
                              "is not supported (expected 'ply')")
        for c in s:
            if (c.tag, c.get("name")) not in _SHAPE_CHILDREN and c.tag != "ref":
                what = ("a <transform> is not supported: export the mesh in world "
                        "coordinates" if c.tag == "transform" else
                        f"<{c.tag} name={c.get('name')!r}> is not supported (expected "
                        "<string name=\"filename\">, <boolean name=\"face_normals\">, <ref>)")
                raise ConfigError(f"{xml_path}: shape {name!r}: {what}")
        fname = next((c.get("value") for c in s.iter("string")
                      if c.get("name") == "filename"), None)
        ref = next((c.get("id") for c in s.iter("ref")), None)
        if fname is None:
            raise ConfigError(f"{xml_path}: shape {name!r}: no <string name=\"filename\">")
        if ref not in mats:
            raise ConfigError(f"{xml_path}: shape {name!r}: material reference {ref!r} "
                              "is not a bsdf defined in the file")
        mtype, thick = mats[ref]
        if mtype not in custom and not itu_defined_at(mtype, frequency_hz):
            bands = ", ".join(f"{lo:g}-{hi:g} GHz" for lo, hi in itu_bands(mtype))
            raise ConfigError(f"{xml_path}: object {name!r}: material {mtype!r} is not defined "
                              f"at {frequency_hz / 1e9:g} GHz (defined: {bands})")
        try:
            mesh_path = confine(fname, xml_path.parent)
            mesh = read_ply(mesh_path)
        except MeshError as exc:
            raise ConfigError(f"{xml_path}: object {name!r}: {exc}") from exc
        lo, hi = mesh.bounds
        if name in objects:
            raise ConfigError(f"{xml_path}: object {name!r} appears twice")
        objects[name] = ObjectInfo(
            name=name, material=mtype, thickness=thick, mesh_file=mesh_path,
            bounds_min=tuple(lo.tolist()), bounds_max=tuple(hi.tolist()),
            mesh_sha256=mesh.sha256)
    if not objects:
        raise ConfigError(f"{xml_path}: the scene has no objects")
    return objects, custom


def _custom_bsdf(xml_path: Path, b, itu_table) -> tuple[str, dict[str, float]]:
    """Name and properties of a custom ``radio-material`` bsdf, or ConfigError."""
    bid = b.get("id", "")
    prefix = schema.MATERIAL_ID_PREFIX
    if not bid.startswith(prefix):
        raise ConfigError(f"{xml_path}: bsdf {bid!r}: a {schema.CUSTOM_MATERIAL_PLUGIN!r} "
                          f"id must be '{prefix}<name>'")
    name = bid[len(prefix):]
    props: dict[str, float] = {}
    for c in b:
        key = c.get("name")
        if c.tag != "float" or key not in schema.CUSTOM_MATERIAL_PROPERTIES:
            raise ConfigError(f"{xml_path}: bsdf {bid!r}: <{c.tag} name={key!r}> is not "
                              f"supported (expected <float name=...> of "
                              f"{', '.join(schema.CUSTOM_MATERIAL_PROPERTIES)})")
        try:
            props[key] = float(c.get("value"))
        except (TypeError, ValueError):
            props[key] = c.get("value")  # reported below
    problems = schema.custom_material_problems(name, props, itu_table)
    if problems:
        raise ConfigError(f"{xml_path}: bsdf {bid!r}: {problems[0]}")
    return name, props


def load_scene(path: str | Path, *, load_sionna: bool = True) -> TwinScene:
    """Load and validate a scene folder (or its ``twin.toml``).

    Args:
        path: the scene folder or its ``twin.toml``.
        load_sionna: build the Sionna scene now (else on first use of ``.sionna``).

    Raises:
        ConfigError: any invalid file, key, object or device; the message names it.
    """
    cfg = load_config(path)
    objects, custom = _parse_scene_xml(cfg.scene.file, cfg.scene.frequency_hz)
    lo = np.min([o.bounds_min for o in objects.values()], axis=0)
    hi = np.max([o.bounds_max for o in objects.values()], axis=0)
    scene = TwinScene(config=cfg, objects=objects, bounds_min=lo, bounds_max=hi,
                      custom_materials=custom)
    for i, d in enumerate(cfg.devices):
        if not scene.contains(d.position):
            raise ConfigError(
                f"{cfg.path}: devices[{i}] ({d.name}).position: {list(d.position)} lies "
                f"outside the room (x {lo[0]:.2f}..{hi[0]:.2f}, y {lo[1]:.2f}..{hi[1]:.2f}, "
                f"z {lo[2]:.2f}..{hi[2]:.2f} m)")
    unknown = [n for n in cfg.room.shell + cfg.room.furniture if n not in objects]
    if unknown:
        raise ConfigError(f"{cfg.path}: room: {', '.join(map(repr, unknown))} "
                          f"{'is not an object' if len(unknown) == 1 else 'are not objects'} "
                          f"of {cfg.scene.file.name}")
    check_placement(scene)
    if load_sionna:
        try:
            scene.sionna  # noqa: B018 - force the load so Mitsuba errors surface here
        except Exception as exc:  # noqa: BLE001 - Mitsuba raises RuntimeError & co.
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[-1]
            raise ConfigError(f"{cfg.scene.file}: Mitsuba could not load the scene: "
                              f"{first[:300]}") from None
    log.info("loaded %s: %d objects, %d devices, %d links", cfg.scene.name, len(objects),
             len(cfg.devices), len(cfg.links))
    return scene
