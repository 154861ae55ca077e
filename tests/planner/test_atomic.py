"""atomic_output_dir: a folder appears whole on success, and nothing changes on failure."""
import pytest

from planner.atomic import atomic_output_dir, atomic_write_file


def test_success_moves_folder_into_place(tmp_path):
    final = tmp_path / "a" / "b" / "out"
    with atomic_output_dir(final) as tmp:
        assert tmp != final and tmp.parent == final.parent
        (tmp / "report.json").write_text("{}")
        (tmp / "images").mkdir()
        (tmp / "images" / "x.png").write_bytes(b"png")
        assert not final.exists()
    assert (final / "report.json").read_text() == "{}"
    assert (final / "images" / "x.png").exists()
    assert sorted(p.name for p in final.parent.iterdir()) == ["out"]


def test_replaces_old_folder(tmp_path):
    final = tmp_path / "out"
    final.mkdir()
    (final / "stale.txt").write_text("old")
    with atomic_output_dir(final) as tmp:
        (tmp / "new.txt").write_text("new")
    assert [p.name for p in final.iterdir()] == ["new.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_error_leaves_nothing_and_keeps_old(tmp_path):
    final = tmp_path / "out"
    final.mkdir()
    (final / "keep.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_output_dir(final) as tmp:
            (tmp / "half.txt").write_text("half")
            raise RuntimeError("boom")
    assert [p.name for p in final.iterdir()] == ["keep.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_error_removes_created_parents(tmp_path):
    final = tmp_path / "new" / "deeper" / "out"
    with pytest.raises(ValueError):
        with atomic_output_dir(final):
            raise ValueError("bad input")
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_file(tmp_path):
    f = tmp_path / "x.json"
    with atomic_write_file(f) as fh:
        fh.write("1")
    assert f.read_text() == "1"
    with pytest.raises(KeyError):
        with atomic_write_file(f) as fh:
            fh.write("2")
            raise KeyError
    assert f.read_text() == "1"
    assert [p.name for p in tmp_path.iterdir()] == ["x.json"]
