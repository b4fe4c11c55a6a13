"""The add-on's stdlib-only modules the engine shares: :data:`schema` and :data:`wire`.

``addon/schema.py`` (the scene-folder vocabulary) and ``addon/wire.py`` (the
live link's wire format) are each the one definition of their contract. The
add-on imports them as sibling modules; the engine loads the same files here,
each as a top-level module of its own (``isac_twin_schema``,
``isac_twin_wire``), because importing them as ``addon.schema`` would run
``addon/__init__.py`` (its ``bpy`` glue) and need the repository root on
``sys.path``.

Where the files are:

* a built wheel carries them in ``engine/addon_files/``: ``setup.py`` copies
  them there from ``addon/`` while building (there is no copy in the source
  tree);
* a source checkout (tests, an editable install) has no ``engine/addon_files/``
  and reads them from the repository's ``addon/`` folder beside ``engine/``.

So both sides always run the bytes of the one source file. Standard library
only: every engine layer may import this module.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

__all__ = ["schema", "wire", "shared_dir", "MODULE_NAMES", "PACKAGED_DIR", "SOURCE_DIR"]

#: Engine-side module name of each shared add-on file (``<name>.py``).
MODULE_NAMES = {"schema": "isac_twin_schema", "wire": "isac_twin_wire"}

_HERE = Path(__file__).resolve().parent
#: Where a built wheel carries the shared files (written by setup.py, not in git).
PACKAGED_DIR = _HERE / "addon_files"
#: Where a source checkout has them.
SOURCE_DIR = _HERE.parent / "addon"


def shared_dir() -> Path:
    """The folder the shared files are loaded from: the wheel's copy, else ``addon/``."""
    return PACKAGED_DIR if PACKAGED_DIR.is_dir() else SOURCE_DIR


def _load(name: str):
    mod_name = MODULE_NAMES[name]
    if mod_name in sys.modules:
        return sys.modules[mod_name]
    path = shared_dir() / f"{name}.py"
    if not path.is_file():
        raise ImportError(f"{path}: the add-on's {name}.py is missing (the engine shares it "
                          f"with the add-on; it is in the repository's addon/ folder and in "
                          f"a built wheel's engine/addon_files/)")
    spec = importlib.util.spec_from_file_location(mod_name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[mod_name] = mod
    try:
        spec.loader.exec_module(mod)
    except BaseException:
        del sys.modules[mod_name]
        raise
    return mod


#: ``addon/schema.py``: patterns, polarizations, robot models and bodies, defaults.
schema = _load("schema")
#: ``addon/wire.py``: framing, messages, edit and command ops of the live link.
wire = _load("wire")
