"""The calibration workflow of `faceplan calibrate`: design, parallel forward runs, emulators,
identification per site and pooled, FE check, pictures and the report.

Two space-filling stages (history matching's refocusing, Vernon, Goldstein & Bower 2010): a
Latin hypercube over the prior box trains a first emulator per site (on a mesh of half the
resolution); the parameter sets whose
implausibility max_k |y_k - mu_k| / sqrt(sigma^2 + s_k^2) stays below 3 for some site (the
cut-off of Pukelsheim's three-sigma rule) bound a smaller box, in which a second hypercube
trains the emulators used for the estimate and the posterior, and a separate hypercube of
held-out runs measures their error. The estimates are finally run through the FE model, whose
curve and residual are the ones reported.
"""
from __future__ import annotations

import sys
import time
from dataclasses import replace

import numpy as np

from planner.calibration.emulator import (PARAMETERS, PRIOR_BOX, fit_emulator, latin_hypercube,
                                          run_forward, to_params)
from planner.calibration.identify import identify, sobol_table, summarise
from planner.calibration.slab import BULK_FACTOR, MeshOptions

__all__ = ["calibrate_sites", "materials_block", "PUBLISHED"]

# published initial Young's moduli of face sites (kPa), as the issue and the method cite them
PUBLISHED = {
    "aspiration": {"range_kpa": [31.0, 42.0],
                   "source": "Luboz et al. 2014, LASTIC aspiration in vivo (cheek, cheekbone, "
                             "forehead, lower lip)"},
    "indentation": {"sites_kpa": {"cheek": 16.0, "cheekbone": 65.0, "chin": 53.0},
                    "source": "indentation of face tissue (cheek ~16, cheekbone ~65, "
                              "chin ~53 kPa)"},
}


def _say(echo, msg):
    if echo:
        print(msg, file=sys.stderr, flush=True)


def _focus_box(sites, ems, rng, n=6000):
    """Bounding box (with a margin) of the not implausible parameter sets of any site."""
    T = PRIOR_BOX[:, 0] + rng.random((n, 3)) * (PRIOR_BOX[:, 1] - PRIOR_BOX[:, 0])
    keep = np.zeros(n, dtype=bool)
    for sd, em in zip(sites, ems):
        mu, s = em.predict(T)
        sig = sd.noise if sd.noise else 0.05 * (sd.y.max() - sd.y.min())
        imp = np.max(np.abs(sd.y - mu) / np.sqrt(sig ** 2 + s ** 2), axis=1)
        ok = imp < 3.0
        if ok.sum() < 10:               # the first emulator too coarse: the best 2 %
            ok = imp <= np.quantile(imp, 0.02)
        keep |= ok
    lo, hi = T[keep].min(0), T[keep].max(0)
    margin = 0.15 * (hi - lo) + 0.02 * (PRIOR_BOX[:, 1] - PRIOR_BOX[:, 0])
    box = np.column_stack([np.maximum(lo - margin, PRIOR_BOX[:, 0]),
                           np.minimum(hi + margin, PRIOR_BOX[:, 1])])
    return box, int(keep.sum()), n


def materials_block(c10: float, c20: float, ratio: float) -> dict:
    """`model.materials` entries (facemodel.materials parameter names) of the two layers."""
    def yeoh(f):
        return {"C10": round(f * c10, 5), "C20": round(f * c20, 5),
                "K": round(BULK_FACTOR * 2.0 * f * c10, 3)}
    return {"hypodermis": yeoh(1.0), "dermis": yeoh(ratio)}


def calibrate_sites(sites, client, *, opt: MeshOptions = MeshOptions(), n_stage1: int = 16,
                    n_stage2: int = 24, n_heldout: int = 8, seed: int = 0, echo: bool = True):
    """Calibrate; returns (report dict, extras for the pictures)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    _say(echo, f"calibrate: {len(sites)} site(s); stage 1: {n_stage1} forward runs per site "
               f"over the prior box")
    th1 = latin_hypercube(PRIOR_BOX, n_stage1, seed)
    # stage 1 only bounds the plausible region (with a margin): a mesh of half the resolution
    # (curves within ~2 % of the full one) serves it at a third of the cost
    opt1 = replace(opt, n_fine=max(4, opt.n_fine // 2))
    out1 = run_forward(client, [(sd.site, sd.x, t) for sd in sites for t in th1], opt1,
                       "stage 1", echo)
    timings = {"stage1_runs": time.perf_counter() - t0}
    ems1 = [fit_emulator(PRIOR_BOX, th1, out1[i * n_stage1:(i + 1) * n_stage1], seed)
            for i in range(len(sites))]
    box, n_plausible, n_tried = _focus_box(sites, ems1, rng)
    _say(echo, f"calibrate: focused box C10 {np.exp(box[0, 0]):.3g}-{np.exp(box[0, 1]):.3g} kPa, "
               f"C20/C10 {box[1, 0]:.2f}-{box[1, 1]:.2f}, ratio {np.exp(box[2, 0]):.2f}-"
               f"{np.exp(box[2, 1]):.2f}; stage 2: {n_stage2} + {n_heldout} held-out runs per site")
    th2 = latin_hypercube(box, n_stage2, seed + 1)
    thh = latin_hypercube(box, n_heldout, seed + 2)
    both = np.vstack([th2, thh])
    t1 = time.perf_counter()
    out2 = run_forward(client, [(sd.site, sd.x, t) for sd in sites for t in both], opt,
                       "stage 2", echo)
    timings["stage2_runs"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    m = len(both)
    ems, heldout = [], []
    for i, sd in enumerate(sites):
        runs = out2[i * m:(i + 1) * m]
        em = fit_emulator(box, th2, runs[:n_stage2], seed)
        ems.append(em)
        ok = [j for j in range(n_heldout) if runs[n_stage2 + j] is not None]
        if ok:
            pred, _ = em.predict(thh[ok])
            fe = np.asarray([runs[n_stage2 + j] for j in ok])
            heldout.append(np.abs(pred / fe - 1.0))
    err = np.concatenate([h.ravel() for h in heldout]) if heldout else np.array([np.nan])
    _say(echo, f"calibrate: emulator held-out error max {100 * np.nanmax(err):.2f} %, "
               f"rms {100 * np.sqrt(np.nanmean(err ** 2)):.2f} %")

    fits = {}
    for sd, em in zip(sites, ems):
        fits[sd.name] = identify([sd], [em], box, rng)
    pooled = identify(sites, ems, box, rng) if len(sites) > 1 else fits[sites[0].name]

    timings["emulators_and_posteriors"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    # the FE model at the estimates: the reported curves and residuals
    jobs = [(sd.site, sd.x, fits[sd.name]["theta"]) for sd in sites]
    jobs += [(sd.site, sd.x, pooled["theta"]) for sd in sites]
    fe = run_forward(client, jobs, opt, "FE check", echo)
    n = len(sites)
    timings["fe_check_runs"] = time.perf_counter() - t1
    t1 = time.perf_counter()

    def _fe_rms(curve, sd):
        return None if curve is None else round(float(np.sqrt(np.mean((curve - sd.y) ** 2))), 6)

    site_records = {}
    extras = {"sites": sites, "fits": fits, "pooled": pooled, "emulators": ems, "box": box,
              "fe_site": fe[:n], "fe_pooled": fe[n:]}
    for i, sd in enumerate(sites):
        rec = summarise(fits[sd.name])
        rec.update(test=sd.site.test, n_points=int(len(sd.x)),
                   residual_rms_fe=_fe_rms(fe[i], sd),
                   units={"curve": "mm" if sd.site.test == "aspiration" else "mN"})
        site_records[sd.name] = rec
    pooled_rec = summarise(pooled)
    pooled_rec["residual_rms_fe"] = {sd.name: _fe_rms(fe[n + i], sd) for i, sd in enumerate(sites)}
    # the pooled residual per site (each in its curve's units); one number when all sites
    # measure the same quantity, and in units of each site's noise over all sites
    res, k = pooled["residuals"], 0
    per_site, normalised = {}, []
    for sd, sig in zip(sites, pooled["sigmas"]):
        r = res[k:k + len(sd.y)]
        k += len(sd.y)
        per_site[sd.name] = round(float(np.sqrt(np.mean(r ** 2))), 6)
        normalised.append(r / sig)
    pooled_rec["residual_rms_sites"] = per_site
    pooled_rec["residual_rms_normalised"] = round(float(np.sqrt(np.mean(
        np.concatenate(normalised) ** 2))), 4)
    if len({sd.site.test for sd in sites}) == 1:
        pooled_rec["residual_rms"] = round(float(pooled["residual_rms"]), 6)
    else:
        pooled_rec["residual_rms"] = per_site
    sens = {sd.name: sobol_table(em1) for sd, em1 in zip(sites, ems1)}
    timings["sensitivity"] = time.perf_counter() - t1
    c10, c20, ratio = to_params(pooled["theta"])
    if pooled["fixed_ratio"] is not None:
        ratio = float(pooled["fixed_ratio"])
    report = {
        "faceplan": 1,
        "command": "calibrate",
        "parameters": {"C10_kpa": "hypodermis Yeoh C10", "C20_kpa": "hypodermis Yeoh C20",
                       "E0_kpa": "6 C10, initial Young's modulus (incompressible)",
                       "dermis_ratio": "dermis / hypodermis, both C10 and C20"},
        "sites": site_records,
        "pooled": pooled_rec,
        "emulator": {"n_runs": int(sum(e.n_runs for e in ems)),
                     "n_runs_per_site": [int(e.n_runs) for e in ems],
                     "n_stage1_runs_per_site": int(n_stage1),
                     "heldout_error_pct": _finite(100 * np.nanmax(err)),
                     "heldout_rms_pct": _finite(100 * np.sqrt(np.nanmean(err ** 2))),
                     "n_heldout_runs_per_site": int(n_heldout),
                     "focused_box": {name: [round(float(a), 4), round(float(b), 4)]
                                     for name, (a, b) in zip(PARAMETERS, box)},
                     "plausible_fraction_stage1": round(n_plausible / n_tried, 4)},
        "sensitivity": sens,
        "materials": materials_block(c10, c20, ratio),
        "published": PUBLISHED,
        "comparison": _comparison(sites, site_records),
        "mesh": {"n_fine": opt.n_fine, "growth": opt.growth, "lateral": opt.lateral,
                 "n_skin": opt.n_skin, "wedge_deg": opt.wedge_deg},
        "timings_s": {**{k: round(v, 2) for k, v in timings.items()},
                      "total": round(time.perf_counter() - t0, 2)},
    }
    return report, extras


def _finite(v, digits=3):
    """A JSON-safe number: None when no held-out run succeeded."""
    return round(float(v), digits) if np.isfinite(v) else None


def _comparison(sites, records) -> list[dict]:
    rows = []
    for sd in sites:
        rec = records[sd.name]
        e = rec["E0_kpa"]
        if sd.site.test == "aspiration":
            lo, hi = PUBLISHED["aspiration"]["range_kpa"]
            ref = f"{lo:g}-{hi:g} kPa (aspiration, Luboz et al. 2014)"
            within = lo <= e["estimate"] <= hi
        else:
            pub = PUBLISHED["indentation"]["sites_kpa"]
            key = next((k for k in sorted(pub, key=len, reverse=True) if k in sd.name.lower()),
                       None)
            ref = f"~{pub[key]:g} kPa ({key}, indentation)" if key else \
                "cheek ~16, cheekbone ~65, chin ~53 kPa (indentation)"
            within = None if key is None else bool(0.5 * pub[key] <= e["estimate"] <= 2 * pub[key])
        rows.append({"site": sd.name, "test": sd.site.test, "E0_kpa": e["estimate"],
                     "E0_interval_90": e["interval_90"], "published": ref,
                     "consistent": within})
    return rows
