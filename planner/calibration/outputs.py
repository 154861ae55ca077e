"""Pictures and files of a calibration: the measured curves with the fitted FE curve and the
posterior band (5-95 % of the emulated curves of the posterior sample), the parameter cloud
(the weighted posterior sample, pooled and per site), `calibration.json` and `report.html`."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from planner.calibration.emulator import to_params

__all__ = ["write_outputs"]


_LABELS = {"aspiration": ("suction (kPa)", "apex height (mm)"),
           "indentation": ("depth (mm)", "force (mN)")}


def _resample(fit, rng, n):
    w = fit["weights"]
    idx = rng.choice(len(w), size=n, p=w)
    return fit["samples"][idx]


def _band(em, samples):
    y, _ = em.predict(samples)
    return np.percentile(y, 5, axis=0), np.percentile(y, 95, axis=0)


def _curves_png(path, extras, rng):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sites = extras["sites"]
    n = len(sites)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.6), squeeze=False)
    for ax, sd, em, fe, fep in zip(axes[0], sites, extras["emulators"], extras["fe_site"],
                                   extras["fe_pooled"]):
        fit = extras["fits"][sd.name]
        lo, hi = _band(em, _resample(fit, rng, 300))
        ax.fill_between(sd.x, lo, hi, color="#4c72b0", alpha=0.3, label="90 % band (site)")
        if fe is not None:
            ax.plot(sd.x, fe, "-", color="#4c72b0", label="FE, site estimate")
        if fep is not None and n > 1:
            ax.plot(sd.x, fep, "--", color="#c44e52", label="FE, pooled estimate")
        err = sd.noise if sd.noise else None
        ax.errorbar(sd.x, sd.y, yerr=err, fmt="o", ms=3.5, color="k", label="measured")
        xl, yl = _LABELS[sd.site.test]
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_title(f"{sd.name} ({sd.site.test})")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _cloud_png(path, extras, rng):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9.0, 3.8))
    fits = [(name, f) for name, f in extras["fits"].items()]
    if len(extras["sites"]) > 1:
        fits.append(("pooled", extras["pooled"]))
    for k, (name, fit) in enumerate(fits):
        S = _resample(fit, rng, 600)
        c10 = np.exp(S[:, 0])
        ratio = np.exp(S[:, 2])
        col = "k" if name == "pooled" else f"C{k}"
        axes[0].scatter(6 * c10, S[:, 1] * c10, s=3, alpha=0.35, color=col, label=name)
        axes[1].scatter(6 * c10, ratio, s=3, alpha=0.35, color=col, label=name)
        e10, e20, er = to_params(fit["theta"])
        axes[0].plot(6 * e10, e20, "x", color=col, ms=9, mew=2)
        axes[1].plot(6 * e10, fit["fixed_ratio"] or er, "x", color=col, ms=9, mew=2)
    axes[0].set_xlabel("E0 = 6 C10 (kPa)")
    axes[0].set_ylabel("C20 (kPa)")
    axes[1].set_xlabel("E0 = 6 C10 (kPa)")
    axes[1].set_ylabel("dermis / hypodermis ratio")
    axes[0].set_title("posterior sample")
    axes[1].set_title("E0 and dermis ratio (x: estimate)")
    axes[0].legend(fontsize=7, markerscale=3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_outputs(out_dir: Path, report: dict, extras: dict, render: bool = True) -> None:
    """calibration.json, images/*.png and report.html into out_dir (a fresh folder)."""
    from planner.html_report import write_html_report

    out_dir = Path(out_dir)
    rng = np.random.default_rng(0)
    images = []
    if render:
        (out_dir / "images").mkdir(parents=True, exist_ok=True)
        p1 = out_dir / "images" / "curves.png"
        _curves_png(p1, extras, rng)
        p2 = out_dir / "images" / "parameter_cloud.png"
        _cloud_png(p2, extras, rng)
        images = [(p1, "measured curves, FE curve at the estimate and the 90 % posterior band"),
                  (p2, "parameter cloud: the posterior sample (x: estimate)")]
    (out_dir / "calibration.json").write_text(json.dumps(report, indent=2))
    rows = []
    for name, rec in list(report["sites"].items()) + [("pooled", report["pooled"])]:
        rows.append([name, rec["E0_kpa"]["estimate"], rec["E0_kpa"]["interval_90"],
                     rec["C10_kpa"]["estimate"], rec["C20_kpa"]["estimate"],
                     rec["C20_kpa"]["interval_90"], rec["dermis_ratio"]["estimate"],
                     rec["dermis_ratio"]["identifiable"]])
    sens_rows = [[site, r["parameter"], r["S1_level"], r["ST_level"], r["S1_shape"],
                  r["ST_shape"], r["constrained"]]
                 for site, table in report["sensitivity"].items() for r in table]
    tables = {
        "Parameters (hypodermis; the dermis has dermis_ratio times C10 and C20)": (
            ["site", "E0 kPa", "E0 90 %", "C10 kPa", "C20 kPa", "C20 90 %", "dermis ratio",
             "ratio identifiable"], rows),
        "Published values": (["site", "E0 kPa", "90 %", "published", "consistent"],
                             [[c["site"], c["E0_kpa"], c["E0_interval_90"], c["published"],
                               c["consistent"]] for c in report["comparison"]]),
        "Sobol sensitivity of the curve (level: mean ln y; shape: ln y_last - ln y_first)": (
            ["site", "parameter", "S1 level", "ST level", "S1 shape", "ST shape",
             "constrained"], sens_rows),
    }
    intro = ("Patient-specific Yeoh parameters from in-vivo measurements: inverse FE on a layered "
             "slab (dermis over hypodermis on bone) with a Gaussian-process emulator of the "
             "forward runs; 90 % intervals from the posterior. Use `faceplan predict CASE "
             "--materials calibration.json` to predict with them.")
    write_html_report(out_dir / "report.html", "faceplan calibrate", report, images, tables, intro)
