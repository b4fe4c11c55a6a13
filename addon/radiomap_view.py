"""Show a ``radiomap`` message in Blender: a coloured plane on the floor and its colour scale.

Plain functions (the Live panel's operators and the live session call them;
tests call them under headless ``bpy``). Objects live in the live view's
collection and are named ``ISAC_Live_RadioMap*``:

* ``ISAC_Live_RadioMap``: one quad at the map's height covering its cells,
  textured with the image ``ISAC_Live_RadioMap`` (one pixel per cell, nearest
  filtering, cells without a value transparent), emissive so that Cycles,
  EEVEE and Workbench show the same colours;
* ``ISAC_Live_RadioMapLegend``: the colour bar (a horizontal bar in front of
  the map's south edge) with text objects for the layer and unit (``..._Title``), the scale's
  ends (``..._Min``, ``..._Max``) and its middle (``..._Mid``);
* access points of the map marked as small cones with a name label
  (:func:`legend.mark_access_point`; the live view marks them from the
  ``scene`` message too).

Pixel ``(ix, iy)`` of the image is cell ``(iy, ix)`` of the message (Blender's
image rows start at the bottom, the map's rows at its smallest y).
"""

from __future__ import annotations

import bpy

from . import legend
from .live_view import COLLECTION, PREFIX

MAP = PREFIX + "RadioMap"
LEGEND = PREFIX + "RadioMapLegend"
#: Default layer shown: the best server's RSS.
DEFAULT_LAYER = "best"
#: Colour-map stops (t, RGB), perceptually ordered (viridis-like): weak -> strong.
MAP_STOPS = ((0.0, (0.267, 0.005, 0.329)), (0.25, (0.230, 0.322, 0.546)),
             (0.5, (0.128, 0.567, 0.551)), (0.75, (0.369, 0.789, 0.383)),
             (1.0, (0.993, 0.906, 0.144)))
#: Gap between the map's south edge and its legend bar, m.
LEGEND_GAP_M = 0.35


def map_color(t: float) -> tuple[float, float, float]:
    """RGB of ``t`` in [0, 1] on :data:`MAP_STOPS` (clipped)."""
    t = min(1.0, max(0.0, t))
    for (t0, c0), (t1, c1) in zip(MAP_STOPS, MAP_STOPS[1:]):
        if t <= t1:
            u = (t - t0) / (t1 - t0)
            return (c0[0] + u * (c1[0] - c0[0]), c0[1] + u * (c1[1] - c0[1]),
                    c0[2] + u * (c1[2] - c0[2]))
    return MAP_STOPS[-1][1]


def layer(msg: dict, name: str) -> dict:
    """The layer ``name`` of a ``radiomap`` message.

    Raises:
        KeyError: naming the layers the message has.
    """
    for lay in msg["layers"]:
        if lay["name"] == name:
            return lay
    raise KeyError(f"radio map has no layer {name!r} (layers: "
                   f"{', '.join(x['name'] for x in msg['layers'])})")


#: Colour-table entries of :func:`layer_pixels` (values are quantized to 1/255 of the scale,
#: as fine as an 8-bit image holds them).
_LUT = [(*map_color(k / 255), 1.0) for k in range(256)]
_NONE = (0.0, 0.0, 0.0, 0.0)


def layer_pixels(lay: dict) -> list[float]:
    """Flat RGBA ``[ny * nx * 4]`` of a layer on its own scale (``vmin``..``vmax``);
    cells without a value (null) are transparent."""
    lo, hi = float(lay["vmin"]), float(lay["vmax"])
    k = 255.0 / ((hi - lo) or 1.0)
    lut, none = _LUT, _NONE
    out: list[float] = []
    ext = out.extend
    for v in lay["values"]:
        if v is None:
            ext(none)
        else:
            i = int((v - lo) * k + 0.5)
            ext(lut[0 if i < 0 else 255 if i > 255 else i])
    return out


def show_layer(scene, msg: dict, name: str | None = None, *, visible: bool = True) -> str:
    """Build or update the map plane, its image and the legend for layer ``name``
    (default :data:`DEFAULT_LAYER`, else the first). Returns the layer shown.

    Raises:
        KeyError: the message has no layer ``name``.
    """
    if name is None or name == "":
        names = [x["name"] for x in msg["layers"]]
        name = DEFAULT_LAYER if DEFAULT_LAYER in names else names[0]
    lay = layer(msg, name)
    ny, nx = msg["shape"]
    c = float(msg["cell_size"])
    ox, oy = msg["origin"]
    x0, y0 = ox - c / 2, oy - c / 2
    x1, y1 = x0 + nx * c, y0 + ny * c
    z = float(msg["height"])
    img = legend.image(MAP, nx, ny)
    img.pixels.foreach_set(layer_pixels(lay))
    img.update()
    plane = legend.quad(scene, MAP, x0, y0, x1, y1, z, legend.textured_material(MAP, img))
    plane["isac_layer"] = name
    plane["isac_scene_hash"] = msg["scene_hash"]
    # legend: a horizontal colour bar in front of the map's south edge (what an overview
    # camera from the south sees)
    lo, hi = float(lay["vmin"]), float(lay["vmax"])
    what = {"dBm": "RSS", "dB": "SINR" if name == "sinr" else "gain"}.get(lay["unit"], "")
    title = f"{'best server' if name == 'best' else name} {what} ({lay['unit']})"
    legend.colour_bar(scene, LEGEND, map_color, lo, hi, title,
                      (x0, y0 - LEGEND_GAP_M - legend.BAR_SIZE_M[1], z),
                      length=min(legend.BAR_SIZE_M[0], max(x1 - x0, 1.0)))
    for t in msg.get("tx", []):
        legend.mark_access_point(scene, t["name"], t["position"],
                                 toward=((x0 + x1) / 2, (y0 + y1) / 2))
    set_visible(scene, visible)
    return name


def radiomap_objects(scene) -> list:
    """The map and its legend objects that exist now."""
    coll = bpy.data.collections.get(COLLECTION)
    if coll is None:
        return []
    return [o for o in coll.objects if o.name.startswith(MAP)]


def set_visible(scene, visible: bool) -> None:
    """Show or hide the map and its legend (viewport and render)."""
    for o in radiomap_objects(scene):
        if o.hide_viewport == visible or o.hide_render == visible:
            o.hide_viewport = not visible
            o.hide_render = not visible


def apply_radiomap(scene, msg: dict, view) -> None:
    """``radiomap``: keep the message on the view (layer switches need it), show the layer
    the panel selects."""
    view.radiomap = msg
    p = getattr(scene, "isac_live", None)
    want = p.radiomap_layer if p is not None else None
    names = [x["name"] for x in msg["layers"]]
    if want not in names:
        want = None
    shown = show_layer(scene, msg, want,
                       visible=p.show_radiomap if p is not None else True)
    if p is not None:
        if p.radiomap_layer != shown:
            p.radiomap_layer = shown
        joined = ",".join(names)
        if p.radiomap_layers != joined:
            p.radiomap_layers = joined


def select_layer(scene, view, name: str) -> str:
    """Show layer ``name`` of the view's last radio map (the panel's layer buttons).

    Raises:
        KeyError: no radio map received yet, or no such layer.
    """
    msg = getattr(view, "radiomap", None)
    if msg is None:
        raise KeyError("no radio map received yet (start the engine with serve --radiomap)")
    layer(msg, name)
    p = getattr(scene, "isac_live", None)
    if p is not None and p.radiomap_layer != name:
        p.radiomap_layer = name
    return show_layer(scene, msg, name, visible=p.show_radiomap if p is not None else True)
