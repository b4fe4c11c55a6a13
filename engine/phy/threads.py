"""BLAS on one thread while the twin steps.

The PHY's linear algebra is many small matrices (per resource element a
``[Nr, Nt]`` channel, e.g. 2 x 32; eq. 4 a ``[N, L] @ [L, M]`` product of a
few MFLOP). On them a multi-threaded BLAS only adds the hand-offs and the
spinning of its idle threads: numpy's OpenBLAS on 2 threads made the lab's
4-robot PHY take 20.4 ms per step against 11.9 ms on one, and its spinning
threads cost 4.6 s of system CPU in 200 steps (0.45 s on one), CPU that a radar
frame beside the steps needs (issue #19, measured with ``isac-twin run --timing``).
"""

from __future__ import annotations

import sys

__all__ = ["one_blas_thread"]

#: (number of modules imported when made, threadpoolctl.ThreadpoolController)
_CONTROLLER: tuple | None = None


def one_blas_thread():
    """A context manager in which the BLAS libraries loaded in this process run
    on one thread (``threadpoolctl``); the previous limits come back on exit.
    The libraries are looked up again after new imports (e.g. scipy brings its
    own OpenBLAS); a lookup costs ~1 ms, a limit ~20 us."""
    global _CONTROLLER
    if _CONTROLLER is None or _CONTROLLER[0] != len(sys.modules):
        from threadpoolctl import ThreadpoolController

        _CONTROLLER = (len(sys.modules), ThreadpoolController())
    return _CONTROLLER[1].limit(limits=1, user_api="blas")
