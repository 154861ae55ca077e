"""Reading and checking the measurements of `faceplan calibrate DATA`.

DATA is a YAML file (or a folder holding `sites.yaml`) listing sites; each site gives its test
(`aspiration`: pressure_kpa, height_mm; `indentation`: depth_mm, force_mn), the device
geometry, the local dermis and hypodermis thickness, the measurement noise (standard deviation
of the measured quantity, mm or mN; optional) and its curve, as a CSV file beside the YAML or
inline as a mapping of columns. Every mistake is an `InputError` naming the file, the row (1 =
first data row of a CSV) and the field. Units are checked by physical range, since a value
1000 times off is the common slip: a suction cannot exceed one atmosphere (101.3 kPa; a
value above it is a pressure in Pa), an apex height cannot exceed the aperture, a depth cannot
exceed the tissue, and the force of an indentation must give an apparent Hertz modulus of a
soft tissue (0.1-5000 kPa, else it is in N or uN).
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from planner.calibration.slab import Site
from planner.errors import InputError

__all__ = ["SiteData", "read_calibration_data", "COLUMNS"]

COLUMNS = {"aspiration": ("pressure_kpa", "height_mm"), "indentation": ("depth_mm", "force_mn")}
ATMOSPHERE_KPA = 101.325
_TOP_KEYS = {"faceplan_calibration", "sites", "patient", "notes"}
_SITE_KEYS = {"name", "test", "aperture_mm", "rim_mm", "indenter_radius_mm", "skin_mm",
              "fat_mm", "noise", "curve", "location", "notes"}
_RANGES = {"skin_mm": (0.2, 10.0), "fat_mm": (0.5, 80.0), "aperture_mm": (1.0, 50.0),
           "rim_mm": (0.2, 20.0), "indenter_radius_mm": (0.1, 50.0)}


@dataclass(frozen=True)
class SiteData:
    name: str
    site: Site
    x: np.ndarray                   # pressures (kPa) or depths (mm), increasing, > 0
    y: np.ndarray                   # heights (mm) or forces (mN)
    noise: float | None             # standard deviation of y, None = unknown
    source: str                     # the file the curve came from

    @property
    def columns(self) -> tuple[str, str]:
        return COLUMNS[self.site.test]


def _number(v, file, field, positive=True):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise InputError(f"must be a finite number, got {v!r}", file=file, field=field)
    v = float(v)
    if positive and v <= 0:
        raise InputError(f"must be positive, got {v:g}", file=file, field=field)
    return v


def _read_yaml(path: Path) -> dict:
    import yaml

    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read: {exc}", file=str(path)) from None
    except yaml.YAMLError as exc:
        raise InputError(f"not valid YAML: {exc}", file=str(path)) from None
    if not isinstance(doc, dict):
        raise InputError("must be a mapping with faceplan_calibration and sites", file=str(path))
    return doc


def _read_csv(path: Path, columns, field: str):
    if not path.is_file():
        raise InputError("curve file not found", file=str(path), field=field)
    try:
        with path.open(newline="") as fh:
            rows = [r for r in csv.reader(fh) if r and not r[0].lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"cannot read the curve: {exc}", file=str(path)) from None
    if not rows:
        raise InputError("empty curve file", file=str(path))
    header = [h.strip() for h in rows[0]]
    for c in columns:
        if c not in header:
            raise InputError(f"missing column {c!r} (the header has {', '.join(header)}; "
                             f"expected {', '.join(columns)})", file=str(path), field=c)
    idx = [header.index(c) for c in columns]
    out = []
    for i, row in enumerate(rows[1:], start=1):
        vals = []
        for c, j in zip(columns, idx):
            try:
                v = float(row[j])
            except (IndexError, ValueError):
                raise InputError(f"row {i}: not a number: {row[j] if j < len(row) else ''!r}",
                                 file=str(path), field=c) from None
            if not math.isfinite(v):
                raise InputError(f"row {i}: not finite", file=str(path), field=c)
            vals.append(v)
        out.append(vals)
    return np.asarray(out, dtype=float).reshape(-1, 2)


def _inline(curve, columns, file, field):
    if set(curve) != set(columns):
        missing = [c for c in columns if c not in curve]
        extra = [c for c in curve if c not in columns]
        raise InputError(f"curve columns must be {', '.join(columns)}"
                         + (f"; missing {', '.join(missing)}" if missing else "")
                         + (f"; unknown {', '.join(map(str, extra))}" if extra else ""),
                         file=file, field=field)
    cols = []
    for c in columns:
        v = curve[c]
        if not isinstance(v, list):
            raise InputError("must be a list of numbers", file=file, field=f"{field}.{c}")
        cols.append([_number(x, file, f"{field}.{c}[{i + 1}]", positive=False)
                     for i, x in enumerate(v)])
    if len(cols[0]) != len(cols[1]):
        raise InputError(f"{columns[0]} and {columns[1]} differ in length", file=file, field=field)
    return np.asarray(cols, dtype=float).T.reshape(-1, 2)


def _check_curve(xy, site: Site, noise, file, columns, field_prefix=""):
    cx, cy = (field_prefix + c for c in columns)
    x, y = xy[:, 0].copy(), xy[:, 1].copy()
    if site.test == "aspiration" and len(x) and np.all(x <= 0):
        x = -x                      # suction given as negative gauge pressure
    for i in range(len(x)):
        if x[i] < 0 or (x[i] == 0 and y[i] != 0):
            raise InputError(f"row {i + 1}: {columns[0]} must be positive "
                             f"(suction magnitude or depth; give all signs alike)", file=file, field=cx)
        if site.test == "aspiration" and x[i] > ATMOSPHERE_KPA:
            raise InputError(f"row {i + 1}: suction {x[i]:g} exceeds one atmosphere "
                             f"({ATMOSPHERE_KPA} kPa): the values look like Pa; give kPa",
                             file=file, field=cx)
        if site.test == "aspiration" and y[i] >= site.aperture_mm:
            raise InputError(f"row {i + 1}: height {y[i]:g} mm is not below the aperture "
                             f"({site.aperture_mm:g} mm): is it in micrometres? give mm",
                             file=file, field=cy)
        if site.test == "indentation" and x[i] >= site.thickness:
            raise InputError(f"row {i + 1}: depth {x[i]:g} mm is not below the tissue thickness "
                             f"({site.thickness:g} mm): is it in micrometres? give mm",
                             file=file, field=cx)
        if y[i] < 0:
            raise InputError(f"row {i + 1}: must not be negative", file=file, field=cy)
    keep = x > 0
    rows = np.nonzero(keep)[0] + 1
    x, y = x[keep], y[keep]
    if len(x) < 3:
        raise InputError(f"the curve needs at least 3 points with {columns[0]} > 0, "
                         f"got {len(x)}", file=file, field=cx)
    for j in range(1, len(x)):
        if not x[j] > x[j - 1]:
            raise InputError(f"row {rows[j]}: the curve is not monotonic: {columns[0]} "
                             f"{x[j]:g} after {x[j - 1]:g} (must increase)", file=file, field=cx)
        # the measured quantity may dip by measurement noise, not more
        slack = 2.0 * noise if noise else 0.0
        if y[j] < y[j - 1] - slack:
            raise InputError(f"row {rows[j]}: the curve is not monotonic: {columns[1]} "
                             f"{y[j]:g} after {y[j - 1]:g}", file=file, field=cy)
    if y[-1] <= 0:
        raise InputError("the measured quantity never rises above 0", file=file, field=cy)
    if site.test == "indentation":
        # apparent Hertz modulus of an incompressible half-space, E = 9 F / (16 sqrt(R) d^1.5)
        e = 9.0 * y / (16.0 * np.sqrt(site.indenter_radius_mm) * x ** 1.5)
        e_app = float(np.median(e[y > 0])) if np.any(y > 0) else 0.0
        if not 0.1 <= e_app <= 5000.0:
            raise InputError(f"the forces give an apparent modulus of {e_app:.3g} kPa, outside "
                             f"soft tissue (0.1-5000 kPa): are they in N or uN? give mN",
                             file=file, field=cy)
    return x, y


def read_calibration_data(data: str | Path) -> list[SiteData]:
    """The sites of a calibration data file (or folder with sites.yaml), checked."""
    data = Path(data)
    if data.is_dir():
        path = data / "sites.yaml"
        if not path.is_file():
            raise InputError("a calibration data folder must hold sites.yaml", file=str(data))
    elif data.is_file():
        path = data
    else:
        raise InputError("calibration data not found", file=str(data))
    f = str(path)
    doc = _read_yaml(path)
    unknown = sorted(set(map(str, doc)) - _TOP_KEYS)
    if unknown:
        raise InputError(f"unknown key(s) {', '.join(unknown)} (known: "
                         f"{', '.join(sorted(_TOP_KEYS))})", file=f, field=unknown[0])
    if doc.get("faceplan_calibration") != 1:
        raise InputError("must be 1 (the format version)", file=f, field="faceplan_calibration")
    sites = doc.get("sites")
    if not isinstance(sites, list) or not sites:
        raise InputError("must be a non-empty list of sites", file=f, field="sites")
    out, names = [], set()
    for k, s in enumerate(sites):
        fld = f"sites[{k}]"
        if not isinstance(s, dict):
            raise InputError("must be a mapping", file=f, field=fld)
        unknown = sorted(set(map(str, s)) - _SITE_KEYS)
        if unknown:
            raise InputError(f"unknown key(s) {', '.join(unknown)} (known: "
                             f"{', '.join(sorted(_SITE_KEYS))})", file=f, field=f"{fld}.{unknown[0]}")
        name = s.get("name", f"site{k + 1}")
        if not isinstance(name, str) or not name.strip() or "/" in name or "\\" in name:
            raise InputError("must be a plain name", file=f, field=f"{fld}.name")
        if name in names:
            raise InputError(f"site name {name!r} used twice", file=f, field=f"{fld}.name")
        names.add(name)
        fld = f"sites[{k}] ({name})"
        test = s.get("test")
        if test not in COLUMNS:
            raise InputError(f"must be aspiration or indentation, got {test!r}", file=f,
                             field=f"{fld}.test")
        needed = ["skin_mm", "fat_mm", "curve"] + (["aperture_mm", "rim_mm"] if test == "aspiration"
                                                   else ["indenter_radius_mm"])
        for key in needed:
            if key not in s:
                raise InputError("missing", file=f, field=f"{fld}.{key}")
        for key in ("skin_mm", "fat_mm"):
            if isinstance(s[key], dict) and "from_case" in s[key]:
                raise InputError("thickness from a case is not available in this build: give the "
                                 "thickness in mm (measured on the CT or by ultrasound)",
                                 file=f, field=f"{fld}.{key}")
        geo = {}
        for key in ("skin_mm", "fat_mm", "aperture_mm", "rim_mm", "indenter_radius_mm"):
            if key in s:
                v = _number(s[key], f, f"{fld}.{key}")
                lo, hi = _RANGES[key]
                if not lo <= v <= hi:
                    raise InputError(f"{v:g} mm is outside {lo:g}-{hi:g} mm", file=f,
                                     field=f"{fld}.{key}")
                geo[key] = v
        noise = s.get("noise")
        if noise is not None:
            noise = _number(noise, f, f"{fld}.noise")
        site = Site(test=test, **geo)
        cols = COLUMNS[test]
        curve = s["curve"]
        if isinstance(curve, str):
            cpath = (path.parent / curve)
            xy = _read_csv(cpath, cols, f"{fld}.curve")
            src, prefix = str(cpath), ""
        elif isinstance(curve, dict):
            xy = _inline(curve, cols, f, f"{fld}.curve")
            src, prefix = f, f"{fld}.curve."
        else:
            raise InputError("must be a CSV file name or a mapping of columns", file=f,
                             field=f"{fld}.curve")
        x, y = _check_curve(xy, site, noise, src, cols, prefix)
        if test == "indentation":
            site = Site(test=test, max_depth_mm=float(x.max()), **geo)
        if noise is not None and noise >= 0.5 * (y.max() - y.min()):
            raise InputError(f"noise {noise:g} is not small against the curve's range "
                             f"{y.max() - y.min():.3g}", file=f, field=f"{fld}.noise")
        out.append(SiteData(name, site, x, y, noise, src))
    return out
