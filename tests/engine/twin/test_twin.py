"""engine/twin/twin.py: Algorithm 1 end to end on a small real scene (Sionna tracing, PHY, robots)."""

import logging

import numpy as np
import pytest

from isac_twin import Command, Edit, Twin
from isac_twin.scene.synthetic import two_ap_lab

pytestmark = pytest.mark.slow


def _lab(folder):
    """A 6 x 4 x 3 m room with a metal cabinet, AP1 (2x2) and AP2 (1x1) on disjoint symbols."""
    return two_ap_lab(folder, furniture={"cabinet": ((4.5, 0.2, 0), (5.1, 0.8, 1.8), "metal",
                                                     0.01)},
                      tracer={"samples_per_src": 20000, "max_depth": 2})


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    return _lab(tmp_path_factory.mktemp("lab") / "lab")


def _run(folder, steps, seed=3):
    tw = Twin.from_scene(folder, seed=seed)
    tw.set_path("robot1", {"kind": "circle", "centre": [3.0, 2.0], "radius": 1.0})
    return tw, list(tw.run(steps))


def test_step_produces_paths_rates_and_motion(lab):
    tw, res = _run(lab, 4)
    last = res[-1]
    assert last.step == 3 and last.time_s == pytest.approx(4 * tw.dt)
    rb = last.robots["robot1"]
    assert np.linalg.norm(rb.pose[:2] - [4.0, 2.0]) > 0.01  # it moved
    for lk in (("AP1", "robot1"), ("AP2", "robot1")):
        ls = last.links[lk]
        assert ls.paths.num_paths > 3 and ls.paths.los_delay is not None
        # LOS delay is the antenna distance over c.
        ant = rb.pose[:3] + [0, 0, 0.25]
        tx = np.array(tw.config.device(lk[0]).position)
        assert ls.paths.los_delay == pytest.approx(np.linalg.norm(ant - tx) / 299792458.0,
                                                   rel=1e-5)
        assert ls.rate_bps > 0 and np.isfinite(ls.snr_db)
    # Disjoint symbol sets: no interference, so the 2x2 AP (2 streams) beats the 1x1 AP.
    assert last.links[("AP1", "robot1")].rate_bps > last.links[("AP2", "robot1")].rate_bps
    sig = last.signals[("AP1", "robot1")]
    assert sig.h.shape == (14, 1024, 2, 4)
    assert set(last.timings_s) == {"agents", "trace", "phy", "publish", "sense", "estimate",
                                   "control"}
    # The robot's radio publishes the CSI of each link it receives, as a sensor.
    sub = tw.bus.node("probe").subscribe("/robot1/csi", "isac_twin_msgs/msg/Csi")
    nxt = tw.step()
    csi = {m.tx: m for m in sub.drain()}
    assert set(csi) == {"AP1", "AP2"} and csi["AP1"].header.stamp == pytest.approx(nxt.time_s)
    np.testing.assert_array_equal(csi["AP1"].h, nxt.signals[("AP1", "robot1")].h)
    assert "steps/s" in tw.stats.table()


def test_same_seed_same_run_other_seed_differs(lab):
    _, a = _run(lab, 3, seed=5)
    _, b = _run(lab, 3, seed=5)
    _, c = _run(lab, 3, seed=6)
    for ra, rb in zip(a, b):
        np.testing.assert_array_equal(ra.robots["robot1"].pose, rb.robots["robot1"].pose)
        for lk in ra.links:
            np.testing.assert_array_equal(ra.links[lk].paths.tau, rb.links[lk].paths.tau)
            np.testing.assert_array_equal(ra.links[lk].paths.a, rb.links[lk].paths.a)
            assert ra.links[lk].rate_bps == rb.links[lk].rate_bps
    assert not np.array_equal(a[-1].robots["robot1"].pose, c[-1].robots["robot1"].pose)


def _same(p, q):
    return p.num_paths == q.num_paths and np.allclose(p.tau, q.tau, rtol=1e-9, atol=0) \
        and np.allclose(p.a, q.a, rtol=1e-6, atol=0)


def test_edits_change_the_next_trace_and_flag_stale_databases(lab, caplog):
    tw = Twin.from_scene(lab, seed=1)
    tw.register_database("fingerprints.npz", tw.scene.content_hash())
    before = tw.step().links[("AP2", "robot1")].paths
    tw.apply_edit(Edit(op="move", target="cabinet", position=(4.0, 1.0, 0.9)))
    with caplog.at_level(logging.WARNING, logger="isac_twin.twin.twin"):
        moved = tw.step()
    assert "fingerprints.npz" in caplog.text and "stale" in caplog.text
    assert tw.stale_databases() == ["fingerprints.npz"]
    assert moved.scene_hash != tw.databases["fingerprints.npz"][0]
    p = moved.links[("AP2", "robot1")].paths
    # The robot barely moved (it has no controller): path changes are the edit's.
    assert not _same(p, before)
    tw.apply_edit(Edit(op="material", target="cabinet", material="wood", thickness=0.05))
    wood = tw.step().links[("AP2", "robot1")].paths
    tw.apply_edit(Edit(op="remove", target="cabinet"))
    gone = tw.step().links[("AP2", "robot1")].paths
    assert "cabinet" not in tw.scene.objects
    assert not _same(wood, p) and not _same(gone, wood)
    # Metal reflects more than wood: the strongest cabinet bounce loses power.
    assert np.abs(wood.a).sum() < np.abs(p.a).sum()


def test_commands_and_bad_input(lab):
    tw = Twin.from_scene(lab, seed=1, phy=False)
    # run/pause/step are the twin's own run state (the live server reads it)
    tw.command(Command("step", {"count": 3}))
    assert (tw.running, tw.pending_steps) == (False, 3)
    assert tw.step().step == 0 and tw.pending_steps == 2
    tw.command(Command("pause"))
    assert tw.pending_steps == 0  # pause cancels the steps still pending
    tw.command(Command("run"))
    assert tw.running
    for bad, match in ((Command("step", {"count": "abc"}), "count: expected an integer"),
                       (Command("step", {"count": 10**9}), "count: expected an integer"),
                       (Command("teleop", {"robot": "robot1", "linear": float("nan"),
                                           "angular": 0}), "linear: expected a number"),
                       (Command("teleop", {"robot": "r9", "linear": 0, "angular": 0}),
                        "robot: expected one of robot1"),
                       (Command("set_goal", {"robot": "robot1", "goal": [1e308, 0]}),
                        "goal: expected \\[x, y\\] inside the room")):
        with pytest.raises(ValueError, match=match):
            tw.command(bad)
    assert tw.running and tw.pending_steps == 0  # a rejected command changed nothing
    tw.command(Command("teleop", {"robot": "robot1", "linear": 0.1, "angular": 0.0}))
    tw.step()
    r = tw.step()
    assert r.robots["robot1"].velocity[0] == pytest.approx(0.1, abs=0.02)
    tw.command(Command("reset"))
    assert tw.step_index == 0
    with pytest.raises(ValueError, match="unknown op 'fly'"):
        tw.command(Command("fly"))
    with pytest.raises(KeyError, match="no robot named 'r2'"):
        tw.set_path("r2", {"kind": "circle", "centre": [3, 2], "radius": 1})
    with pytest.raises(ValueError, match="outside|leaves|room"):
        tw.set_path("robot1", {"kind": "circle", "centre": [3, 2], "radius": 5})
    with pytest.raises(ValueError, match="edit explode 'cabinet': op"):
        tw.apply_edit(Edit(op="explode", target="cabinet"))
    with pytest.raises(ValueError, match="material: 'floorboard' is not defined at 2.4 GHz"):
        tw.apply_edit(Edit(op="material", target="cabinet", material="floorboard"))
    tw.step()  # the rejected edits were never queued: the twin keeps stepping


@pytest.mark.parametrize("bad, field", [
    (Edit(op="move", target="cabinet", position=(float("nan"), 1.0, 0.9)), "position"),
    (Edit(op="move", target="cabinet", position=(1e308, 1.0, 0.9)), "position"),
    (Edit(op="move", target="sofa", position=(1.0, 1.0, 0.9)), "target"),
    (Edit(op="material", target="cabinet", material="unobtainium"), "material"),
    (Edit(op="material", target="cabinet", material="wood", thickness=-0.1), "thickness"),
    (Edit(op="material", target="cabinet", material="wood", thickness=float("inf")),
     "thickness"),
    (Edit(op="move", target="AP1", orientation=(0.0, float("inf"), 0.0)), "orientation"),
])
def test_a_bad_edit_between_two_good_ones_loses_neither(lab, bad, field):
    """Issue 15, 'no edit lost': the bad edit is refused when queued, naming the edit
    and the field; the good edits before and after it are both applied. (Before, a
    bad edit was queued, failed inside the next step, and the step's exception
    discarded every edit queued with it.)"""
    tw = Twin.from_scene(lab, seed=1, phy=False)
    tw.apply_edit(Edit(op="move", target="cabinet", position=(4.0, 1.0, 0.9)))
    with pytest.raises(ValueError, match=rf"edit {bad.op} '{bad.target}': {field}"):
        tw.apply_edit(bad)
    tw.apply_edit(Edit(op="material", target="cabinet", material="wood", thickness=0.05))
    tw.step()
    assert tw.scene.object_poses["cabinet"][:3] == pytest.approx([4.0, 1.0, 0.9])
    assert tw.scene.objects["cabinet"].material == "wood"
    assert tw.scene.objects["cabinet"].thickness == pytest.approx(0.05)


def test_moving_devices_by_edit(lab):
    tw = Twin.from_scene(lab, seed=1, phy=False)
    tw.register_database("grid.npz", tw.scene.content_hash())
    d0 = tw.step().links[("AP1", "robot1")].paths.los_delay
    tw.apply_edit(Edit(op="move", target="AP1", position=(1.0, 2.0, 2.0)))
    tw.apply_edit(Edit(op="move", target="robot1", position=(4.0, 3.0, 0.0)))
    r = tw.step()
    assert tw.stale_databases() == ["grid.npz"]  # traced from AP1's old position
    assert r.robots["robot1"].pose[:2] == pytest.approx([4.0, 3.0], abs=0.02)
    d1 = r.links[("AP1", "robot1")].paths.los_delay
    expect = np.linalg.norm(np.array([4.0, 3.0, 0.25]) - [1.0, 2.0, 2.0]) / 299792458.0
    assert d1 == pytest.approx(expect, rel=1e-3) and d1 != pytest.approx(d0, rel=1e-3)
    with pytest.raises(ValueError, match="edit move .AP1.: position.*outside the room"):
        tw.apply_edit(Edit(op="move", target="AP1", position=(9.0, 2.0, 2.0)))


def test_hooks_state_source_and_trace_schedule(lab):
    """A sourced robot is placed (no motion model, no controller) and the trace
    schedule skips tracing on the steps it refuses; unhooking restores both."""
    from isac_twin.robots import KinematicState
    tw = Twin.from_scene(lab, seed=1, phy=False)
    tw.set_path("robot1", {"kind": "circle", "centre": [3.0, 2.0], "radius": 1.0})
    calls = []
    tw.set_state_source("robot1", lambda t, dt: calls.append((t, dt)) or KinematicState(
        pose=np.array([1.0 + t, 1.5, 0.0, 0.0, 0.0, 0.3]), v=1.0, w=0.0, t=t))
    tw.trace_schedule = lambda k: k % 2 == 0
    cmd = tw.bus.node("probe2").subscribe("/robot1/cmd_vel", "geometry_msgs/msg/Twist")
    res = list(tw.run(3))
    assert [t for t, _ in calls] == pytest.approx([0.05, 0.10, 0.15])
    np.testing.assert_allclose(res[1].robots["robot1"].pose[:2], [1.10, 1.5])
    assert [bool(r.links) for r in res] == [True, False, True]
    assert len(cmd.drain()) == 0  # a placed robot is not driven
    tw.reset()  # new agents, same hooks
    np.testing.assert_allclose(tw.step().robots["robot1"].pose[:2], [1.05, 1.5])
    with pytest.raises(KeyError, match="no robot named 'ghost'"):
        tw.set_state_source("ghost", None)
    tw.set_state_source("robot1", None)
    tw.trace_schedule = None
    cmd = tw.bus.node("probe3").subscribe("/robot1/cmd_vel", "geometry_msgs/msg/Twist")
    r = tw.step()
    assert r.links and len(cmd.drain()) == 1
    assert not np.allclose(r.robots["robot1"].pose[:2], [1.10, 1.5])


def test_add_edits_read_no_host_file(tmp_path, lab):
    """Issue 22: an ``add`` edit's mesh comes from a regular PLY inside the scene folder
    (relative path) or an asset folder; a device, FIFO, absolute or ``..`` path, a
    symbolic link out of the folder, a missing or oversized file are all refused with
    the same message (it reveals nothing about the host), at once, and nothing is read
    from a device (before, ``/dev/zero`` grew the engine by 2.4 GB and a FIFO hung it)."""
    import os
    import shutil

    from isac_twin.twin import twin as twin_mod

    folder = tmp_path / "lab"
    shutil.copytree(lab, folder)
    meshes = folder / "meshes"
    good = next(meshes.glob("*.ply"))
    os.mkfifo(meshes / "fifo.ply")
    (meshes / "out.ply").symlink_to(tmp_path / "outside.ply")
    shutil.copy(good, tmp_path / "outside.ply")
    assets = tmp_path / "assets"
    assets.mkdir()
    shutil.copy(good, assets / "box.ply")
    tw = Twin.from_scene(folder, seed=1, phy=False, asset_dirs=[assets])
    messages = set()
    for path in ("/dev/zero", str(meshes / "fifo.ply"), "meshes/fifo.ply", "/etc/passwd",
                 "/no/such/file.ply", "../lab/meshes/" + good.name, "meshes/out.ply",
                 str(good), "meshes/missing.ply", "twin.toml"):
        with pytest.raises(ValueError) as err:
            tw.apply_edit(Edit(op="add", target="box", material="wood", mesh_file=path))
        messages.add(str(err.value))
    assert messages == {"edit add 'box': mesh_file: expected a PLY file inside the scene "
                        "folder (a relative path) or an asset folder, at most "
                        f"{twin_mod.MAX_EDIT_MESH_BYTES} bytes"}
    tw.apply_edit(Edit(op="add", target="box", material="wood",
                       mesh_file="meshes/" + good.name))
    tw.apply_edit(Edit(op="add", target="box2", material="wood",
                       mesh_file=str(assets / "box.ply")))
    tw.step()
    assert {"box", "box2"} <= set(tw.scene.objects)


def test_set_path_is_checked_against_the_room_as_it_is_now(tmp_path):
    """A live set_path through the desk is refused by name; once the desk is moved away
    (an edit), the same path is accepted."""
    from isac_twin import PathError
    from isac_twin.scene.synthetic import l_room

    tw = Twin.from_scene(l_room(tmp_path / "l", robot=(1.0, 1.0, 0.0)), phy=False, seed=0)
    through = {"kind": "polyline", "waypoints": [[1.0, 1.0], [2.0, 4.2]]}
    with pytest.raises(PathError, match=r"set_path\(robot1\): the polyline .* lies in object "
                                        r"'Desk'"):
        tw.command(Command("set_path", {"robot": "robot1", "path": through}))
    with pytest.raises(PathError, match="lies in object 'Room_Wall_4'"):  # to the cut-out
        tw.set_path("robot1", {"kind": "goal", "goal": [5.0, 4.5]})
    tw.apply_edit(Edit(op="move", target="Desk", position=(3.1, 4.0, 0.375)))
    tw.step()
    tw.set_path("robot1", through)  # free now


def test_paced_run_names_the_stage_of_each_overrun(lab):
    """A paced run counts an overrun against the step's longest stage, or against
    the caller when the consumer of a result held the loop (issue #19)."""
    import time

    tw = Twin.from_scene(lab, seed=1, phy=False)
    tw.estimators.append(lambda twin, res: time.sleep(0.4) if res.step == 1 else None)
    for res in tw.run(4, rate_hz=4.0):  # period 250 ms; normal steps take far less
        if res.step == 2:
            time.sleep(0.4)
    st = tw.stats
    assert st.overrun_stages.get("estimate") == 1 and st.overrun_stages.get("caller") == 1
    assert st.overruns == sum(st.overrun_stages.values()) and st.overrun_ms >= 2 * 150
    assert "estimate 1" in st.overrun_summary() and "caller 1" in st.table()
    with pytest.raises(ValueError, match="rate_hz"):
        list(tw.run(1, rate_hz=0))


def test_paced_run_starts_its_schedule_after_the_start_up_step(lab):
    """The twin's first step (chains, kernel recording: ~1.2 s for 4 robots) is
    the paced run's start-up, not an overrun; the schedule starts after it, and
    the objects alive then are frozen out of the cyclic GC (its full
    collections took ~30 ms, an overrun at 20 Hz). Before, step 0 was always
    an overrun of ~1.2 s."""
    import gc
    import time

    tw = Twin.from_scene(lab, seed=1, phy=False)
    tw.estimators.append(lambda twin, res: time.sleep(0.4) if res.step == 0 else None)
    list(tw.run(3, rate_hz=4.0))
    st = tw.stats
    assert st.startup_s >= 0.4 and st.overruns == 0, st.overrun_summary()
    assert "start-up" in st.overrun_summary() and gc.get_freeze_count() > 0
    tw.estimators.append(lambda twin, res: time.sleep(0.4))
    list(tw.run(1, rate_hz=4.0))  # a later run has no start-up step: an overrun
    assert tw.stats.overruns == 1 and tw.stats.overrun_stages == {"estimate": 1}
    gc.unfreeze()


def test_a_slow_csi_consumer_is_timed_and_named_as_the_publish_stage(lab):
    """The step's result and its CSI publication (a recorder's synchronous
    callback) are a timed stage, ``publish``: an overrun there is named so, not
    charged to another stage (issue #19; before, that time was in no stage)."""
    import time

    from isac_twin.twin.twin import STAGES

    tw = Twin.from_scene(lab, seed=1, sensing=False)
    tw.step()  # compiles the tracer's kernels
    tw.bus.node("slow_recorder").subscribe(
        "/robot1/csi", "isac_twin_msgs/msg/Csi",
        lambda m: time.sleep(0.4) if m.tx == "AP1" else None)
    res = list(tw.run(2, rate_hz=4.0))  # 250 ms period: the callback overruns it
    assert "publish" in STAGES and all(r.timings_s["publish"] >= 0.4 for r in res)
    assert tw.stats.stage_s["publish"] >= 0.8
    assert tw.stats.overrun_stages == {"publish": 2}


def test_csi_is_built_only_for_consumers_and_records_the_same(lab, tmp_path):
    """Issue 19: without a subscriber to ``/<robot>/csi`` the twin publishes no CSI and
    the PHY does not expand the channel over the symbols (one value per symbol
    group is kept); an MCAP recorded with ``--csi full`` and ``compact`` holds the
    channel the PHY computed, on every symbol, equal to the per-link synthesis
    (``NetworkPHY.channel``) at each symbol group's mean time."""
    from isac_twin.transport.record import CsiRecording, read_messages, record_twin

    tw, res = _run(lab, 2)
    assert tw.bus.registry().topic("/robot1/csi").messages == 0
    assert tw.bus.registry().topic("/robot1/scan").messages == 0  # nor scans (no subscriber)
    sig = res[-1].signals[("AP1", "robot1")]
    assert sig.time_invariant and sig.h_by_group.shape == (2, 1024, 2, 4)
    assert "h" not in vars(sig)  # not expanded: nobody read it
    assert sig.h.shape == (14, 1024, 2, 4)  # expanded on first read
    for mode, csi in (("full", CsiRecording.full()), ("compact", CsiRecording())):
        rec_tw = Twin.from_scene(lab, seed=3)
        rec_tw.set_path("robot1", {"kind": "circle", "centre": [3.0, 2.0], "radius": 1.0})
        out = tmp_path / f"{mode}.mcap"
        record_twin(rec_tw, 2, out, csi=csi)
        got = [m.decode() for m in read_messages(out, ["/robot1/csi"])]
        assert len(got) == 4  # 2 steps x 2 links
        for m in got:
            step = round(m.header.stamp / tw.dt) - 1
            s = res[step].signals[(m.tx, "robot1")]
            np.testing.assert_array_equal(m.h, s.h[::csi.symbol_step, ::csi.subcarrier_step])
            if mode == "full":  # the per-link synthesis, independent of the batched one
                t = tw.phy.grid.symbol_times
                times = np.bincount(s.group, weights=t) / np.bincount(s.group)
                ref = tw.phy.channel(res[step].links[(m.tx, "robot1")].paths, times)[s.group]
                np.testing.assert_allclose(m.h, ref, rtol=0,
                                           atol=1e-5 * np.abs(ref).max())


def test_material_edits_name_itu_or_custom_materials(tmp_path):
    folder = _lab(tmp_path / "lab")
    xml = (folder / "scene.xml").read_text()
    bsdf = ('\t<bsdf type="radio-material" id="mat-damp_plaster">\n'
            '\t\t<float name="relative_permittivity" value="6.5"/>\n'
            '\t\t<float name="conductivity" value="0.05"/>\n'
            '\t\t<float name="thickness" value="0.05"/>\n\t</bsdf>\n')
    xml = xml.replace("<!-- Shapes", bsdf + "<!-- Shapes", 1)
    (folder / "scene.xml").write_text(xml)
    tw = Twin.from_scene(folder, seed=1)
    assert tw.scene.custom_materials["damp_plaster"]["relative_permittivity"] == 6.5
    tw.validate_edit(Edit(op="material", target="cabinet", material="concrete", thickness=0.1))
    with pytest.raises(ValueError, match=r"edit material 'cabinet': material: unknown material "
                                         r"'dry_plaster'.*\(damp_plaster\)"):
        tw.apply_edit(Edit(op="material", target="cabinet", material="dry_plaster"))
    with pytest.raises(ValueError, match="custom material 'damp_plaster' has its own thickness"):
        tw.apply_edit(Edit(op="material", target="cabinet", material="damp_plaster",
                           thickness=0.3))
    tw.apply_edit(Edit(op="material", target="cabinet", material="damp_plaster"))
    tw.step()
    m = tw.scene.sionna.objects["cabinet"].radio_material
    assert tw.scene.objects["cabinet"].material == "damp_plaster"
    assert float(m.relative_permittivity.numpy()[0]) == pytest.approx(6.5)
    assert float(m.conductivity.numpy()[0]) == pytest.approx(0.05)
