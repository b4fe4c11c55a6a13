"""Benchmark: what the free-space placement check (engine/scene/room.py) adds to loading a scene.

For each bundled room, times ``load_scene(..., load_sionna=False)`` (parse
twin.toml and scene.xml, read every PLY, bounds and placement checks) and,
in the same run, ``check_placement`` alone and the Mitsuba scene load that
every traced command adds on top, and prints the check's share of each.
No assertions on time.

Run: ``python bench/bench_placement.py [--repeat 5]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from isac_twin import (
    bundled_scene_dir,  # noqa: E402
    load_scene,  # noqa: E402
)
from isac_twin.scene.room import check_placement, robot_path_points  # noqa: E402


def best(fn, repeat: int) -> float:
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return min(ts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    a = ap.parse_args(argv)
    for name in ("aces_lab", "l_office"):
        folder = bundled_scene_dir(name)
        scene = load_scene(folder, load_sionna=False)
        npts = sum(len(p[0]) for d in scene.config.devices
                   if (p := robot_path_points(d)) is not None)
        t_check = best(lambda: check_placement(scene), a.repeat)
        t_load = best(lambda: load_scene(folder, load_sionna=False), a.repeat)
        t_mi = best(lambda: load_scene(folder).sionna, max(1, a.repeat // 2))
        print(f"{name}: {len(scene.objects)} objects, {len(scene.config.devices)} devices, "
              f"{npts} path points; check {1e3 * t_check:.1f} ms, load without Mitsuba "
              f"{1e3 * t_load:.1f} ms (check = {t_check / t_load:.2f} of it), load with "
              f"Mitsuba {1e3 * t_mi:.1f} ms (check = {t_check / t_mi:.3f} of it)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
