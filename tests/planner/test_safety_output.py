"""Nothing the user already has is destroyed: `--out` is checked before any work.

Every command refuses, with exit 2 naming the path and before reading the case, an output
location that holds something that is not a previous output of the same command: an existing
file, the case folder or a parent of it, the working directory, home, a non-empty folder
without the marker; and a location that cannot be written to or lacks free space.
"""
import json
import os
import shutil
from pathlib import Path

import pytest

from planner import atomic
from planner.atomic import MARKER, atomic_output_dir, check_output, prepare_output
from planner.cli import main
from planner.errors import InputError


@pytest.fixture
def case(tmp_path):
    """A case folder whose files must survive every refused command (never read: the check
    comes first)."""
    c = tmp_path / "case"
    (c / "preop" / "bone").mkdir(parents=True)
    (c / "preop" / "skin.stl").write_text("solid skin\nendsolid skin\n")
    (c / "preop" / "bone" / "maxilla.stl").write_text("solid b\nendsolid b\n")
    (c / "plan.yaml").write_text("faceplan: 1\nsegments: {}\n")
    (c / "case.yaml").write_text("id: x\n")
    return c


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def no_work(monkeypatch):
    """Any attempt to read a case or a prediction fails the test: the refusal must come first."""
    def boom(*a, **k):
        raise AssertionError("work started before --out was checked")

    import planner.case
    import planner.compare.inputs
    import planner.pipeline

    monkeypatch.setattr(planner.case, "load_case", boom)
    monkeypatch.setattr(planner.compare.inputs, "read_prediction", boom)
    monkeypatch.setattr(planner.pipeline, "run_demo", boom)


def _argv(command, case, out):
    if command == "demo":
        return ["demo", "--out", str(out), "--no-images", "--quiet"]
    if command == "predict":
        return ["predict", str(case), "--out", str(out), "--no-images", "--quiet"]
    if command == "register":
        return ["register", str(case), "--out", str(out), "--no-images"]
    return ["compare", str(case), "--out", str(out), "--no-images"]


COMMANDS = ("predict", "register", "compare", "demo")


@pytest.mark.parametrize("command", COMMANDS)
def test_existing_file_is_refused(command, case, tmp_path, no_work, capsys):
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes")
    assert main(_argv(command, case, notes)) == 2
    err = capsys.readouterr().err
    assert str(notes) in err and "--out" in err and "existing file" in err
    assert notes.read_text() == "my notes"


@pytest.mark.parametrize("command", ("predict", "register", "compare"))
def test_case_folder_and_its_parent_are_refused(command, case, tmp_path, no_work, capsys):
    before = _snapshot(tmp_path)
    for out in (case, tmp_path):
        assert main(_argv(command, case, out)) == 2
        err = capsys.readouterr().err
        assert str(out) in err and "input" in err
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("command", COMMANDS)
def test_working_directory_and_home_are_refused(command, case, tmp_path, no_work, capsys, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    (work / "thesis.tex").write_text("chapter 1")
    monkeypatch.chdir(work)
    assert main(_argv(command, case, ".")) == 2
    assert "working directory" in capsys.readouterr().err
    assert main(_argv(command, case, work.parent)) == 2       # a parent of the working directory
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    assert main(_argv(command, case, "~")) == 2
    assert "home" in capsys.readouterr().err
    assert (work / "thesis.tex").read_text() == "chapter 1"


@pytest.mark.parametrize("command", COMMANDS)
def test_foreign_folder_is_refused(command, case, tmp_path, no_work, capsys):
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "a.jpg").write_bytes(b"jpeg")
    assert main(_argv(command, case, photos)) == 2
    err = capsys.readouterr().err
    assert str(photos) in err and MARKER in err
    assert [p.name for p in photos.iterdir()] == ["a.jpg"]
    # another command's output is not replaced either
    other = tmp_path / "other"
    other.mkdir()
    (other / MARKER).write_text(json.dumps({"command": "synth-not-" + command}))
    (other / "x").write_text("1")
    assert main(_argv(command, case, other)) == 2
    assert "not of `faceplan " + command in capsys.readouterr().err


def test_unwritable_location_is_refused_before_work(case, tmp_path, no_work, capsys, monkeypatch):
    def refuse(folder):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(atomic, "_probe_writable", refuse)
    out = tmp_path / "ro" / "out"
    assert main(_argv("predict", case, out)) == 2
    err = capsys.readouterr().err
    assert "not writable" in err and str(out) in err and not out.exists()


def test_read_only_file_system_is_refused(case, tmp_path, no_work, capsys, monkeypatch):
    """A read-only file system (EROFS on creating the probe file; as root, permission bits do
    not stop writes, so the file system's answer is patched in)."""
    import errno
    import tempfile

    real = tempfile.mkstemp

    def read_only(*a, dir=None, **k):
        if dir is not None and Path(dir).is_relative_to(tmp_path / "ro"):
            raise OSError(errno.EROFS, "Read-only file system", str(dir))
        return real(*a, dir=dir, **k)

    (tmp_path / "ro").mkdir()
    monkeypatch.setattr(atomic.tempfile, "mkstemp", read_only)
    assert main(_argv("register", case, tmp_path / "ro" / "out")) == 2
    err = capsys.readouterr().err
    assert "not writable" in err and "Read-only file system" in err
    assert list((tmp_path / "ro").iterdir()) == []


def test_too_little_free_space_is_refused(case, tmp_path, no_work, capsys, monkeypatch):
    real = shutil.disk_usage

    def tiny(path):
        u = real(path)
        return type(u)(u.total, u.total - 10 * 2**20, 10 * 2**20)     # 10 MB free

    monkeypatch.setattr(atomic.shutil, "disk_usage", tiny)
    assert main(_argv("compare", case, tmp_path / "out")) == 2
    err = capsys.readouterr().err
    assert "10 MB free" in err and "nothing was written" in err


def test_new_empty_and_own_previous_output_are_accepted(tmp_path):
    assert prepare_output(tmp_path / "new" / "out", "predict") == tmp_path / "new" / "out"
    assert not (tmp_path / "new").exists()          # the check creates nothing
    empty = tmp_path / "empty"
    empty.mkdir()
    prepare_output(empty, "predict")
    with atomic_output_dir(empty, "predict") as tmp:
        (tmp / "report.json").write_text("{}")
    assert json.loads((empty / MARKER).read_text())["command"] == "predict"
    with atomic_output_dir(prepare_output(empty, "predict"), "predict") as tmp:   # re-run: replaced
        (tmp / "report.json").write_text('{"run": 2}')
    assert json.loads((empty / "report.json").read_text()) == {"run": 2}
    with pytest.raises(InputError, match="faceplan predict"):
        prepare_output(empty, "register")
    # an output written before markers existed (its usual files) is replaced like a marked one
    legacy = tmp_path / "legacy"
    legacy.mkdir()
    (legacy / "prediction.vtu").write_text("x")
    (legacy / "report.json").write_text("{}")
    prepare_output(legacy, "predict")


def test_marker_is_written_last_and_only_on_success(tmp_path):
    order = []
    real = atomic._write_marker

    def spy(folder, kind):
        order.append(sorted(p.name for p in folder.iterdir()))
        real(folder, kind)

    atomic._write_marker, saved = spy, atomic._write_marker
    try:
        with atomic_output_dir(tmp_path / "o", "register") as tmp:
            (tmp / "a.txt").write_text("a")
        with pytest.raises(RuntimeError):
            with atomic_output_dir(tmp_path / "p", "register") as tmp:
                (tmp / "a.txt").write_text("a")
                raise RuntimeError
    finally:
        atomic._write_marker = saved
    assert order == [["a.txt"]]
    assert not (tmp_path / "p").exists()


def test_content_appearing_during_the_run_is_not_replaced(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(InputError):
        with atomic_output_dir(out, "predict") as tmp:
            (tmp / "report.json").write_text("{}")
            out.mkdir()
            (out / "precious.txt").write_text("typed meanwhile")
    assert (out / "precious.txt").read_text() == "typed meanwhile"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_check_without_kind_still_refuses_files_and_inputs(tmp_path, monkeypatch):
    f = tmp_path / "f.txt"
    f.write_text("x")
    with pytest.raises(InputError, match="existing file"):
        check_output(f, None)
    with pytest.raises(InputError, match="input"):
        check_output(tmp_path, None, inputs=[tmp_path / "case"])
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match="working directory"):
        with atomic_output_dir("."):
            pass
    assert f.read_text() == "x"


# ------------------------------------------------------------ free space: an estimate of the outputs
def test_prediction_size_estimate_bounds_the_real_outputs(tmp_path):
    """The estimate (`planner.output_size`) is an upper bound of what `write_outputs` writes
    for the coarse mesh and the demo head's skin, and not a wild one: within 4x of it (the
    bounds per item are 1.2-2x the writers' sizes, times the 1.5 margin)."""
    import numpy as np
    import trimesh

    import generic_mesh
    from planner.output_size import prediction_output_bytes
    from planner.pipeline import DEMO_HEAD, Prediction, Progress, write_outputs
    from planner.plan import load_plan

    model = generic_mesh.load("coarse")
    d = np.load(DEMO_HEAD)
    skin = trimesh.Trimesh(d["skin_vertices"].astype(float), d["skin_faces"], process=False)
    (tmp_path / "plan.yaml").write_text("faceplan: 1\nsegments:\n  maxilla: {translation: [0, 3, 0]}\n")
    n, m = len(model.nodes), len(model.hexes)
    rng = np.random.default_rng(0)   # non-zero fields: compressed output would be optimistic
    pred = Prediction(model, load_plan(tmp_path / "plan.yaml"), rng.normal(0.0, 0.01, (n, 3)),
                      rng.normal(0.0, 1.0, (m, 3, 3)), {"converged": True, "load": 1.0})
    out = write_outputs(pred, tmp_path / "out", Progress(echo=False), {"case": None}, render=False,
                        patient_skin=skin)
    written = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    estimate = prediction_output_bytes(n, m, len(skin.vertices), render=False)
    assert written < estimate < 4 * written, (written, estimate)


def test_predict_refuses_a_disk_smaller_than_its_outputs(tmp_path, capsys, monkeypatch):
    """40 MB free passes the floor checked before reading, but not the estimate of a coarse
    prediction with its pictures (~50 MB); the refusal comes before the registration."""
    import planner.pipeline
    from planner.pipeline import write_demo_case

    case = write_demo_case(tmp_path / "case")
    real = shutil.disk_usage

    def small(path):
        u = real(path)
        return type(u)(u.total, u.total - 40 * 2**20, 40 * 2**20)

    def boom(*a, **k):
        raise AssertionError("registration started although the outputs cannot be written")

    monkeypatch.setattr(atomic.shutil, "disk_usage", small)
    monkeypatch.setattr(planner.pipeline, "register_case", boom)
    assert main(["predict", str(case), "--resolution", "coarse", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "40 MB free" in err and "estimated size" in err and "nothing was written" in err
    assert not (case / "predict").exists()
