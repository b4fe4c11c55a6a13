"""The calibration report's figure (``calibration.png`` beside ``calibration.json``).

Left: each fitted parameter's change (after - before) in a readable unit (cm for
x/y offsets, deg for yaw, % of the start value for materials), labelled with
its values before -> after and its sensitivity (|d mismatch / d parameter| at
the start per typical change; unobserved parameters greyed). Right: the RMS
power residual per snapshot (dB) before and after the fit.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def _display(name: str, before: float, after: float) -> tuple[float, str, str]:
    """(change in display unit, unit label, 'before -> after' text) of one parameter."""
    kind = name.rsplit(".", 1)[1]
    if kind in ("x", "y"):
        return (after - before) * 100.0, "cm", f"{before * 100:+.2f} -> {after * 100:+.2f} cm"
    if kind == "yaw":
        return (math.degrees(after - before), "deg",
                f"{math.degrees(before):+.2f} -> {math.degrees(after):+.2f} deg")
    unit = " S/m" if kind == "conductivity" else ""
    rel = 100.0 * (after - before) / before if before else 0.0
    return rel, "%", f"{before:.4g} -> {after:.4g}{unit}"


def plot_report(report: dict, path: str | Path) -> Path:
    """Write the figure of a calibration report (:meth:`CalibrationResult.to_json` plus
    ``calibrate_recording``'s keys) to ``path`` (PNG); return the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    params = report["parameters"]
    unseen = set(report.get("unobserved", []))
    n = len(params)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 1.5 + 0.45 * max(n, 4)),
                                  gridspec_kw={"width_ratios": [3, 2]})
    y = np.arange(n)[::-1]
    for yi, p in zip(y, params):
        change, unit, text = _display(p["name"], p["initial"], p["final"])
        sens = abs(p.get("gradient_initial", 0.0))
        grey = p["name"] in unseen
        ax.barh(yi, change, height=0.45, color="0.75" if grey else "tab:blue")
        ax.text(0.01, yi + 0.26, f"{text}   sensitivity {sens:.3g} dB^2 per unit"
                + ("   NOT SEEN" if grey else ""), fontsize=7, va="bottom",
                transform=ax.get_yaxis_transform())
    ax.set_yticks(y)
    ax.set_yticklabels([f"{p['name']} [{_display(p['name'], 1, 1)[1]}]" for p in params],
                       fontsize=8)
    ax.axvline(0.0, color="k", lw=0.6)
    ax.set_ylim(-0.6, n - 0.1)
    ax.set_xlabel("change after - before (cm, deg, or % of the start value)")
    m = report["mismatch_db2"]
    ax.set_title(f"parameters: mismatch {m['initial']:.3g} -> {m['final']:.3g} dB^2, "
                 f"{'converged' if report.get('converged') else 'NOT converged'}", fontsize=9)
    after = np.asarray(report["residual_db_per_measurement"], float)
    before = report.get("residual_db_per_measurement_initial")
    k = np.arange(len(after))
    if before is not None:
        ax2.plot(k, before, "o-", color="tab:red", label="before")
    ax2.plot(k, after, "o-", color="tab:green", label="after")
    ax2.set_xticks(k)
    ax2.set_xlabel("snapshot")
    ax2.set_ylabel("RMS power residual (dB)")
    ax2.set_title("residual per snapshot", fontsize=9)
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
