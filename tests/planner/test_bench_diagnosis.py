"""`bench/diagnosis.py` counts a case it cannot load or register as not diagnosed and goes on.

A cohort of many heads must not stop at the first one faceplan fails on: the failure is a
figure of the method (reported with the case, its withheld effect and why) and the remaining
cases are diagnosed. Checked on a cohort kept on disk (`--keep --no-make`) whose only case
folder is empty, so that no solve runs.
"""
import importlib.util
import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _bench():
    spec = importlib.util.spec_from_file_location("bench_diagnosis", REPO / "bench" / "diagnosis.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_case_that_cannot_be_loaded_is_counted_not_diagnosed(tmp_path, capsys):
    seed = 424242
    (tmp_path / "random" / str(seed) / "case_0").mkdir(parents=True)
    (tmp_path / "random" / f"key_{seed}.json").write_text(json.dumps(
        [{"case": "case_0", "effect": "sliding", "value": {"sliding": 1.0}}]))
    rc = _bench().main_bench(["--keep", str(tmp_path), "--no-make", "--random", "1", "--none", "0",
                              "--seed", str(seed), "--workers", "0"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "case_0: not diagnosed:" in out
    # the summary names it, with its withheld effect, and counts no verdict for it
    assert "not diagnosed (faceplan could not register, load, accept or solve the case): 1: case_0 (sliding)" in out
    assert "named 0/0" in out


def test_interval_hits_read_each_parameter_against_its_truth():
    """The bench's interval check: a bone correction's components against the key's vector, a
    segment the key did not move against no correction, factors against their value (1 when
    the key does not set them), and with the achieved movements in the fit the remainder
    against 0."""
    hits = _bench()._interval_hits
    row = {"value": {"bone_execution.maxilla": [0.5, 1.0, 0.0, 1.3, 0.0, 0.0]},
           "fitted": {"bone_execution.maxilla": [0.4, 0.9, 0.0, 0.3, 0.0, 0.0]},
           "intervals": {"bone_execution.maxilla.tx": [0.2, 0.6], "bone_execution.maxilla.rx": [0.0, 0.6],
                         "bone_execution.mandible.ty": [-0.1, 0.1], "bone_execution.mandible.rz": [0.2, 0.4]}}
    assert hits(row) == [True, False, True, False]
    row = {"value": {"stiffness.dermis": 0.6}, "fitted": {},
           "intervals": {"stiffness.dermis": [0.5, 0.7], "stiffness.muscle": [1.1, 1.4]}}
    assert hits(row) == [True, False]
    row = {"value": {"bone_execution.maxilla": [2.0, 0.0, 0.0, 0.0, 0.0, 0.0]}, "fitted": {"bone_execution": 1},
           "intervals": {"bone_execution.maxilla.tx": [-0.1, 0.1]}}
    assert hits(row) == [True]
    assert hits({"value": {"sliding": "maxilla"}, "fitted": {"sliding": "maxilla"}}) == []


def test_stored_solves_are_keyed_by_the_code_they_depend_on(tmp_path):
    """A kept cohort's solves are reused only while the model and solver code is the same: a
    change to a solver source (e.g. a material law) changes the digest, a change to the
    analysis (which reads solves, makes none) does not."""
    bench = _bench()
    for part in bench.SOLVE_CODE:
        p = tmp_path / part
        if p.suffix == ".py":
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text("# " + part + "\n")
        else:
            (p / "sub").mkdir(parents=True)
            (p / "sub" / "law.py").write_text("x = 1\n")
    (tmp_path / "planner" / "diagnosis" / "analysis.py").write_text("y = 1\n")
    d0 = bench._solve_code_digest(tmp_path)
    (tmp_path / "planner" / "diagnosis" / "analysis.py").write_text("y = 2\n")
    assert bench._solve_code_digest(tmp_path) == d0
    (tmp_path / "solver" / "sub" / "law.py").write_text("x = 2\n")
    assert bench._solve_code_digest(tmp_path) != d0
    # and the real tree's digest is stable between two reads
    assert bench._solve_code_digest() == bench._solve_code_digest()
