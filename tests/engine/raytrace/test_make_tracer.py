"""[tracer] keys added for ray tracing (deterministic, grid_file) and make_tracer."""

from __future__ import annotations

import pytest

from isac_twin import ConfigError, load_config, make_tracer
from isac_twin.raytrace.grid import save_grid
from isac_twin.raytrace.grid_backend import GridTracer
from isac_twin.raytrace.sionna import SionnaTracer
from isac_twin.scene.synthetic import furnished_room


def test_tracer_keys(tmp_path):
    cfg = load_config(furnished_room(tmp_path / "a", tracer={"deterministic": False}))
    assert cfg.tracer.deterministic is False and cfg.tracer.grid_file == ""
    assert isinstance(make_tracer(cfg), SionnaTracer)
    with pytest.raises(ConfigError, match=r"tracer\.grid_file: required"):
        load_config(furnished_room(tmp_path / "b", tracer={"backend": "grid"}))
    with pytest.raises(ConfigError, match=r"tracer\.deterministic: expected true or false"):
        load_config(furnished_room(tmp_path / "c", tracer={"deterministic": 1}))


def test_grid_backend_from_config(tmp_path, room_grid, capsys):
    from isac_twin.cli import main

    folder = furnished_room(tmp_path / "g", tracer={"backend": "grid",
                                                   "grid_file": "grid.npz"})
    save_grid(room_grid, folder / "grid.npz")
    assert isinstance(make_tracer(load_config(folder)), GridTracer)
    assert main(["trace", str(folder)]) == 0
    assert "backend 'grid'" in capsys.readouterr().out
