"""BLAS on one thread in a process that runs the twin.

The PHY's linear algebra is many small matrices (per resource element a
``[Nr, Nt]`` channel, e.g. 2 x 32; eq. 4 a ``[N, L] @ [L, M]`` product of a
few MFLOP). On them a multi-threaded BLAS only adds the hand-offs and the
spinning of its idle threads: numpy's OpenBLAS on 2 threads made the lab's
4-robot PHY take 20.4 ms per step against 11.9 ms on one, and its spinning
threads cost 4.6 s of system CPU in 200 steps (0.45 s on one), CPU that a radar
frame beside the steps needs (issue #19, measured with ``isac-twin run --timing``).

The setting is for the rest of the process, not a context restored after each
call: BLAS's thread count is global, so a radar frame computed on a worker
thread would otherwise run on one or two BLAS threads depending on whether the
stepping thread was inside a step, and its float32 results would differ in
the last bits from the synchronous radar's.
"""

from __future__ import annotations

import sys

__all__ = ["one_blas_thread"]

#: ``len(sys.modules)`` when the loaded BLAS libraries were last set
_SEEN: int | None = None


def one_blas_thread() -> None:
    """Put every BLAS library loaded in this process on one thread
    (``threadpoolctl``), for the rest of the process. Called by every twin step,
    PHY call and radar frame; it looks the libraries up again only after new
    imports (e.g. scipy brings its own OpenBLAS): ~4 ms then, ~1 us otherwise."""
    global _SEEN
    n = len(sys.modules)
    if n == _SEEN:
        return
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    _SEEN = len(sys.modules)
