"""MCA query speed on a full fingerprint database, against brute-force scoring.

Uses the cached database of the bundled lab (``out/cache``; the finest one
found, 5 cm if it has been built, e.g. by ``python -m isac_twin.experiments.demo --spacing
0.05``) and, for the paper's size whatever is cached, a synthetic database of
the 5 cm grid of an 8 x 6 m room (19,200 points, image-source path lengths).
Queries are database fingerprints with 2 cm Gaussian length noise and one
missed path, J = 9 measured paths per AP. The brute-force baseline scores
every point exactly (``MCALocalizer.exact_scores`` over all points + top-k) in
the same run; the two must agree on the k best scores. Goal: <= 2 ms/query.

    .venv/bin/python bench/bench_mca.py [--queries N] [--db FILE]
"""

from __future__ import annotations

import argparse
import glob
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from isac_twin.localization.fingerprints import load_database  # noqa: E402
from isac_twin.localization.mca import MCALocalizer  # noqa: E402


def synthetic_db(nx=160, ny=120, aps=((0.05, 3.0, 2.0), (4.0, 0.05, 2.0)), L=9):
    """A 5 cm grid of an 8 x 6 x 3 m room: LOS + 6 first-order image sources + 2 second-order."""
    xs, ys = np.meshgrid(0.025 + 0.05 * np.arange(nx), 0.025 + 0.05 * np.arange(ny),
                         indexing="ij")
    pos = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.25)], axis=1)
    lengths = np.full((len(pos), len(aps), L), np.nan)
    for a, ap in enumerate(aps):
        ap = np.array(ap)
        ims = [ap, ap * [-1, 1, 1], [16 - ap[0], ap[1], ap[2]], ap * [1, -1, 1],
               [ap[0], 12 - ap[1], ap[2]], ap * [1, 1, -1], [ap[0], ap[1], 6 - ap[2]],
               [-ap[0], -ap[1], ap[2]], [16 - ap[0], 12 - ap[1], ap[2]]]
        d = np.stack([np.linalg.norm(pos - np.array(im), axis=1) for im in ims[:L]], axis=1)
        lengths[:, a, :d.shape[1]] = d
    return pos, lengths


def bench(name, pos, lengths, queries: int, k: int, eps: float, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    t = time.perf_counter()
    loc = MCALocalizer(pos, lengths, eps=eps, k=k)
    build = time.perf_counter() - t
    idx = rng.choice(len(pos), size=queries, replace=False)
    meas = []
    for i in idx:
        m = lengths[i] + rng.normal(0, 0.02, lengths[i].shape)
        m[:, rng.integers(0, lengths.shape[2])] = np.nan
        meas.append(m)
    loc(meas[0])  # warm-up
    t = time.perf_counter()
    ests = [loc(m) for m in meas]
    fast = (time.perf_counter() - t) / queries
    all_idx = np.arange(len(pos))
    t = time.perf_counter()
    brute = []
    for m in meas:
        s = loc.exact_scores(loc._check_measured(m), all_idx)
        top = np.argpartition(-s, k - 1)[:k]
        brute.append(np.sort(s[top])[::-1])
    slow = (time.perf_counter() - t) / queries
    agree = all(np.allclose(e.best_scores, b, rtol=1e-9) for e, b in zip(ests, brute))
    err = np.median([np.linalg.norm(e.position[:2] - pos[i, :2]) for e, i in zip(ests, idx)])
    scored = np.mean([e.candidates_scored for e in ests])
    print(f"{name}: {len(pos)} points x {lengths.shape[1]} APs x {lengths.shape[2]} paths; "
          f"table built in {build:.2f} s")
    print(f"  branch and bound: {1e3 * fast:.3f} ms/query (exact scores for {scored:.0f} "
          f"points on average); brute force: {1e3 * slow:.2f} ms/query; "
          f"speed-up x{slow / fast:.1f}; same top-{k}: {agree}; median error "
          f"{100 * err:.1f} cm")
    return {"ms_per_query": 1e3 * fast, "brute_ms": 1e3 * slow, "agree": agree}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--db", type=Path, default=None, help="a fingerprint database file")
    ap.add_argument("--num-paths", type=int, default=9)
    ap.add_argument("-k", type=int, default=4)
    ap.add_argument("--eps", type=float, default=0.5)
    a = ap.parse_args(argv)
    files = [a.db] if a.db else sorted(
        (Path(p) for p in glob.glob(str(ROOT / "out" / "cache" / "*.npz"))),
        key=lambda p: float(p.stem.rsplit("-", 1)[1].rstrip("cm")))
    ok = True
    if files:
        db = load_database(files[0])
        free = db.free_indices
        r = bench(f"{files[0].name} ({100 * db.spacing:g} cm grid of the lab)", db.points[free],
                  db.lengths[free][:, :, :a.num_paths], min(a.queries, len(free)), a.k, a.eps)
        ok &= r["agree"]
    else:
        print("no cached lab database in out/cache (run python -m isac_twin.experiments.demo first)")
    pos, lengths = synthetic_db(L=a.num_paths)
    r = bench("synthetic 5 cm grid of an 8 x 6 m room", pos, lengths, a.queries, a.k, a.eps)
    ok &= r["agree"]
    print(f"goal <= 2 ms/query on the 5 cm grid: "
          f"{'met' if r['ms_per_query'] <= 2.0 else 'NOT met'} ({r['ms_per_query']:.2f} ms)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
