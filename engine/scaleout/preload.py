"""Worker start-up: import the tracer stack when a Dask worker process starts.

A worker's first tile otherwise pays for importing Sionna RT (Mitsuba, Dr.Jit
and its LLVM back end): about 1 s on the 2-core development machine, 3 s
under load, out of a ~1.6 s tile. Every worker pays it at once, so on a local
cluster it is time during which no worker traces, the same for 1 and for N
workers (it lowers the N-vs-1 speed-up). Imported at worker start, it is part
of starting the worker instead, which a long-lived cluster pays once for all
grids.

:func:`isac_twin.scaleout.cluster.cluster_client` starts local workers with this
preload; on a cluster of your own, give it to every worker::

    dask worker tcp://head:8786 --nworkers 1 --nthreads 1 --preload isac_twin.scaleout.preload

(without it the tiles are the same, the first one only slower). Dask calls
:func:`dask_setup` with the worker after importing this module.
"""

from __future__ import annotations

import logging
import time

from .tiles import DEFAULT_WORKER_THREADS

log = logging.getLogger(__name__)


def warm(threads: int = DEFAULT_WORKER_THREADS) -> float:
    """Import Sionna RT and the tracer modules, set Dr.Jit's thread count.

    Args:
        threads: Dr.Jit worker threads of this process (a tile's
            :class:`~isac_twin.scaleout.tiles.TileJob` sets its own again).

    Returns:
        Seconds it took.
    """
    t = time.perf_counter()
    import drjit as dr

    from ..raytrace import chains, grid, solver_core  # noqa: F401
    from ..scene.twin_scene import load_scene  # noqa: F401

    solver_core.load_sionna_rt()
    dr.set_thread_count(int(threads))
    return time.perf_counter() - t


def dask_setup(worker) -> None:
    """Dask's preload hook: :func:`warm` in the worker process."""
    log.info("worker %s: tracer stack imported in %.2f s", worker.address, warm())
