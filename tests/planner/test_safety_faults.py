"""Faults lose nothing: SIGKILL, Ctrl-C, a full disk.

A process killed (SIGKILL) while it fills an output folder leaves no visible partial output, and
the next run on the same folder removes its hidden temporary; Ctrl-C at any moment (start-up
included) exits 130 without a traceback or output; a disk that fills up while writing gives a
one-line message, exit 4, and nothing half-written.
"""
import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
import types
from pathlib import Path

import pytest

from planner import cli
from planner.atomic import MARKER, atomic_output_dir, clean_orphans

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}

WRITER = textwrap.dedent("""
    import sys, time
    from planner.atomic import atomic_output_dir
    with atomic_output_dir(sys.argv[1], "predict") as tmp:
        print("writing", flush=True)
        for i in range(400):
            (tmp / f"part{i}.txt").write_text("x" * 1000)
            time.sleep(0.005)
""")


def _dead_pid() -> int:
    return int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                              capture_output=True, text=True).stdout)


@pytest.mark.parametrize("delay", [0.05, 0.6])
def test_sigkill_leaves_no_partial_output(tmp_path, delay):
    out = tmp_path / "out"
    with atomic_output_dir(out, "predict") as tmp:          # a previous, complete output
        (tmp / "report.json").write_text('{"previous": true}')
    p = subprocess.Popen([sys.executable, "-c", WRITER, str(out)], env=ENV, stdout=subprocess.PIPE)
    assert p.stdout.readline().strip() == b"writing"
    time.sleep(delay)
    p.send_signal(signal.SIGKILL)
    p.wait()
    visible = sorted(q.name for q in tmp_path.iterdir() if not q.name.startswith("."))
    assert visible == ["out"]
    assert json.loads((out / "report.json").read_text()) == {"previous": True}   # untouched
    assert any(q.name.startswith(".out.tmp-") for q in tmp_path.iterdir())        # the orphan
    with atomic_output_dir(out, "predict") as tmp:            # the next run cleans it
        (tmp / "report.json").write_text('{"next": true}')
    assert sorted(q.name for q in tmp_path.iterdir()) == ["out"]
    assert sorted(q.name for q in out.iterdir()) == [MARKER, "report.json"]


def test_kill_between_the_two_renames_keeps_the_previous_output(tmp_path):
    out = tmp_path / "out"
    with atomic_output_dir(out, "predict") as tmp:
        (tmp / "report.json").write_text('{"previous": true}')
    pid = _dead_pid()
    os.replace(out, tmp_path / f".out.old-{pid}-abc")       # moved aside, then killed
    (tmp_path / f".out.tmp-{pid}-def").mkdir()              # the new one never moved in
    clean_orphans(out)
    assert sorted(q.name for q in tmp_path.iterdir()) == ["out"]
    assert json.loads((out / "report.json").read_text()) == {"previous": True}


def test_a_live_writer_s_temporary_is_not_touched(tmp_path):
    live = tmp_path / f".out.tmp-{os.getppid()}-abc"
    live.mkdir()
    clean_orphans(tmp_path / "out")
    assert live.is_dir()


# the command starts right after the interpreter has imported planner.cli ("ready"); an
# interrupt before that hits Python's own start-up, which no program can catch
# A job started in the background of a shell inherits SIGINT ignored, and Python then keeps
# ignoring it; a user's Ctrl-C comes from a terminal where it is not: restore Python's handler.
STARTER = ("import signal; signal.signal(signal.SIGINT, signal.default_int_handler); "
           "import sys, planner.cli; sys.stderr.write('ready\\n'); sys.stderr.flush(); "
           "sys.exit(planner.cli.main(sys.argv[1:]))")


@pytest.mark.parametrize("delay", [0.05, 1.5, 4.0])
def test_ctrl_c_at_any_moment_exits_130(tmp_path, delay):
    out = tmp_path / "demo"
    p = subprocess.Popen([sys.executable, "-c", STARTER, "demo", "--out", str(out), "--no-images", "--quiet"],
                         env={**ENV, "FACEPLAN_CACHE": str(tmp_path / "c")}, cwd=tmp_path,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert p.stderr.readline().strip() == "ready"
    time.sleep(delay)          # 0.05 s: still importing the commands (numpy, scipy, trimesh...)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    assert "Traceback" not in err and "interrupted" in err
    assert sorted(q.name for q in tmp_path.iterdir() if q.name != "c") == []


def test_an_interrupt_landing_in_a_finalizer_is_not_reported_as_a_traceback(tmp_path):
    # Ctrl-C can arrive while Python runs a finalizer (llvmlite's __del__ during numba's
    # compilation, say): Python cannot propagate it and prints "Exception ignored ...
    # Traceback". The repeat delivers the interrupt again, so the command reports it once, as
    # an interrupt; an unrelated exception in a finalizer is still reported
    code = textwrap.dedent("""
        import gc, signal
        from planner import cli
        it = cli._Interrupts()
        it.install()
        class Finalised:
            def __init__(self, exc): self.exc = exc
            def __del__(self): raise self.exc
        it.pending = signal.SIGINT
        Finalised(KeyboardInterrupt()); gc.collect()
        Finalised(ValueError("a real fault")); gc.collect()
        it.restore()
        Finalised(KeyboardInterrupt("after restore")); gc.collect()
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                       env={**os.environ, "PYTHONPATH": str(Path(cli.__file__).resolve().parents[1])})
    assert r.returncode == 0, r.stderr
    assert r.stderr.count("Exception ignored") == 2
    assert "a real fault" in r.stderr and "after restore" in r.stderr


def test_full_disk_exit_4_and_nothing_half_written(tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"

    def run(args):
        with atomic_output_dir(out, "fake") as tmp:
            (tmp / "prediction.vtu").write_text("half")
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp / "images" / "a.png"))

    fake = types.SimpleNamespace(add_arguments=lambda p: None, run=run)
    monkeypatch.setitem(cli.COMMANDS, "fake", ("fake", "a command that fills the disk"))
    monkeypatch.setattr(cli, "_load", lambda name: fake)
    assert cli.main(["fake"]) == 4
    err = capsys.readouterr().err
    assert "No space left on device" in err and "nothing was written" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_a_bug_s_oserror_is_not_dressed_as_environment(monkeypatch):
    def run(args):
        raise FileNotFoundError(errno.ENOENT, "No such file", "/nonexistent")

    fake = types.SimpleNamespace(add_arguments=lambda p: None, run=run)
    monkeypatch.setitem(cli.COMMANDS, "fake", ("fake", "x"))
    monkeypatch.setattr(cli, "_load", lambda name: fake)
    with pytest.raises(FileNotFoundError):
        cli.main(["fake"])


def _in_private_mount(tmp_path, options, argv):
    """Run the CLI with a fresh tmpfs (mount `options`) at tmp_path/mnt, in a private user and
    mount namespace (`unshare -rm`: no privilege needed where user namespaces are enabled)."""
    import shutil as sh

    if sh.which("unshare") is None:
        pytest.skip("unshare not available")
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    probe = subprocess.run(["unshare", "-rm", "mount", "-t", "tmpfs", "-o", options, "tmpfs", str(mnt)],
                           capture_output=True)
    if probe.returncode != 0:
        pytest.skip("no user/mount namespaces here")
    script = (f"mount -t tmpfs -o {options} tmpfs {mnt} && "
              f"exec {sys.executable} -m planner.cli " + " ".join(argv))
    return subprocess.run(["unshare", "-rm", "sh", "-c", script], env=ENV, capture_output=True,
                          text=True, timeout=120), mnt


@pytest.mark.parametrize("options,words", [("size=1m", "MB free"), ("ro,size=1m", "not writable")])
def test_real_full_or_read_only_disk_refused_before_work(tmp_path, options, words):
    case = tmp_path / "case"
    (case / "preop").mkdir(parents=True)
    p, mnt = _in_private_mount(tmp_path, options, ["predict", str(case), "--out", str(tmp_path / "mnt" / "out"),
                                                   "--quiet"])
    assert p.returncode == 2, p.stderr
    assert words in p.stderr and "Traceback" not in p.stderr and str(mnt / "out") in p.stderr


def test_disk_full_while_compare_writes(tmp_path, monkeypatch, capsys):
    """A real command (compare on the analytic face phantom) whose second file write fails with
    ENOSPC: exit 4, a one-line message, no output folder and no temporary left."""
    import pyvista as pv
    import trimesh

    from planner.compare.phantom import face_phantom, write_prediction_folder

    pred, scan = face_phantom(3.0), face_phantom(2.5, jitter=0.5, seed=1, offset=0.3)
    case = tmp_path / "case"
    write_prediction_folder(case / "predict", pred.vertices, pred.faces, pred.region, pred.region_names,
                            pred.landmarks, pred.unoperated_regions)
    (case / "postop").mkdir()
    trimesh.Trimesh(scan.vertices, scan.faces, process=False).export(case / "postop" / "skin.stl")
    real, calls = pv.PolyData.save, []

    def full(self, filename, *a, **k):
        calls.append(filename)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(filename))
        return real(self, filename, *a, **k)

    monkeypatch.setattr(pv.PolyData, "save", full)
    assert cli.main(["compare", str(case), "--no-images"]) == 4
    err = capsys.readouterr().err
    assert "No space left on device" in err and "Traceback" not in err and len(calls) == 2
    assert sorted(p.name for p in case.iterdir()) == ["postop", "predict"]
