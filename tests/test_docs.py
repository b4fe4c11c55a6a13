"""The user docs stay true: README.md, CONTRIBUTING.md, CHANGELOG.md, docs/*.md and the bundled
rooms' READMEs.

Checked here: the README's length and its two commands; no issue numbers; every
``isac_twin.<module path>`` named resolves; every relative link (and its #anchor), every
repository path in backticks and every test named exists; the README's Python and ``bpy``
examples run as written (the ``bpy`` one in a fresh interpreter with a scratch
``BLENDER_USER_RESOURCES``, its scene folder then loaded by the engine); the README's command
table lists every command of ``isac-twin --help``.
"""

from __future__ import annotations

import importlib
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted([README, ROOT / "CONTRIBUTING.md", ROOT / "CHANGELOG.md",
               *(ROOT / "docs").glob("*.md"), *(ROOT / "blend_scenes").glob("*/README.md")])
MAX_README_LINES = 150

ISSUE = re.compile(r"\b[Ii]ssues?\s*#?\d|#\d")
MODULE_PATH = re.compile(r"(?<![\w.])isac_twin(?:\.[A-Za-z_]\w*)+")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.M | re.S)
# Repository paths in backticks, e.g. `engine/scene/room.py` or `blend_scenes/aces_lab/`.
REPO_PATH = re.compile(r"`((?:engine|addon|bench|tests|blend_scenes|docs)/[\w./-]*)`")


def doc_ids():
    return [str(p.relative_to(ROOT)) for p in DOCS]


def section(text: str, heading: str) -> str:
    """The text under a ``## heading`` up to the next ``## `` heading."""
    m = re.search(rf"^## {re.escape(heading)}\n(.*?)(?=^## |\Z)", text, re.M | re.S)
    assert m, f"README.md has no section '## {heading}'"
    return m.group(1)


def fenced(text: str, lang: str) -> list[str]:
    return [body for kind, body in FENCE.findall(text) if kind == lang]


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = FENCE.sub("", path.read_text())
    return {slug(h) for h in re.findall(r"^#+ (.+)$", text, re.M)}


def test_readme_is_short_and_keeps_the_two_commands():
    text = README.read_text()
    assert len(text.splitlines()) <= MAX_README_LINES
    for cmd in ("python3 build.py demo", "python3 build.py test"):  # CI and a hook grep them
        assert cmd in text, cmd


@pytest.mark.parametrize("doc", DOCS, ids=doc_ids())
def test_no_issue_numbers(doc):
    hits = [f"{doc.name}:{i}: {line.strip()}" for i, line in
            enumerate(doc.read_text().splitlines(), 1) if ISSUE.search(line)]
    assert not hits, "user docs state current facts, not issue numbers:\n" + "\n".join(hits)


def resolve(dotted: str) -> bool:
    """True when ``dotted`` is an importable module or an attribute path below one."""
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:n]))
        except ModuleNotFoundError as exc:
            if exc.name and not ".".join(parts[:n]).startswith(exc.name):
                raise  # the module exists but one of its own imports is missing
            continue
        try:
            for attr in parts[n:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return False
        return True
    return False


def test_every_module_path_named_resolves():
    named: dict[str, set[str]] = {}
    for doc in DOCS:
        for name in MODULE_PATH.findall(doc.read_text()):
            named.setdefault(name, set()).add(doc.name)
    assert len(named) >= 10, named  # the pattern finds the names
    bad = [f"{name} (in {', '.join(sorted(docs))})" for name, docs in sorted(named.items())
           if not resolve(name)]
    assert not bad, "named in the docs, not in the package:\n" + "\n".join(bad)


def test_resolve_tells_a_wrong_name():
    assert resolve("isac_twin.twin.twin.Twin.step")
    assert not resolve("isac_twin.twin.twin.Twin.no_such_method")
    assert not resolve("isac_twin.no_such_module")


@pytest.mark.parametrize("doc", DOCS, ids=doc_ids())
def test_relative_links_and_paths_exist(doc):
    text = doc.read_text()
    bad = []
    for target in LINK.findall(FENCE.sub("", text)):
        if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
            continue
        file, _, anchor = target.partition("#")
        path = (doc.parent / file).resolve() if file else doc
        if not path.exists():
            bad.append(f"link {target}: no file {path}")
        elif anchor and path.suffix == ".md" and anchor not in anchors(path):
            bad.append(f"link {target}: {path.name} has no heading '#{anchor}'")
    for rel in REPO_PATH.findall(text):
        if not (ROOT / rel).exists():
            bad.append(f"path `{rel}` does not exist")
    assert not bad, f"{doc.relative_to(ROOT)}:\n" + "\n".join(bad)


def test_every_test_named_exists():
    defined = set()
    for f in (ROOT / "tests").rglob("test_*.py"):
        defined |= set(re.findall(r"^def (test_\w+)", f.read_text(), re.M))
    named = {(name, doc.name) for doc in DOCS
             for name in re.findall(r"`(test_\w+)(?:\[[^\]]*\])?`", doc.read_text())}
    assert named, "no test names found: the pattern is wrong"
    bad = sorted(f"{name} (in {doc})" for name, doc in named if name not in defined)
    assert not bad, "named in the docs, no such test:\n" + "\n".join(bad)


def test_the_docs_map_lists_every_page():
    listed = {Path(t).name for t in LINK.findall(section(README.read_text(), "Documentation"))}
    pages = {p.name for p in (ROOT / "docs").glob("*.md")}
    assert pages <= listed, f"docs/ pages missing from the README's map: {pages - listed}"


def cli_commands() -> list[str]:
    out = subprocess.run([sys.executable, "-m", "isac_twin.cli", "--help"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    m = re.search(r"\{([\w,-]+)\}", out.stdout)
    assert m, out.stdout
    return m.group(1).split(",")


def test_the_cli_table_lists_every_command():
    table = section(README.read_text(), "The command line")
    listed = set(re.findall(r"^\| `([\w-]+)` \|", table, re.M))
    commands = cli_commands()
    assert len(commands) >= 10
    assert set(commands) <= listed, f"not in the README's table: {set(commands) - listed}"
    assert listed <= set(commands), f"in the README's table, not commands: {listed - set(commands)}"


def test_the_readme_names_the_zip_build_py_builds():
    manifest = tomllib.loads((ROOT / "addon" / "blender_manifest.toml").read_text())
    zip_name = f"dist/isac_twin-{manifest['version']}.zip"
    text = README.read_text()
    assert zip_name in text
    assert not set(re.findall(r"dist/isac_twin-[\d.]+\.zip", text)) - {zip_name}


@pytest.mark.slow
def test_the_readme_python_example_runs(tmp_path):
    (code,) = fenced(section(README.read_text(), "The twin from Python"), "python")
    assert len(code.strip().splitlines()) <= 12, "the example is meant to be ten lines"
    script = tmp_path / "example.py"
    script.write_text(code)
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                         cwd=tmp_path, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    lines = out.stdout.splitlines()
    steps = [ln for ln in lines if ln.endswith("Mbit/s")]
    assert len(steps) == 20, out.stdout
    assert any(ln.split()[0] == "trace" for ln in lines if ln.strip()), out.stdout  # stats table


@pytest.mark.slow
@pytest.mark.blender
def test_the_readme_bpy_script_builds_a_room_the_engine_loads(tmp_path):
    bpy = pytest.importorskip("bpy")
    (code,) = fenced(section(README.read_text(), "Your own room in five minutes"), "python")
    script = tmp_path / "myroom.py"
    script.write_text(code)
    tool = Path(bpy.utils.system_resource("SCRIPTS")) / "addons_core/bl_pkg/cli/blender_ext.py"
    (tmp_path / "dist").mkdir()
    built = subprocess.run([sys.executable, str(tool), "build", "--source-dir",
                            str(ROOT / "addon"), "--output-dir", str(tmp_path / "dist")],
                           capture_output=True, text=True, timeout=300)
    assert built.returncode == 0, built.stdout + built.stderr
    (zip_path,) = (tmp_path / "dist").glob("isac_twin-*.zip")
    folder = tmp_path / "out" / "myroom"
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "user"))
    out = subprocess.run([sys.executable, str(script), str(zip_path), str(folder)],
                         capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "placement: ok" in out.stdout, out.stdout
    assert (tmp_path / "user").is_dir()  # installed in the scratch folder, not the user's

    from isac_twin import load_scene

    scene = load_scene(folder)
    cfg = scene.config
    assert {d.name: d.kind for d in cfg.devices} == {"AP1": "access_point", "robot1": "robot"}
    assert [(lk.tx, lk.rx) for lk in cfg.links] == [("AP1", "robot1")]
    robot = next(d for d in cfg.devices if d.kind == "robot")
    assert robot.path["kind"] == "circle"
    assert {"Table", "Rack", "Room_Floor"} <= set(scene.objects)
