"""A radio map as a figure a person can read: one panel per access point (RSS, dBm) plus the
best server's SINR (dB), each with a colour bar, access points marked and labelled, and the
footprints of the objects the map plane cuts drawn in plan."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .radio_map import RadioMap

#: Colour scale of RSS panels, dB below the strongest cell (cells below are clipped).
RSS_RANGE_DB = 60.0


def cut_footprints(scene, height: float) -> list[tuple[float, float, float, float]]:
    """``(x0, y0, x1, y1)`` m of every object whose bounding box the plane ``z = height`` cuts
    (walls and furniture in plan; floor and ceiling slabs excluded)."""
    out = []
    for o in scene.objects.values():
        lo, hi = o.bounds_min, o.bounds_max
        if lo[2] <= height <= hi[2]:
            out.append((lo[0], lo[1], hi[0], hi[1]))
    return out


def save_radio_map_png(rm: RadioMap, path: str | Path, *, footprints=(), dpi: int = 110
                       ) -> Path:
    """Write the figure to ``path`` (PNG); return the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    names = rm.tx_names
    rss = rm.rss_dbm
    finite = rss[np.isfinite(rss)]
    vmax = float(np.ceil(finite.max())) if finite.size else 0.0
    vmin = vmax - RSS_RANGE_DB
    panels = [(f"{n}: RSS (dBm)", rss[i], "viridis", vmin, vmax) for i, n in enumerate(names)]
    sinr = rm.sinr_db
    sf = sinr[np.isfinite(sinr)]
    panels.append(("best server SINR, full reuse (dB)", sinr, "magma",
                   float(np.floor(sf.min())) if sf.size else -10.0,
                   float(np.ceil(sf.max())) if sf.size else 40.0))
    ext = rm.extent()
    w = ext[1] - ext[0]
    h = ext[3] - ext[2]
    ncol = len(panels)
    fig, axes = plt.subplots(1, ncol, figsize=(4.2 * ncol, 4.2 * h / w + 1.2), squeeze=False)
    for ax, (title, img, cmap, lo, hi) in zip(axes[0], panels):
        shown = np.where(np.isfinite(img), img, np.nan)
        im = ax.imshow(shown, origin="lower", extent=ext, cmap=cmap, vmin=lo, vmax=hi,
                       interpolation="nearest")
        for (x0, y0, x1, y1) in footprints:
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, lw=0.6,
                                   ec="0.85"))
        for n, p in zip(names, rm.tx_positions):
            ax.plot(p[0], p[1], marker="^", ms=9, mfc="red", mec="white")
            ax.annotate(n, (p[0], p[1]), xytext=(4, 4), textcoords="offset points",
                        color="white", fontsize=9, weight="bold",
                        bbox={"fc": "black", "alpha": 0.5, "pad": 1, "lw": 0})
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        fig.colorbar(im, ax=ax, shrink=0.8, label=title.split(": ")[-1])
    m = rm.meta
    fig.suptitle(f"{m.get('scene', '')}: radio map at z = {rm.height:.2f} m, "
                 f"{rm.cell_size:g} m cells, {m.get('frequency_hz', 0) / 1e9:g} GHz, "
                 f"isotropic antennas", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
