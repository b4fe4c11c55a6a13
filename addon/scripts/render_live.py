"""Headless: stream a live twin into a room's .blend and render stills of it with its rays.

Runs with Blender as a Python module (the PyPI ``bpy``); no GUI, no GPU::

    .venv/bin/python addon/scripts/render_live.py --steps 20 --every 5 --out renders/live
    .venv/bin/python addon/scripts/render_live.py --blend blend_scenes/l_office/l_office.blend
    .venv/bin/python addon/scripts/render_live.py --replay run.mcap --steps 60 --every 1 \
        --sequence --mp4 renders/run.mp4 --engine BLENDER_WORKBENCH

It opens the .blend (default the bundled lab; the engine serves the
``scene/`` folder beside it unless ``--scene`` says otherwise, and the robot
follows its own ``[devices.path]``), frames the camera on the room's
geometry, starts ``isac-twin serve``
on a free loopback port (paused), registers the add-on, connects its live
client, then for each of ``--steps`` steps sends ``step``, ticks the client
until that step's state, paths and metrics are applied, and every
``--every`` steps renders two PNGs (the whole lab from above, and a close-up
of the robot with its trail; ``--no-closeup`` skips the second) (Cycles on the CPU by default; Workbench
also works headless; EEVEE works but takes minutes per frame without a GPU).
The engine's step log is written next to the PNGs (``steps.jsonl``).

A recorded run: ``--replay RUN.mcap`` has the engine place the robots along the
recording (``isac-twin serve --replay``) and re-trace each step; ``--sequence``
writes one overview frame per rendered step (``frame_NNNN.png``, numbered from 1,
no close-ups) and ``--mp4 FILE`` encodes those frames into an H.264 MP4 at
``--fps`` with Blender's own FFmpeg (no external tool). For speed use
``--engine BLENDER_WORKBENCH`` (flat colours: the rays' colour attribute, or
with ``--radiomap`` the map's texture; about a second per frame on the CPU);
Cycles stays the default for quality.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import bpy  # noqa: E402
from mathutils import Vector  # noqa: E402

log = logging.getLogger("render_live")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--blend", type=Path, default=ROOT / "blend_scenes/aces_lab/aces_lab.blend")
    p.add_argument("--scene", default="", help="scene folder the engine serves (default: the "
                                               "scene/ folder beside the .blend, else bundled)")
    p.add_argument("--python", default="", help="engine interpreter (default: this one)")
    p.add_argument("--steps", type=int, default=20, help="twin steps to stream")
    p.add_argument("--every", type=int, default=5, help="render every this many steps")
    p.add_argument("--out", type=Path, default=ROOT / "renders/live", help="output folder")
    p.add_argument("--engine", default="CYCLES", choices=("CYCLES", "BLENDER_WORKBENCH",
                                                          "BLENDER_EEVEE"))
    p.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel")
    p.add_argument("--resolution", type=int, nargs=2, default=(960, 540))
    p.add_argument("--color", choices=("POWER", "TYPE"), default="POWER",
                   help="colour rays by path power or by interaction type")
    p.add_argument("--rays-per-link", type=int, default=40,
                   help="draw the strongest N rays per link (0 = all the engine sends)")
    p.add_argument("--robot", default="", help="robot to follow with the close-up "
                                               "(default: the .blend's first robot)")
    p.add_argument("--no-closeup", dest="closeup", action="store_false",
                   help="skip the second still per step, close to the robot")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds to wait per step")
    p.add_argument("--radiomap", type=float, default=None, metavar="CELL",
                   help="show the engine's floor radio map (cells of CELL m) with its legend")
    p.add_argument("--radiomap-layer", default="best",
                   help="radio map layer: an access point's name, best or sinr")
    p.add_argument("--replay", type=Path, default=None, metavar="RUN.mcap",
                   help="render a recorded run (isac-twin record): the engine replays it")
    p.add_argument("--sequence", action="store_true",
                   help="one overview frame per rendered step (frame_NNNN.png), no close-ups")
    p.add_argument("--mp4", type=Path, default=None, metavar="FILE",
                   help="also encode the overview frames into this MP4 (implies --sequence)")
    p.add_argument("--fps", type=int, default=10, help="frames per second of the MP4")
    args = p.parse_args(argv)
    if args.replay is not None and not args.replay.is_file():
        p.error(f"--replay {args.replay}: no such file")
    if args.mp4 is not None:
        args.sequence = True
    if args.sequence:
        args.closeup = False
    if args.fps < 1:
        p.error(f"--fps: expected >= 1, got {args.fps}")
    return args


def frames_to_mp4(frames: list, out: Path, fps: int = 10) -> Path:
    """Encode PNG ``frames`` (same size, in order) into an H.264 MP4 ``out`` with Blender's
    FFmpeg (the video sequencer of a scratch scene; the current scene is left as it was).

    Raises:
        ValueError: no frames.
    """
    if not frames:
        raise ValueError("frames_to_mp4: no frames to encode")
    first = bpy.data.images.load(str(frames[0]))
    w, h = first.size
    bpy.data.images.remove(first)
    sc = bpy.data.scenes.new("ISAC_MP4")
    try:
        ed = sc.sequence_editor_create()
        strips = ed.strips if hasattr(ed, "strips") else ed.sequences
        strip = strips.new_image("frames", str(frames[0]), channel=1, frame_start=1)
        for f in frames[1:]:
            strip.elements.append(Path(f).name)
        strip.directory = str(Path(frames[0]).parent) + "/"
        r = sc.render
        r.resolution_x, r.resolution_y, r.resolution_percentage = w, h, 100
        r.fps = int(fps)
        sc.frame_start, sc.frame_end = 1, len(frames)
        if hasattr(r.image_settings, "media_type"):  # Blender 5: pick video before FFmpeg
            r.image_settings.media_type = "VIDEO"
        r.image_settings.file_format = "FFMPEG"
        r.ffmpeg.format = "MPEG4"
        r.ffmpeg.codec = "H264"
        r.ffmpeg.constant_rate_factor = "HIGH"
        r.use_sequencer = True
        r.filepath = str(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.unlink(missing_ok=True)
        with bpy.context.temp_override(scene=sc):
            bpy.ops.render.render(animation=True, scene=sc.name)
    finally:
        bpy.data.scenes.remove(sc)
    # Blender appends the frame range to a movie's name when the path has no '#'
    if not out.is_file():
        made = sorted(out.parent.glob(out.stem + "*" + out.suffix))
        if made:
            made[-1].replace(out)
    return out


def room_bounds(scene) -> tuple[Vector, Vector]:
    """World bounding box of the exported geometry (evaluated meshes), m."""
    from addon.exporter import geometry_objects

    dg = bpy.context.evaluated_depsgraph_get()
    pts = [o.evaluated_get(dg).matrix_world @ Vector(c) for o in geometry_objects(scene)
           for c in o.bound_box]
    if not pts:
        return Vector((0.0, 0.0, 0.0)), Vector((1.0, 1.0, 1.0))
    return (Vector([min(p[i] for p in pts) for i in range(3)]),
            Vector([max(p[i] for p in pts) for i in range(3)]))


def setup_camera(scene, resolution, engine: str, samples: int) -> None:
    """Oblique view from the south over the room's geometry (ceiling and the walls along
    the south edge hidden), a sun, a grey world."""
    lo, hi = room_bounds(scene)
    size = hi - lo
    target = (lo + hi) / 2
    target.z = lo.z + 0.5
    cam = bpy.data.objects.new("LiveCamera", bpy.data.cameras.new("LiveCamera"))
    scene.collection.objects.link(cam)
    cam.location = Vector((target.x, lo.y - 0.4 * size.y, lo.z + 1.3 * max(size.x, size.y)))
    cam.rotation_euler = (target - cam.location).to_track_quat("-Z", "Y").to_euler()
    cam.data.lens = 22
    cam.data.clip_end = max(100.0, 4 * size)
    scene.camera = cam
    dg = bpy.context.evaluated_depsgraph_get()
    for obj in scene.objects:
        if obj.type != "MESH" or obj.isac.device_kind != "NONE":
            continue
        if not obj.isac.export_geometry:  # helpers (boolean cutters)
            obj.hide_render = True
            continue
        box = [obj.evaluated_get(dg).matrix_world @ Vector(c) for c in obj.bound_box]
        zmin = min(p.z for p in box)
        ymax = max(p.y for p in box)
        # what blocks the view from the south: the ceiling and the walls along the south edge
        if zmin >= lo.z + 0.5 * size.z or ymax <= lo.y + 0.05 * size.y:
            obj.hide_render = True
    sun = bpy.data.objects.new("LiveSun", bpy.data.lights.new("LiveSun", "SUN"))
    sun.data.energy = 4.0
    sun.rotation_euler = (math.radians(30), 0.0, math.radians(20))
    scene.collection.objects.link(sun)
    if scene.world is None:
        scene.world = bpy.data.worlds.new("LiveWorld")
    scene.world.color = (0.05, 0.05, 0.06)
    r = scene.render
    r.engine = engine
    r.resolution_x, r.resolution_y = resolution
    r.resolution_percentage = 100
    r.image_settings.file_format = "PNG"
    # the colour maps' own colours (AgX/Filmic desaturate bright emission towards white)
    scene.view_settings.view_transform = "Standard"
    if engine == "CYCLES":
        scene.cycles.device = "CPU"
        scene.cycles.samples = samples
        scene.cycles.use_denoising = True
        scene.cycles.denoiser = "OPENIMAGEDENOISE"
    elif engine == "BLENDER_WORKBENCH":
        scene.display.shading.light = "STUDIO"
        scene.display.shading.color_type = "MATERIAL"


def aim_closeup(scene, robot) -> None:
    """Make a camera 2 m behind and above ``robot`` (looking at it) the scene camera."""
    cam = bpy.data.objects.get("LiveCloseup")
    if cam is None:
        cam = bpy.data.objects.new("LiveCloseup", bpy.data.cameras.new("LiveCloseup"))
        scene.collection.objects.link(cam)
        cam.data.lens = 28
    if robot is None:
        return
    target = robot.location.copy()
    target.z = 0.15
    cam.location = target + Vector((-1.3, -1.3, 1.4))
    cam.rotation_euler = (target - cam.location).to_track_quat("-Z", "Y").to_euler()
    scene.camera = cam


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    import addon
    from addon import live

    bpy.ops.wm.open_mainfile(filepath=str(args.blend))
    if not hasattr(bpy.types.Scene, "isac_live"):
        addon.register()
    scene = bpy.context.scene
    from addon.devices import device_objects

    if not args.robot:
        args.robot = next((o.name for o in device_objects(scene)
                           if o.isac.device_kind == "ROBOT"), "robot1")
    if not args.scene and (args.blend.parent / "scene" / "twin.toml").is_file():
        args.scene = str(args.blend.parent / "scene")
    scene.isac_live.ray_color_mode = args.color
    scene.isac_live.max_paths_per_link = args.rays_per_link
    setup_camera(scene, args.resolution, args.engine, args.samples)
    args.out.mkdir(parents=True, exist_ok=True)
    step_log = args.out / "steps.jsonl"
    step_log.unlink(missing_ok=True)
    extra = ("--radiomap", str(args.radiomap)) if args.radiomap is not None else ()
    if args.replay is not None:
        extra += ("--replay", str(args.replay.resolve()))
    scene.isac_live.radiomap_layer = args.radiomap_layer
    if args.radiomap is not None and args.engine == "BLENDER_WORKBENCH":
        scene.display.shading.color_type = "TEXTURE"  # the map's image (rays turn grey)
    eng = live.EngineProcess(args.python, args.scene,
                             ("--rate", "0", "--paused", "--step-log", str(step_log), *extra))
    session = live.LiveSession(scene, engine=eng)
    p = scene.isac_live

    def wait(pred, what):
        end = time.monotonic() + args.timeout
        while time.monotonic() < end:
            session.tick()
            if pred():
                return
            if session.engine is not None and not session.engine.alive():
                raise RuntimeError(f"the engine exited: {session.engine.log_tail()}")
            time.sleep(0.01)
        raise TimeoutError(f"no {what} within {args.timeout:g} s ({session.client.last_error})")

    written, frames = [], []
    try:
        wait(lambda: session.client.connected and session.applied["scene"], "connection")
        if args.radiomap is not None:
            wait(lambda: session.applied["radiomap"], "radio map")
        for k in range(args.steps):
            session.send_command("step")
            wait(lambda: p.step == k and p.paths_step == k and p.metrics_step == k,
                 f"step {k}")
            if k % args.every == 0 or k == args.steps - 1:
                t0 = time.perf_counter()
                scene.camera = bpy.data.objects["LiveCamera"]
                name = (f"frame_{len(frames) + 1:04d}.png" if args.sequence
                        else f"live_{k:04d}.png")
                scene.render.filepath = str(args.out / name)
                bpy.ops.render.render(write_still=True)
                written.append(scene.render.filepath)
                frames.append(scene.render.filepath)
                if args.closeup:
                    aim_closeup(scene, bpy.data.objects.get(f"ISAC_Live_{args.robot}"))
                    scene.render.filepath = str(args.out / f"live_{k:04d}_{args.robot}.png")
                    bpy.ops.render.render(write_still=True)
                    written.append(scene.render.filepath)
                links = ", ".join(f"{lk.tx}->{lk.rx} {lk.snr_db:.1f} dB" for lk in p.links)
                log.info("step %d: %d rays, %s; rendered %s in %.1f s", k, p.num_rays, links,
                         scene.render.filepath, time.perf_counter() - t0)
    finally:
        session.close()
    if args.mp4 is not None:
        t0 = time.perf_counter()
        written.append(str(frames_to_mp4(frames, args.mp4, args.fps)))
        log.info("encoded %d frames into %s in %.1f s", len(frames), args.mp4,
                 time.perf_counter() - t0)
    print("\n".join(written))
    return 0


if __name__ == "__main__":
    sys.exit(main())
