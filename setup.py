"""Build step (everything else is in pyproject.toml): ship the add-on's shared files.

The engine shares two stdlib-only files with the Blender add-on,
``addon/schema.py`` and ``addon/wire.py`` (see ``engine/addon_shared.py``).
They live once, in ``addon/``; a wheel packages only ``engine*``, so while
building, this copies them into the built package as ``engine/addon_files/``,
where ``engine.addon_shared`` looks first. The source tree never holds a
copy, and an editable install keeps reading ``addon/``.
"""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
#: The add-on files the engine loads (engine.addon_shared.MODULE_NAMES).
SHARED_FILES = ("schema.py", "wire.py")
PACKAGED_DIR = ("engine", "addon_files")


class BuildPyWithAddonFiles(build_py):
    """``build_py`` that also copies :data:`SHARED_FILES` into ``engine/addon_files/``."""

    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):
            return  # an editable install reads addon/ in place
        dest = Path(self.build_lib).joinpath(*PACKAGED_DIR)
        self.mkpath(str(dest))
        for name in SHARED_FILES:
            src = ROOT / "addon" / name
            if not src.is_file():
                raise SystemExit(f"setup.py: {src} is missing: the engine package needs the "
                                 f"add-on's {name} (build from a full checkout or sdist)")
            self.copy_file(str(src), str(dest / name))

    def get_outputs(self, include_bytecode=True):
        out = super().get_outputs(include_bytecode)
        if getattr(self, "editable_mode", False):
            return out
        dest = Path(self.build_lib).joinpath(*PACKAGED_DIR)
        return out + [str(dest / n) for n in SHARED_FILES]


setup(cmdclass={"build_py": BuildPyWithAddonFiles})
