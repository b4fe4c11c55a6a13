"""isac_twin.cli.main: the parser and its registry, what ``--help`` imports, and the one
place that turns an error into a line on stderr and an exit status."""

from __future__ import annotations

import importlib
import re
import subprocess
import sys

import pytest

from isac_twin.cli import COMMANDS, main

from .conftest import ROOT

#: Imported only when a command does the work that needs them.
HEAVY = ("mitsuba", "drjit", "sionna", "zenoh", "dask", "matplotlib", "depthai")


def _imported(stderr: str) -> set[str]:
    """Module names of a ``python -X importtime`` report."""
    return {ln.rsplit("|", 1)[1].strip() for ln in stderr.splitlines()
            if ln.startswith("import time:") and ln.count("|") == 2}


def test_help_imports_no_command_module_and_nothing_heavy():
    """`isac-twin --help` (a real process) lists every command and loads none of their
    modules: no tracer, zenoh, Dask or matplotlib."""
    r = subprocess.run([sys.executable, "-X", "importtime", "-m", "isac_twin.cli", "--help"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    for name in COMMANDS:
        assert f"    {name} " in r.stdout or f"    {name}\n" in r.stdout, name
    mods = _imported(r.stderr)
    assert "isac_twin.cli.main" in mods  # the report is read right
    assert not {m for m in mods if m.split(".")[0] in HEAVY}
    assert not {m for m in mods if m.startswith("isac_twin.cli.") and m not in
                ("isac_twin.cli.main", "isac_twin.cli.__main__")}


def test_every_command_help_imports_nothing_heavy():
    """`isac-twin <cmd> --help` for every command, in one process: each command module's
    own imports (module level) stop short of the heavy packages."""
    code = (
        "import sys\n"
        "from isac_twin.cli import COMMANDS, main\n"
        "for name in COMMANDS:\n"
        "    try:\n"
        "        main([name, '--help'])\n"
        "    except SystemExit as e:\n"
        "        assert e.code == 0, (name, e.code)\n"
        f"print(sorted(m for m in sys.modules if m.split('.')[0] in {HEAVY!r}))\n"
        "print(sorted(m for m in sys.modules if m.startswith('isac_twin.cli.')))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    heavy, cli = r.stdout.strip().splitlines()[-2:]
    assert heavy == "[]", heavy
    for group in {mod for mod, _ in COMMANDS.values()}:  # every group was loaded
        assert f"'isac_twin.cli.{group}'" in cli, (group, cli)


def test_registry_and_command_modules_agree():
    """Every registered command is defined by the module the registry names, and no
    module defines a command the registry lacks."""
    defined = {}
    for group in {mod for mod, _ in COMMANDS.values()}:
        module = importlib.import_module(f"isac_twin.cli.{group}")
        for name, (configure, fn) in module.COMMANDS.items():
            assert callable(configure) and callable(fn), name
            defined[name] = group
    assert defined == {name: mod for name, (mod, _) in COMMANDS.items()}


def test_python_m_and_a_bad_command():
    r = subprocess.run([sys.executable, "-m", "isac_twin.cli", "frobnicate"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and "invalid choice: 'frobnicate'" in r.stderr


# --------------------------------------------------------------------------- the error mapping

class LidarTwin:
    """A ``--twin`` factory that first asks a real RPLIDAR driver for its health over a
    port where no LIDAR answers (pyserial's ``loop://``: the request comes back as is)."""

    @classmethod
    def from_scene(cls, path, seed=0, **kw):
        from isac_twin.devices.rplidar import RPLidar

        lidar = RPLidar("loop://", timeout=0.2)
        lidar.open()
        try:
            lidar.get_health()
        finally:
            lidar.close()


class BuggyTwin:
    """A ``--twin`` factory with a bug."""

    @classmethod
    def from_scene(cls, path, seed=0, **kw):
        return {}["no such key"]


class ElsewhereTwin:
    """A ``--twin`` factory that reads a file the user never named."""

    @classmethod
    def from_scene(cls, path, seed=0, **kw):
        return open("/nonexistent/isac-twin-test/settings.toml")


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("isac-twin: error: "), err
    return lines[0]


def _scene_with(folder, old: str, new: str, file: str = "twin.toml"):
    """A copy of a box room with ``old`` replaced by ``new`` in ``file``."""
    from isac_twin.scene.synthetic import box_room

    box_room(folder)
    f = folder / file
    text = f.read_bytes()
    assert old.encode() in text, old
    f.write_bytes(text.replace(old.encode(), new.encode(), 1))
    return folder


def test_config_error_is_one_line_naming_file_and_key(tmp_path, capsys):
    folder = _scene_with(tmp_path / "s", "rows = 2", "rows = 0")
    assert main(["info", str(folder)]) == 2
    line = _one_line(capsys)
    assert f"{folder / 'twin.toml'}: devices[0] (AP1).array.rows: expected" in line, line


def test_mesh_error_is_one_line_naming_the_file(tmp_path, capsys):
    from isac_twin.scene.synthetic import box_room

    folder = box_room(tmp_path / "s")
    ply = next((folder / "meshes").glob("*.ply"))
    ply.write_bytes(ply.read_bytes()[:-7])  # a truncated mesh
    assert main(["info", str(folder)]) == 2
    assert f"{ply.name}: " in _one_line(capsys)


def test_path_error_is_one_line_naming_file_and_device(tmp_path, capsys):
    """A robot path with two waypoints at one point (it used to end in a PathError
    traceback that named neither the file nor the device)."""
    from isac_twin.scene.synthetic import ROBOT_EXTRA, SyntheticDevice, box_room

    path = {"kind": "polyline", "waypoints": [[2.0, 2.0], [2.0, 2.0]]}
    devs = [SyntheticDevice("AP1", "access_point", "tx", (1.0, 1.0, 2.0)),
            SyntheticDevice("robot1", "robot", "rx", (3.0, 2.0, 0.0),
                            extra={**ROBOT_EXTRA, "path": path})]
    folder = box_room(tmp_path / "s", devices=devs, links=[("AP1", "robot1")])
    for cmd in ("info", "topics"):
        assert main([cmd, str(folder)]) == 2
        line = _one_line(capsys)
        assert "twin.toml: devices[1] (robot1).path: polyline: waypoints 0 and 1 coincide" \
            in line, line


def test_calibration_error_is_one_line_naming_the_file(lab, tmp_path, capsys):
    junk = tmp_path / "junk.mcap"
    junk.write_text("not an mcap")
    assert main(["calibrate", str(lab), "--measurements", str(junk), "--out",
                 str(tmp_path / "o")]) == 2
    assert f"{junk}: no 'csi' entry" in _one_line(capsys)
    assert not (tmp_path / "o").exists()


def test_device_error_is_one_line_naming_the_port(capsys):
    assert main(["serve", "--port", "0", "--twin",
                 "tests.engine.cli.test_main:LidarTwin"]) == 2
    line = _one_line(capsys)
    assert re.search(r"loop://: (no response descriptor|timed out)", line), line


@pytest.mark.slow
def test_wire_error_is_one_line_and_the_server_stops(box_scene_dir, capsys):
    """A radio map too fine for one live-link frame (a WireError, after the server has
    started): one line, exit 2, and the process ends cleanly (with the server's thread
    left stepping the twin it aborted in teardown: 'terminate called without an active
    exception', status 134)."""
    r = subprocess.run([sys.executable, "-m", "isac_twin.cli", "serve", str(box_scene_dir),
                        "--port", "0", "--radiomap", "0.004", "--radiomap-samples", "1000"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 2, r.stderr[-2000:]
    assert r.stderr.strip().splitlines() == [r.stderr.strip()], r.stderr
    assert re.match(r"isac-twin: error: radiomap: frame of \d+ bytes exceeds the maximum",
                    r.stderr), r.stderr


def test_usage_error_and_a_missing_file_are_one_line(tmp_path, capsys):
    missing = tmp_path / "missing.mcap"
    assert main(["replay", str(missing)]) == 2
    assert _one_line(capsys) == f"isac-twin: error: {missing}: No such file or directory"
    assert main(["recover", str(missing)]) == 2
    assert f"{missing}: No such file or directory" in _one_line(capsys)
    assert main(["run", "--steps", "-1"]) == 2
    assert _one_line(capsys) == "isac-twin: error: --steps -1: expected >= 0"


def test_a_bug_keeps_its_traceback(capsys):
    """Neither an unexpected exception nor an OSError on a path the user did not name
    is turned into a line: a bug must not look like bad input."""
    with pytest.raises(KeyError):
        main(["serve", "--port", "0", "--twin", "tests.engine.cli.test_main:BuggyTwin"])
    with pytest.raises(FileNotFoundError):
        main(["serve", "--port", "0", "--twin", "tests.engine.cli.test_main:ElsewhereTwin"])
    assert capsys.readouterr().err == ""
    r = subprocess.run([sys.executable, "-m", "isac_twin.cli", "serve", "--port", "0", "--twin",
                        "tests.engine.cli.test_main:BuggyTwin"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 1 and "Traceback" in r.stderr and "KeyError" in r.stderr
