"""Calibration data: the shipped example reads; bad input is refused (exit 2) naming the file,
the row and the field, and nothing is written."""
import shutil
from importlib.resources import files
from pathlib import Path

import numpy as np
import pytest

from planner.calibration.data import read_calibration_data
from planner.cli import main
from planner.errors import InputError

EXAMPLE = Path(str(files("planner") / "data" / "calibration_example"))


def test_example_reads():
    sites = read_calibration_data(EXAMPLE)
    assert [s.name for s in sites] == ["cheek_left", "cheekbone_left"]
    a, i = sites
    assert a.site.test == "aspiration" and a.site.aperture_mm == 10.0 and a.noise == 0.015
    assert np.all(np.diff(a.x) > 0) and len(a.x) == 8
    assert i.site.test == "indentation" and i.site.max_depth_mm == pytest.approx(i.x.max())


@pytest.fixture
def data(tmp_path):
    d = tmp_path / "data"
    shutil.copytree(EXAMPLE, d)
    return d


def _edit(path, old, new):
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def _refused(data, capsys, *words):
    out = data.parent / "out"
    rc = main(["calibrate", str(data), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert not out.exists()
    for w in words:
        assert w in err, err
    return err


def test_non_monotonic_curve(data, capsys):
    _edit(data / "cheek_left.csv", "7.50,", "4.50,")
    _refused(data, capsys, "cheek_left.csv", "row 3", "pressure_kpa", "not monotonic")


def test_decreasing_measured_quantity(data, capsys):
    _edit(data / "cheekbone_left.csv", "222.78", "100.0")
    _refused(data, capsys, "cheekbone_left.csv", "row 4", "force_mn", "not monotonic")


def test_negative_thickness(data, capsys):
    _edit(data / "sites.yaml", "fat_mm: 5.0", "fat_mm: -5.0")
    _refused(data, capsys, "sites.yaml", "sites[1] (cheekbone_left).fat_mm", "positive")


def test_pressure_in_pascal(data, capsys):
    text = (data / "cheek_left.csv").read_text().splitlines()
    rows = [text[0]] + [f"{float(r.split(',')[0]) * 1000:.0f},{r.split(',')[1]}" for r in text[1:]]
    (data / "cheek_left.csv").write_text("\n".join(rows) + "\n")
    _refused(data, capsys, "cheek_left.csv", "row 1", "pressure_kpa", "Pa")


def test_force_in_newton(data, capsys):
    text = (data / "cheekbone_left.csv").read_text().splitlines()
    rows = [text[0]] + [f"{r.split(',')[0]},{float(r.split(',')[1]) / 1000:.6f}" for r in text[1:]]
    (data / "cheekbone_left.csv").write_text("\n".join(rows) + "\n")
    _refused(data, capsys, "cheekbone_left.csv", "force_mn", "mN")


def test_missing_column(data, capsys):
    _edit(data / "cheek_left.csv", "pressure_kpa,height_mm", "pressure_kpa,apex_mm")
    _refused(data, capsys, "cheek_left.csv", "height_mm", "missing column")


def test_unknown_key(data, capsys):
    _edit(data / "sites.yaml", "    rim_mm: 3.0", "    rim_mm: 3.0\n    rim_width: 3.0")
    _refused(data, capsys, "sites.yaml", "rim_width", "unknown key")


def test_bad_number_and_missing_file(data, capsys):
    _edit(data / "cheek_left.csv", "10.00,", "ten,")
    _refused(data, capsys, "row 4", "pressure_kpa", "not a number")
    _refused(data / "nothing.yaml", capsys, "not found")


def test_inline_curve_and_yaml_file(tmp_path):
    f = tmp_path / "one.yaml"
    f.write_text("faceplan_calibration: 1\nsites:\n  - name: chin\n    test: indentation\n"
                 "    indenter_radius_mm: 2\n    skin_mm: 2\n    fat_mm: 6\n"
                 "    curve: {depth_mm: [0, 0.3, 0.6, 0.9], force_mn: [0, 10, 30, 60]}\n")
    (s,) = read_calibration_data(f)
    assert s.noise is None and list(s.x) == [0.3, 0.6, 0.9]
    f.write_text(f.read_text().replace("force_mn: [0, 10, 30, 60]", "force_mn: [0, 10, 30]"))
    with pytest.raises(InputError, match="differ in length"):
        read_calibration_data(f)
