"""engine/scene/config.py: twin.toml parsing, defaults, and every bad input naming its culprit."""

import re

import pytest

from isac_twin import ConfigError, load_config
from isac_twin.scene.synthetic import box_room


@pytest.fixture()
def folder(tmp_path):
    return box_room(tmp_path / "room")


def _edit(folder, old, new, count=1):
    p = folder / "twin.toml"
    text = p.read_text()
    assert old in text, old
    p.write_text(text.replace(old, new, count))
    return p


def test_loads_and_derives(folder):
    cfg = load_config(folder)
    assert cfg.scene.frequency_hz == 2.4e9
    assert cfg.scene.file == (folder / "scene.xml").resolve()
    assert cfg.ofdm.bandwidth_hz == pytest.approx(80e6)
    assert cfg.ofdm.symbol_time_s == pytest.approx((1024 + 72) / 80e6)
    ap = cfg.device("AP1")
    assert ap.array.num_ant == 4 and ap.is_tx and not ap.is_rx
    robot = cfg.device("robot1")
    assert robot.model == "burger" and robot.antenna_offset == (0.0, 0.0, 0.25)
    # Defaults: the whole grid is the resource set.
    assert robot.subcarriers == (0, 1024) and robot.symbols == (0, 14)
    assert cfg.tracer.backend == "sionna" and cfg.noise.temperature_k == 290.0
    assert [(lk.tx, lk.rx) for lk in cfg.links] == [("AP1", "robot1")]


def test_every_polarization_loads_and_dual_doubles_the_ports(folder):
    for pol, ports in (("V", 4), ("H", 4), ("VH", 8), ("cross", 8)):
        p = folder / "twin.toml"
        p.write_text(re.sub(r'polarization = "\w+"', f'polarization = "{pol}"',
                            p.read_text(), count=1))
        ap = load_config(folder).device("AP1")
        assert (ap.array.polarization, ap.array.num_ant) == (pol, ports)


@pytest.mark.parametrize("table,culprit", [
    ('[tracer]\nbackend = "grid"\ngrid_file = "g.npz"',
     r"devices\[0\] \(AP1\)\.array\.polarization: 'cross' needs the paths' polarization"),
    ('[[sensing]]\ntx = "AP1"\nrx = "AP1"\nrho = 0.25',
     r"sensing\[0\]\.tx: device 'AP1' has polarization 'cross'; sensing links model V"),
    ("[localization]\nmethod = \"MCA\"",
     r"localization: devices\[0\] \(AP1\) has polarization 'cross'; fingerprints"),
])
def test_polarization_refused_where_only_v_is_modelled(folder, table, culprit):
    """Path grids, sensing links and fingerprints carry V elements only: one line."""
    _edit(folder, 'polarization = "V"', 'polarization = "cross"')
    p = folder / "twin.toml"
    p.write_text(p.read_text() + "\n" + table + "\n")
    with pytest.raises(ConfigError, match=culprit) as e:
        load_config(folder)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("old,new,culprit", [
    ("rows = 2", "rows = 0", r"devices\[0\] \(AP1\)\.array\.rows: expected an integer >= 1"),
    ("cols = 2", "cols = 2.5", r"array\.cols: expected an integer"),
    ('pattern = "iso"', 'pattern = "horn"', r"array\.pattern: expected one of iso"),
    ("frequency_hz = 2400000000.0", "frequency_hz = -1.0", r"scene\.frequency_hz: expected a positive"),
    ("num_subcarriers = 1024", "num_subcarriers = 0", r"ofdm\.num_subcarriers"),
    ('kind = "access_point"', 'kind = "drone"', r"devices\[0\] \(AP1\)\.kind: expected one of"),
    ("position = [1.0, 1.0, 2.0]", "position = [1.0, 2.0]", r"\(AP1\)\.position: expected 3 finite"),
    ("position = [1.0, 1.0, 2.0]", "position = [1.0, nan, 2.0]", r"\(AP1\)\.position"),
    ('tx = "AP1"', 'tx = "AP9"', r"links\[0\]\.tx: unknown device 'AP9'"),
    ('tx = "AP1"', 'tx = "robot1"', r"links\[0\]\.tx: device 'robot1' has role 'rx'"),
    ("schema = 1", "schema = 7", r"schema: this engine reads schema 1"),
    ('name = "robot1"', 'name = "AP1"', r"duplicate device name 'AP1'"),
])
def test_bad_values_name_the_key(folder, old, new, culprit):
    _edit(folder, old, new)
    with pytest.raises(ConfigError, match=culprit) as err:
        load_config(folder)
    assert "twin.toml" in str(err.value)


def test_unknown_keys_are_refused(folder):
    _edit(folder, "[ofdm]", "[ofdm]\nnum_subcarrierz = 12")
    with pytest.raises(ConfigError, match=r"ofdm\.num_subcarrierz: unknown key"):
        load_config(folder)
    p = folder / "twin.toml"
    p.write_text(p.read_text() + "\n[extras]\nx = 1\n")
    with pytest.raises(ConfigError, match=r"extras: unknown key"):
        load_config(folder)


def test_resource_range_outside_grid(folder):
    _edit(folder, 'role = "tx"', 'role = "tx"\nsubcarriers = [1000, 1100]')
    with pytest.raises(ConfigError, match=r"\(AP1\)\.subcarriers: expected 0 <= start < stop <= 1024"):
        load_config(folder)


def test_robot_only_keys_on_an_ap(folder):
    _edit(folder, 'role = "tx"', 'role = "tx"\nmodel = "burger"')
    with pytest.raises(ConfigError, match=r"\(AP1\)\.model: only robots"):
        load_config(folder)


def test_missing_file_and_broken_toml(tmp_path, folder):
    with pytest.raises(ConfigError, match="no such file"):
        load_config(tmp_path / "nowhere")
    p = _edit(folder, "[ofdm]", "[ofdm")
    with pytest.raises(ConfigError, match=re.escape(str(p)) + ": not valid TOML"):
        load_config(folder)


def test_missing_required_key(folder):
    _edit(folder, "power_dbm = 20.0\n", "", count=1)
    with pytest.raises(ConfigError, match=r"\(AP1\)\.power_dbm: missing required key"):
        load_config(folder)


def _devices(n_robots: int, ap=(2, 2)) -> str:
    """twin.toml devices/links tables: AP1 (rows x cols) and ``n_robots`` linked robots."""
    out = ['[[devices]]\nname = "AP1"\nkind = "access_point"\nrole = "tx"\n'
           f'position = [1.0, 1.0, 2.0]\npower_dbm = 20.0\n[devices.array]\nrows = {ap[0]}\n'
           f'cols = {ap[1]}\n']
    for i in range(n_robots):
        out.append(f'[[devices]]\nname = "r{i}"\nkind = "robot"\nrole = "rx"\nmodel = "burger"\n'
                   f'position = [{1 + 0.01 * i}, 2.0, 0.0]\npower_dbm = 10.0\n'
                   '[devices.array]\nrows = 1\ncols = 2\n')
    out += [f'[[links]]\ntx = "AP1"\nrx = "r{i}"\n' for i in range(n_robots)]
    return "".join(out)


def _with_devices(folder, tables: str, ofdm=None):
    p = folder / "twin.toml"
    text = p.read_text()
    head = text[:text.index("[[devices]]")]
    if ofdm is not None:
        head = re.sub(r"num_subcarriers = \d+", f"num_subcarriers = {ofdm[0]}", head)
        head = re.sub(r"num_symbols = \d+", f"num_symbols = {ofdm[1]}", head)
        head = re.sub(r"subcarrier_spacing_hz = [\d.e+]+", "subcarrier_spacing_hz = 1000.0",
                      head)
    p.write_text(head + tables)
    return p


@pytest.mark.parametrize("ofdm, ap, robots, culprit", [
    # every key within its own limit, the product beyond the step's budget
    ((65536, 4096), (256, 256), 1,
     r"twin\.toml: limits\.step_memory_mb: a step's channels need 4096 symbols x 65536 "
     r"subcarriers x 131072 antenna pairs x 8 B on AP1 -> r0 \(1 link\) = 2\.8e\+14 B, "
     r"beyond the budget of 2048 MB"),
    ((1024, 14), (2, 2), 300,
     r"twin\.toml: limits\.devices: 301 devices, beyond the limit of 256"),
])
def test_a_resource_budget_bounds_the_product_of_the_sizes(folder, ofdm, ap, robots, culprit):
    """The per-key limits do not bound their product (65,536 subcarriers, 4,096 symbols
    and a 256 x 256 array passed and grew past 1.6 GB at step 1; 1,000 robots past
    4 GB): the budget is computed at load and refused in one line naming the product
    and the limit, which ``[limits]`` raises."""
    _with_devices(folder, _devices(robots, ap), ofdm)
    with pytest.raises(ConfigError, match=culprit):
        load_config(folder)
    p = folder / "twin.toml"
    p.write_text(p.read_text() + "[limits]\nstep_memory_mb = 1e12\ndevices = 400\n")
    cfg = load_config(folder)
    assert len(cfg.devices) == robots + 1 and cfg.limits.devices == 400


def test_the_budget_counts_every_link_and_refuses_bad_limits(folder):
    """64 links of a 16 x 16 AP to 2-antenna robots on 1024 x 14: 64 x 14 x 1024 x 512 x
    8 B = 3.8 GB > 2 GiB (each link alone is 59 MB); a limit must be a positive number."""
    _with_devices(folder, _devices(64, (16, 16)))
    with pytest.raises(ConfigError, match=r"14 symbols x 1024 subcarriers x 512 antenna pairs "
                                          r"\(the largest; 32768 in all\) x 8 B on AP1 -> r0 "
                                          r"\.\.\. \(64 links\) = 3\.8e\+09 B"):
        load_config(folder)
    p = folder / "twin.toml"
    text = p.read_text()
    for bad, key in (("links = 0", "links"), ("step_memory_mb = -1", "step_memory_mb"),
                     ("devices = 2.5", "devices"), ("colour = 1", "colour")):
        p.write_text(text + f"[limits]\n{bad}\n")
        with pytest.raises(ConfigError, match=rf"twin\.toml: limits\.{key}"):
            load_config(folder)


@pytest.mark.parametrize("name, why", [
    ("", "empty"), (" ", "empty"), ("x" * 256, "256 characters"),
    ("AP\n\x1b[31mred", r"not printable"),
])
def test_device_names_are_printable_and_bounded(folder, name, why):
    import json

    p = folder / "twin.toml"
    text = p.read_text().replace('name = "AP1"', f"name = {json.dumps(name)}", 1)
    text = text.replace('tx = "AP1"', f"tx = {json.dumps(name)}")
    p.write_text(text)
    with pytest.raises(ConfigError, match=rf"devices\[0\]\.name: .*{why}"):
        load_config(folder)
