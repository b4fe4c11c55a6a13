"""Point Dr.Jit at an LLVM it can use, before Mitsuba is first imported.

Dr.Jit 1.5 crashes with LLVM 15 ("Cannot select ... fmaximum") and works with
LLVM >= 19. The PyPI wheel ``karellen-llvm-core`` (a dependency) installs
``libLLVM.so.23.1`` into the environment's ``lib/`` folder, so no root install is
needed: it is found through the installed distribution's own file list (wherever
pip put it: a venv, ``--user``, ``--target``), then under the interpreter's
prefixes; Debian's ``libllvm19`` or newer is the fallback. An older system LLVM is
never chosen.
"""

from __future__ import annotations

import glob
import os
import sys
from importlib import metadata
from pathlib import Path

ENV_VAR = "DRJIT_LIBLLVM_PATH"


def candidate_paths() -> list[Path]:
    """LLVM shared libraries to try, best first."""
    found: list[Path] = []
    try:
        dist = metadata.distribution("karellen-llvm-core")
        found += sorted(Path(dist.locate_file(f)).resolve() for f in dist.files or ()
                        if f.name.startswith("libLLVM.so."))
    except metadata.PackageNotFoundError:
        pass
    for prefix in dict.fromkeys([sys.prefix, sys.base_prefix]):
        lib = Path(prefix) / "lib"
        found += sorted(Path(p) for p in glob.glob(str(lib / "libLLVM.so.*")))
        found += sorted(Path(p) for p in glob.glob(str(lib / "libLLVM-*.so")))
    for ver in (23, 22, 21, 20, 19):
        found += [Path(f"/usr/lib/llvm-{ver}/lib/libLLVM.so.1"),
                  Path(f"/usr/lib/llvm-{ver}/lib/libLLVM-{ver}.so")]
    return [p for p in found if p.is_file()]


def configure_llvm() -> str | None:
    """Set ``DRJIT_LIBLLVM_PATH`` when unset; return the path in effect.

    A value the user set is never overridden.
    """
    current = os.environ.get(ENV_VAR)
    if current:
        return current
    paths = candidate_paths()
    if not paths:
        return None
    os.environ[ENV_VAR] = str(paths[0])
    return str(paths[0])
