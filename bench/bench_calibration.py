"""Benchmark: one gradient step of the calibration (isac_twin.calibration.forward_model).

A 5 x 4 x 3 m synthetic room with a metal cabinet, one AP, N receiver
positions, K subcarriers; parameters: the walls' permittivity and the
cabinet's x/y offsets. Prints the mean time of a gradient step (trace with
``loop_mode="evaluated"``, CFR, backward) and, as the baseline measured in
the same run, of the same evaluation without gradients; the ratio is the
cost of Dr.Jit's AD. No assertions on time.

Run: ``python bench/bench_calibration.py [--positions 4] [--subcarriers 8]
[--rays 20000] [--repeat 3]``

``--compiles`` counts the Dr.Jit kernels compiled (not found in a cache) per traced
evaluation of the lab's 10 pieces of furniture at new poses, with the candidate
generator and with the chain model (chains enumerated again every other
evaluation); its baseline is the first evaluation, which compiles every kernel.
The aim is 0 after the warm-up; Dr.Jit's kernel history is the process's and its
cache keys depend on the allocator's state, so this is measured here, not tested.

``--lab`` runs the closing-the-loop case instead (:mod:`isac_twin.experiments.lab_calibration`):
the bundled lab's perturbed "real" room (furniture shifted N(0, 3 cm), turned
N(0, 2 deg); the tables' wood 30 % denser), one lap of the robot's CSI recorded
there (``--snr`` adds noise), the twin calibrated from it (the tables' material
and the furniture's x/y/yaw), then (``--localize``) the localization errors
against the truth in the realistic mode with the original and the calibrated
twin. It prints each object's recovered offset against the truth, the fitted
permittivity, the times, and writes ``--out``/lab.json. Its baseline is the
original twin (mismatch and localization error before calibration).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from isac_twin import load_scene  # noqa: E402
from isac_twin.calibration import Calibrator, Measurements, Parameter, SolverSettings  # noqa: E402
from isac_twin.scene import synthetic as syn  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--positions", type=int, default=4)
    ap.add_argument("--subcarriers", type=int, default=None,
                    help="subcarriers (default 8; --lab: recorded subcarriers used, evenly "
                         "spread, default 16)")
    ap.add_argument("--rays", type=int, default=20000)
    ap.add_argument("--depth", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--lab", action="store_true", help="the closing-the-loop case on the lab")
    ap.add_argument("--snr", type=float, default=None, help="--lab: CSI noise SNR, dB")
    ap.add_argument("--no-noise", action="store_true",
                    help="--lab: no noise estimate added to the model's power")
    ap.add_argument("--localize", action="store_true",
                    help="--lab: also the localization errors, original vs calibrated twin")
    ap.add_argument("--per-fix", action="store_true",
                    help="--lab: also the per-fix errors (no fusion) of MCA and MCA-angles on "
                         "the recorded lap, original vs calibrated vs true-room twin")
    ap.add_argument("--snapshots", type=int, default=8, help="--lab: CSI snapshots used")
    ap.add_argument("--max-steps", type=int, default=40, help="--lab: optimiser iterations")
    ap.add_argument("--objects", default="", help="--lab: objects whose poses are fitted "
                                                  "(comma-separated; default the furniture)")
    ap.add_argument("--out", type=Path, default=Path("out/bench_calibration_lab"))
    ap.add_argument("--compiles", action="store_true",
                    help="kernels compiled per traced evaluation at new poses (the lab)")
    a = ap.parse_args(argv)
    if a.compiles:
        return compiles()
    if a.lab:
        a.subcarriers = a.subcarriers or 16
        return lab(a)
    a.subcarriers = a.subcarriers or 8
    with tempfile.TemporaryDirectory() as tmp:
        objs = syn.room_objects((5.0, 4.0, 3.0), {"Cabinet": ((3.0, 2.5, 0.0), (3.6, 3.0, 1.5),
                                                              "metal", 0.002)})
        devs = [syn.SyntheticDevice("AP1", "access_point", "tx", (0.5, 0.5, 2.0)),
                syn.SyntheticDevice("robot1", "robot", "rx", (2.0, 2.0, 0.0),
                                    extra=dict(syn.ROBOT_EXTRA))]
        folder = syn.write_scene_folder(Path(tmp) / "room", objs, devs, [("AP1", "robot1")],
                                        frequency_hz=2.4e9)
        rng = np.random.default_rng(0)
        rx = np.column_stack([rng.uniform(0.5, 2.8, a.positions), rng.uniform(0.5, 3.5,
                              a.positions), np.full(a.positions, 0.3)])
        k = np.linspace(-40e6, 40e6, a.subcarriers)
        meas = Measurements((0.5, 0.5, 2.0), rx, k, np.ones((a.positions, a.subcarriers)))
        cal = Calibrator(load_scene(folder), meas,
                         [Parameter("permittivity", "concrete"), Parameter("x", "Cabinet"),
                          Parameter("y", "Cabinet")],
                         SolverSettings(max_depth=a.depth, samples_per_src=a.rays))
        cal.evaluate(cal.initial)  # JIT warm-up
        cal.evaluate(cal.initial, grad=False)
        times = {}
        for grad in (False, True):
            t0 = time.perf_counter()
            for i in range(a.repeat):
                cal.evaluate(cal.initial + 0.001 * (i + 1) * cal.scales, grad=grad)
            times[grad] = (time.perf_counter() - t0) / a.repeat
    print(f"calibration step: {a.positions} positions x {a.subcarriers} subcarriers, "
          f"{a.rays} rays, depth {a.depth}, 3 parameters")
    print(f"  forward only (baseline): {times[False]:.3f} s")
    print(f"  gradient step:           {times[True]:.3f} s  ({times[True] / times[False]:.2f}x)")
    return 0


def compiles(evaluations: int = 4) -> int:
    """Kernels compiled per traced evaluation at new poses (module doc)."""
    import drjit as dr

    from isac_twin.scene.bundled import bundled_scene_dir

    offsets = np.linspace(-40e6, 40e6, 6)
    for chains in (False, True):
        scene = load_scene(bundled_scene_dir("aces_lab"))
        objects = list(scene.config.room.furniture)
        rx = np.array([(2.0, 2.0, 0.3), (3.0, 1.5, 0.3), (4.0, 2.5, 0.3)])
        meas = Measurements((1.0, 1.0, 2.5), rx, offsets, np.ones((len(rx), len(offsets))))
        cal = Calibrator(scene, meas, [Parameter(k, o) for o in objects for k in ("x", "y", "yaw")],
                         SolverSettings(max_depth=2, samples_per_src=4000, seed=1, chains=chains))
        rng = np.random.default_rng(0)
        counts = []
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            for i in range(2 + evaluations):
                if i < 2 or i % 2:
                    cal.refresh_chains()
                dr.kernel_history()
                cal.evaluate(rng.normal(0.0, 0.01, len(cal.initial)), grad=False)
                counts.append(sum(1 for h in dr.kernel_history()
                                  if h.get("type") == dr.KernelType.JIT and not h.get("cache_hit")))
        finally:
            dr.set_flag(dr.JitFlag.KernelHistory, False)
        print(f"lab, 30 pose parameters, {'chains' if chains else 'candidate generator'}: kernels "
              f"compiled per evaluation at new poses {counts[2:]} (first evaluation, the baseline: "
              f"{counts[0]}; second {counts[1]}); buffer regrows {cal.buffer_regrows}")
    return 0


def lab(a) -> int:
    import json

    from isac_twin.experiments.lab_calibration import closing_the_loop, localization_errors

    folder = Path(__file__).resolve().parents[1] / "blend_scenes" / "aces_lab" / "scene"
    objects = [o.strip() for o in a.objects.split(",") if o.strip()] or None
    r = closing_the_loop(folder, a.out, snr_db=a.snr, snapshots=a.snapshots,
                         subcarriers=a.subcarriers, max_steps=a.max_steps, objects=objects,
                         dt=2.0, noise=not a.no_noise)
    print(f"lab, one lap ({r['steps']} steps of {r['dt']} s), {a.snapshots} snapshots x "
          f"{a.subcarriers} subcarriers, CSI noise "
          f"{'none' if a.snr is None else f'{a.snr:g} dB SNR'}")
    print(f"{'object':14s} {'truth dx dy (cm) dyaw (deg)':>30s} {'fitted':>24s} "
          f"{'error':>24s}  clear path  unseen")
    for name, o in r["objects"].items():
        f3 = lambda v: " ".join(f"{x:+7.2f}" for x in v)  # noqa: E731
        print(f"{name:14s} {f3(o['truth_cm_deg']):>30s} {f3(o['fitted_cm_deg']):>24s} "
              f"{f3(o['error_cm_deg']):>24s}  {'yes' if o['clear_path'] else 'no':10s}  "
              f"{','.join(o['unobserved'])}")
    m = r["material"]
    print(f"material {m['name']}: permittivity twin {m['twin_permittivity']:.3f}, real "
          f"{m['relative_permittivity']:.3f}, fitted {m['fitted']:.3f} "
          f"({m['error_percent']:.1f} % off)")
    for lk, snr in zip(r["links"], r["noise_snr_db"]):
        print(f"noise estimated on {lk[0]}->{lk[1]}: " + (
            "none (the model's exact power)" if snr is None else
            f"SNR {np.median(snr):.1f} dB (median of {len(snr)} snapshots, "
            f"{min(snr):.1f}..{max(snr):.1f})"))
    mm = r["mismatch_db2"]
    print(f"mismatch {mm['initial']:.4g} -> {mm['final']:.4g} dB^2 (baseline: the original "
          f"twin; {mm['at_truth']:.4g} at the truth"
          f"{': the fit is below it, noise-limited' if mm['final'] < mm['at_truth'] else ''}"
          f"), {r['evaluations']} evaluations at {r['seconds_per_step']:.1f} s, "
          f"{'converged' if r['converged'] else 'NOT converged'} ({r['message']})")
    print(f"recording {r['record_s']:.0f} s, calibration {r['calibration_s']:.0f} s "
          f"(candidate buffer {r['candidate_buffer']['size']}, grown "
          f"{r['candidate_buffer']['regrows']} times)")
    print("stages: " + "; ".join(
        f"{st['stage']} {st['seconds']:.0f} s ({st['evaluations']} evaluations, "
        f"{st['gradient_steps']} with gradients)" for st in r["stages"]))
    if r["polish"]:
        st = r["polish"]
        print(f"polish: {st['traces']} traces, {len(st['parameters'])} coordinates, mismatch "
              f"{st['mismatch_db2']['before']:.4g} -> {st['mismatch_db2']['after']:.4g} dB^2")
    for k, st in enumerate((r["hop"] or {}).get("rounds", [])):
        mm, pa = st["mismatch_db2"], st["polish_after"]
        print(f"hop {k + 1}: {st['traces']} traces, {len(r['hop']['parameters'])} coordinates, "
              f"mismatch {mm['before']:.4g} -> {mm['after']:.4g} dB^2, moved "
              f"{', '.join(st['moved']) or 'nothing'}"
              + (f", then a polish of {pa['traces']} traces -> {pa['mismatch_db2']:.4g} dB^2"
                 if pa else ""))
    for target, o in r["observability"].items():
        share = np.asarray(o["power_share_per_snapshot"]) * 100
        print(f"{target}: paths per snapshot {o['paths_per_snapshot']}, power share max "
              f"{share.max():.2f} % (median {np.median(share):.2f} %), -+10 % permittivity "
              f"changes the mismatch by {o['mismatch_change_db2_at_minus_plus_10_percent'][0]:+.4f}"
              f" / {o['mismatch_change_db2_at_minus_plus_10_percent'][1]:+.4f} dB^2 (residual "
              f"{o['mismatch_final_db2']:.4f} dB^2): 1-sigma {o['uncertainty_percent']:.1f} %")
    for note in r["could_not_see"]:
        print(f"  could not see: {note}")
    if a.localize:
        loc = localization_errors(folder, r["calibrated_scene"], cache_dir=a.out / "cache",
                                  true_folder=r["true_room_scene"])
        r["localization"] = loc
        st = loc["settings"]
        print(f"localization against the truth, realistic mode: {st['method']} + "
              f"{st['fusion']} {'closed loop' if st['closed_loop'] else 'open loop'}, pilots "
              f"{st['snr_db']:g} dB, {st['spacing_m'] * 100:g} cm database, dt {st['dt_s']} s")
        for label in ("original", "calibrated", "true room"):
            e = loc[label]
            print(f"  {label:10s} twin: RMSE {e['rmse'] * 100:.1f} cm, median "
                  f"{e['median'] * 100:.1f} cm, P90 {e['p90'] * 100:.1f} cm, max "
                  f"{e['max'] * 100:.1f} cm over {e['steps']} steps (database "
                  f"{e['database_s']:.0f} s, run {e['run_s']:.0f} s)")
        print(f"  calibrated / original RMSE: "
              f"{loc['calibrated']['rmse'] / loc['original']['rmse']:.2f}x")
    if a.per_fix:
        r["per_fix"] = print_per_fix(folder, r, a.out / "cache")
    (a.out / "lab.json").write_text(json.dumps(r, indent=1))
    return 0


def print_per_fix(folder, r, cache_dir) -> dict:
    """:func:`isac_twin.experiments.lab_calibration.per_fix_errors` of the original, the calibrated and the
    true-room twin on the lap recorded for ``r`` (a :func:`closing_the_loop` result)."""
    from isac_twin.experiments.lab_calibration import per_fix_errors, real_room

    twins = {"original": load_scene(folder), "calibrated": load_scene(r["calibrated_scene"]),
             "true room": real_room(folder, seed=r["seed"])[0]}
    pf = per_fix_errors(twins, real_room(folder, seed=r["seed"])[0], r["recording"],
                        seed=r["seed"], cache_dir=cache_dir)
    st = pf["settings"]
    print(f"per-fix localization against the truth (no fusion), in the real room: pilots "
          f"{st['snr_db']:g} dB (realistic) or the traced paths' delays (the paper's MDP), "
          f"{st['spacing_m'] * 100:g} cm database, {pf['steps']} fixes every {st['dt_s']} s "
          f"along the recorded lap")
    for m in pf["original"]:
        for label in twins:
            e = pf[label][m]
            print(f"  {m:17s} {label:10s} twin: RMSE {e['rmse'] * 100:5.1f} cm, median "
                  f"{e['median'] * 100:5.1f}, P90 {e['p90'] * 100:5.1f}, max "
                  f"{e['max'] * 100:5.1f} cm (database {pf['database_s'][label]:.0f} s)")
    return pf


if __name__ == "__main__":
    sys.exit(main())
