"""engine.addon_shared: the engine runs the add-on's own schema.py and wire.py, from a
source checkout and from a built wheel."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest

from engine import addon_shared

ROOT = Path(__file__).resolve().parents[2]
ADDON = ROOT / "addon"


def test_checkout_loads_the_addon_files_themselves():
    assert addon_shared.shared_dir() == ADDON
    assert not addon_shared.PACKAGED_DIR.exists(), (
        f"{addon_shared.PACKAGED_DIR} exists in the source tree: it would shadow addon/ "
        "(only a built wheel has it)")
    for name, mod in (("schema", addon_shared.schema), ("wire", addon_shared.wire)):
        assert Path(mod.__file__).resolve() == ADDON / f"{name}.py"
        assert mod.__name__ == addon_shared.MODULE_NAMES[name]
        assert sys.modules[mod.__name__] is mod


def test_protocol_uses_the_shared_wire():
    from engine.live import protocol

    assert protocol.wire is addon_shared.wire


def _copy_sources(dest: Path, *, with_addon: bool = True) -> None:
    """The files a checkout holds for building: no caches, no earlier build output."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "addon_files", "*.egg-info")
    for name in ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md"):
        shutil.copy2(ROOT / name, dest / name)
    shutil.copytree(ROOT / "engine", dest / "engine", ignore=ignore)
    if with_addon:
        shutil.copytree(ADDON, dest / "addon", ignore=ignore)


def _clean_python(tmp_path: Path) -> Path:
    """A fresh venv's interpreter (no pip, no site-packages of ours)."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    return venv / "bin" / "python"


def test_engine_without_the_addon_files_names_what_is_missing(tmp_path):
    """An engine copied alone (no addon/ beside it, no packaged copy) fails at import with
    the path it looked for, not with an AttributeError later."""
    src = tmp_path / "src"
    src.mkdir()
    _copy_sources(src, with_addon=False)
    r = subprocess.run([sys.executable, "-I", "-c",
                        f"import sys; sys.path.insert(0, {str(src)!r}); import engine.addon_shared"],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode != 0
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("ImportError: ") and str(src / "addon" / "schema.py") in last, last
    assert "is missing" in last


@pytest.mark.slow
def test_built_wheel_imports_protocol_in_a_clean_venv(tmp_path):
    """``pip wheel .`` builds a wheel whose ``engine.live.protocol`` imports and works in a
    fresh venv that has only the wheel and the third-party dependencies (no repository)."""
    src = tmp_path / "src"
    src.mkdir()
    _copy_sources(src)
    dist = tmp_path / "dist"
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "-w",
                        str(dist)], capture_output=True, text=True, cwd=src)
    assert r.returncode == 0, r.stdout + r.stderr
    (whl,) = dist.glob("isac_twin-*.whl")
    with zipfile.ZipFile(whl) as z:
        names = set(z.namelist())
        for name in ("schema", "wire"):  # one source: the wheel's bytes are addon/'s
            assert z.read(f"engine/addon_files/{name}.py") == (ADDON / f"{name}.py").read_bytes()
        z.extractall(tmp_path / "site")
    assert not any(n.startswith("addon/") for n in names)
    assert not (src / "engine" / "addon_files").exists(), "the build wrote into the sources"

    import numpy

    deps = Path(numpy.__file__).resolve().parents[1]  # third-party packages only, no .pth run
    script = textwrap.dedent(f"""
        import json, sys
        sys.path.insert(0, {str(tmp_path / "site")!r})
        sys.path.append({str(deps)!r})
        import engine, engine.config
        from engine.live import protocol
        w = protocol.wire
        msg = w.edit("move", "Table_1", position=(1, 2, 0.5))
        (back,) = w.Decoder("v2e").feed(w.encode(msg))
        print(json.dumps({{"engine": engine.__file__, "wire": w.__file__,
                          "schema": sys.modules["isac_twin_schema"].__file__,
                          "patterns": list(engine.config.PATTERNS),
                          "edit": protocol.edit_from_message(back).target}}))
    """)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    r = subprocess.run([str(_clean_python(tmp_path)), "-I", "-c", script], capture_output=True,
                       text=True, cwd=tmp_path, env=env)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    site = str(tmp_path / "site")
    assert out["engine"].startswith(site)
    assert out["wire"] == str(tmp_path / "site" / "engine" / "addon_files" / "wire.py")
    assert out["schema"] == str(tmp_path / "site" / "engine" / "addon_files" / "schema.py")
    assert out["patterns"] == list(addon_shared.schema.PATTERNS)
    assert out["edit"] == "Table_1"
