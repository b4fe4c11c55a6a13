"""``calibrate``: fit a scene's materials and object poses to recorded CSI."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..calibration import calibrate_recording
from ..errors import UsageError
from .options import scene_arg, scene_path

__all__ = ["COMMANDS", "cmd_calibrate", "parse_links"]


def _calibrate_args(p: argparse.ArgumentParser) -> None:
    scene_arg(p)
    p.add_argument("--measurements", type=Path, required=True,
                   help="an .mcap written by `isac-twin record` (/<robot>/csi and "
                        "/<robot>/ground_truth)")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder: scene/ (calibrated) and calibration.json")
    p.add_argument("--params", default="materials",
                   help="comma-separated: materials, poses (default materials)")
    p.add_argument("--objects", default="", help="comma-separated objects whose x, y, yaw "
                                                 "offsets are fitted (with --params poses)")
    p.add_argument("--materials", default="",
                   help="comma-separated materials fitted with --params materials: ITU "
                        "type, custom name or TYPE-THICKNESS such as wood-0.03 (default: "
                        "every material but metal)")
    p.add_argument("--links", default=None, metavar="TX,RX[;TX,RX...]",
                   help="the recorded links to use (default: every recorded link)")
    p.add_argument("--snapshots", type=int, default=6,
                   help="CSI messages used per link (default 6)")
    p.add_argument("--subcarriers", type=int, default=16,
                   help="recorded subcarriers used (default 16)")
    p.add_argument("--max-steps", type=int, default=30, help="optimiser iterations per start")
    p.add_argument("--pose-scan", action="store_true",
                   help="scan each fitted x/y/yaw offset (lambda/8 steps within +-10 cm, "
                        "1 deg within +-5 deg) before fitting, against local minima")
    p.add_argument("--no-scan", action="store_true",
                   help="start at the scene's permittivities (no scan, single start)")
    p.add_argument("--no-hop", action="store_true",
                   help="with poses: after the pose polish, do not scan the x/y offsets of "
                        "the objects with a clear path across the next half-wavelength "
                        "basins (shifts of 0.3-0.6 wavelength in wavelength/12 steps)")
    p.add_argument("--no-noise", action="store_true",
                   help="compare the model's exact power (default: each snapshot's noise, "
                        "estimated from the delay-domain tail of all its recorded "
                        "subcarriers, is added to the model's power)")


def parse_links(text: str) -> list[tuple[str, str]]:
    """``--links`` text ``TX,RX[;TX,RX...]`` -> ``[(tx, rx), ...]``.

    Raises:
        UsageError: not of that form.
    """
    links = [tuple(p.strip() for p in lk.split(",")) for lk in text.split(";")]
    if not links or any(len(lk) != 2 or not all(lk) for lk in links):
        raise UsageError(f"--links: expected TX,RX[;TX,RX...], got {text!r}")
    return links


def _names(text: str) -> list[str]:
    """A comma-separated option -> its non-empty names."""
    return [n.strip() for n in text.split(",") if n.strip()]


def cmd_calibrate(args) -> int:
    """Fit materials and/or object poses of a scene to a recording's CSI (Sionna's
    gradients); write the calibrated scene folder and calibration.json."""
    links = parse_links(args.links) if args.links is not None else None
    if not args.measurements.is_file():
        raise UsageError(f"--measurements {args.measurements}: no such file")
    run = calibrate_recording(scene_path(args), args.measurements, args.out,
                              what=tuple(_names(args.params)), objects=_names(args.objects),
                              links=links, max_snapshots=args.snapshots,
                              max_subcarriers=args.subcarriers, max_steps=args.max_steps,
                              scan=not args.no_scan, pose_scan=args.pose_scan,
                              hop=not args.no_hop, noise=not args.no_noise,
                              materials=_names(args.materials) or None)
    r = run.report
    for p in r["parameters"]:
        print(f"{p['name']:32s} {p['initial']:12.6g} -> {p['final']:12.6g}")
    m = r["mismatch_db2"]
    print(f"mismatch {m['initial']:.4g} -> {m['final']:.4g} dB^2, "
          f"{'converged' if r['converged'] else 'NOT converged'} ({r['message']}), "
          f"{r['evaluations']} evaluations at {r['seconds_per_step']:.2f} s")
    if r["unobserved"]:
        print(f"not seen by the measurements: {', '.join(r['unobserved'])}")
    for name, mat in r["materials_written"].items():
        print(f"material {name}: eps_r {mat['relative_permittivity']:.6g}, sigma "
              f"{mat['conductivity']:.6g} S/m, {mat['thickness']:g} m")
    print(f"wrote {run.scene_dir} and {run.report_path}")
    return 0


#: command -> (adds its options to a sub-parser, runs it: args -> exit status)
COMMANDS = {"calibrate": (_calibrate_args, cmd_calibrate)}
