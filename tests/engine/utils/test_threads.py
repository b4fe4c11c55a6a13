"""engine/utils/threads.py: a process that runs the twin runs BLAS on one thread."""

import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]

# In a fresh process: numpy's OpenBLAS starts on every core (2 on CI), the
# twin's first step (or a PHY call) puts every loaded BLAS on one thread for
# good, also a library loaded later (scipy's own OpenBLAS).
_SCRIPT = textwrap.dedent("""
    import numpy as np
    from threadpoolctl import threadpool_info
    from isac_twin.utils.threads import one_blas_thread

    def blas():
        return sorted(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")

    before = blas()
    one_blas_thread()
    after = blas()
    import scipy.linalg  # brings its own BLAS
    loaded = blas()
    one_blas_thread()
    print(before, after, loaded, blas())
""")


def test_one_blas_thread_for_every_loaded_library_and_later_ones():
    r = subprocess.run([sys.executable, "-c", _SCRIPT], cwd=ROOT, capture_output=True,
                       text=True, timeout=120,
                       env={"PATH": "/usr/bin:/bin", "OPENBLAS_NUM_THREADS": "2"})
    assert r.returncode == 0, r.stderr
    before, after, loaded, final = (eval(x + "]") for x in r.stdout.strip()[:-1].split("] "))
    assert before == [2] and after == [1]
    assert len(loaded) == 2 and max(loaded) == 2 and final == [1, 1]
