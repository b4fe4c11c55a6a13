#!/usr/bin/env python3
"""ISAC Twin's one entry point: set up, test, run the demo, build the add-on, benchmark.

    python3 build.py demo      # the bundled room end to end -> out/demo/
    python3 build.py test      # the whole test suite
    python3 build.py addon     # dist/isac_twin-<version>.zip, validated by Blender
    python3 build.py bench     # every benchmark under bench/
    python3 build.py setup     # only create/refresh .venv

Each command first creates or refreshes ``.venv`` (Python 3.11) with every
dependency from ``pyproject.toml`` (engine, bpy, device and test extras). A
stamp of the dependency spec makes a second run skip the install. No step
needs root: Dr.Jit's LLVM comes from the ``karellen-llvm-core`` wheel and the
engine points Dr.Jit at it itself.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
STAMP = VENV / ".isac-twin-stamp"
EXTRAS = "dev"
PY = (3, 11)


def fail(msg: str) -> None:
    print(f"build.py: {msg}", file=sys.stderr)
    sys.exit(1)


def venv_python() -> Path:
    return VENV / "bin" / "python"


def find_python311() -> str:
    """An interpreter for the venv: this one if it is 3.11, else python3.11 on PATH."""
    if sys.version_info[:2] == PY:
        return sys.executable
    found = shutil.which("python3.11")
    if found:
        return found
    fail(f"Python 3.11 is required (bpy 5.0 and sionna-rt wheels are built for it), but this "
         f"is Python {sys.version.split()[0]} and no python3.11 is on PATH: install Python "
         "3.11 and run this command again.")
    return ""  # unreachable


def spec_hash() -> str:
    h = hashlib.sha256()
    h.update((ROOT / "pyproject.toml").read_bytes())
    h.update(EXTRAS.encode())
    return h.hexdigest()


def venv_ok() -> bool:
    py = venv_python()
    if not py.exists():
        return False
    out = subprocess.run([str(py), "-c", "import sys; print(sys.version_info[:2] == (3, 11))"],
                         capture_output=True, text=True)
    return out.stdout.strip() == "True"


def setup() -> Path:
    """Create or refresh the virtual environment; return its python."""
    if not venv_ok():
        if VENV.exists():
            print("build.py: .venv is not a Python 3.11 environment; recreating it")
            shutil.rmtree(VENV)
        print(f"build.py: creating {VENV.relative_to(ROOT)} ...", flush=True)
        r = subprocess.run([find_python311(), "-m", "venv", str(VENV)])
        if r.returncode:
            fail("creating the virtual environment failed (is the python3.11 'venv' module "
                 "installed? on Debian: apt-get install python3.11-venv).")
    if STAMP.exists() and STAMP.read_text() == spec_hash():
        return venv_python()
    print("build.py: installing dependencies into .venv (first run takes a few minutes) ...",
          flush=True)
    py = str(venv_python())
    env = dict(os.environ, PIP_DISABLE_PIP_VERSION_CHECK="1")
    r = subprocess.run([py, "-m", "pip", "install", "-q", "--upgrade", "pip"], env=env)
    if r.returncode == 0:
        r = subprocess.run([py, "-m", "pip", "install", "-q", "-e", f".[{EXTRAS}]"], cwd=ROOT,
                           env=env)
    if r.returncode:
        fail(f"installing the dependencies failed (pip exited {r.returncode}); the reason "
             "is in pip's output above.")
    STAMP.write_text(spec_hash())
    return venv_python()


def run(py: Path, *args: str, **kw) -> int:
    return subprocess.run([str(py), *args], cwd=ROOT, **kw).returncode


def cmd_test(py: Path, extra: list[str]) -> int:
    # Arguments go to pytest; the whole tests/ folder unless a path is given.
    paths = [a for a in extra if not a.startswith("-") and (ROOT / a.split("::")[0]).exists()]
    return run(py, "-m", "pytest", *([] if paths else ["tests"]), *extra)


def cmd_demo(py: Path, extra: list[str]) -> int:
    return run(py, "-m", "isac_twin.experiments.demo", *extra)


def blender_ext_script(py: Path) -> Path:
    """Blender's own extension builder/validator, shipped inside the bpy wheel."""
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()"
                                "['purelib'])"], capture_output=True, text=True).stdout.strip())
    found = sorted(site.glob("bpy/*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        fail(f"Blender's extension tool blender_ext.py was not found under {site}/bpy.")
    return found[-1]


def build_addon_zip(py: Path, out_dir: Path = ROOT / "dist") -> Path:
    """Build the add-on extension zip with Blender's builder and validate it.

    Returns the zip's path; exits with a clear message when either step fails.
    """
    tool = blender_ext_script(py)
    out_dir.mkdir(parents=True, exist_ok=True)
    for old in out_dir.glob("isac_twin-*.zip"):
        old.unlink()
    r = subprocess.run([str(py), str(tool), "build", "--source-dir", str(ROOT / "addon"),
                        "--output-dir", str(out_dir)], capture_output=True, text=True)
    zips = sorted(out_dir.glob("isac_twin-*.zip"))
    if r.returncode or not zips:
        fail(f"building the add-on failed:\n{r.stdout}{r.stderr}")
    v = subprocess.run([str(py), str(tool), "validate", str(zips[0])], capture_output=True,
                       text=True)
    if v.returncode:
        fail(f"Blender's validator rejected {zips[0].name}:\n{v.stdout}{v.stderr}")
    return zips[0]


def cmd_addon(py: Path, extra: list[str]) -> int:
    z = build_addon_zip(py)
    print(f"built and validated {z.relative_to(ROOT)}")
    return 0


def cmd_bench(py: Path, extra: list[str]) -> int:
    benches = sorted((ROOT / "bench").glob("bench_*.py"))
    if extra:
        benches = [b for b in benches if any(e in b.name for e in extra)]
    status = 0
    for b in benches:
        print(f"\n=== {b.name} ===", flush=True)
        status |= run(py, str(b))
    return status


COMMANDS = {"test": cmd_test, "demo": cmd_demo, "addon": cmd_addon, "bench": cmd_bench,
            "setup": lambda py, extra: 0}


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in COMMANDS:
        print(__doc__)
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    py = setup()
    return COMMANDS[argv[0]](py, argv[1:])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
