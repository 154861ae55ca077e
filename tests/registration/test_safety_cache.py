"""The registration cache is never silently wrong: a damaged entry is detected and rebuilt.

The registration itself is replaced by a counting stand-in (the cache, not the registration,
is under test): a second call must reuse the entry, a damaged entry (truncated, bit-flipped or
empty npz, a report.json of the wrong shape, nodes shifted 20 mm, no digest) must be deleted
with a CacheWarning and computed again, and the rebuilt entry must be reused afterwards.
"""
import json
import os
import warnings

import numpy as np
import pytest
import trimesh

import registration.face as face


@pytest.fixture
def counted(monkeypatch, generic):
    calls = []

    def fake(arrays, skin, bones, landmarks, options, files, teeth=None):
        calls.append(1)
        report = {"time": {}, "repair": {"elements_needing_repair": 0},
                  "teeth": {k: {"segment": seg} for k, (_, _, seg) in generic.teeth.items()}}
        return np.asarray(arrays.nodes, float) + 0.5, None, report, dict(generic.teeth)

    monkeypatch.setattr(face, "match_and_repair_arrays", fake)
    return calls


def _run(generic, cache_dir):
    skin = trimesh.creation.icosphere(subdivisions=2, radius=80.0)
    return face.mesh_match_and_repair(generic, skin, {}, cache_dir=cache_dir)


def _entry(cache_dir):
    (entry,) = [p for p in cache_dir.iterdir() if p.is_dir()]
    return entry


def _truncate(entry):
    f = entry / "result.npz"
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])


def _bitflip(entry):
    f = entry / "result.npz"
    b = bytearray(f.read_bytes())
    b[len(b) // 2] ^= 0x10
    f.write_bytes(bytes(b))


def _empty(entry):
    (entry / "result.npz").write_bytes(b"")


def _wrong_report(entry):
    (entry / "report.json").write_text(json.dumps([1, 2, 3]))


def _shifted_nodes(entry):
    with np.load(entry / "result.npz") as z:
        data = {k: z[k] for k in z.files}
    data["nodes"] = data["nodes"] + np.array([0.0, 20.0, 0.0])
    np.savez_compressed(entry / "result.npz", **data)


def _no_digest(entry):
    (entry / "digest.json").unlink()


@pytest.mark.parametrize("damage", [_truncate, _bitflip, _empty, _wrong_report, _shifted_nodes, _no_digest])
def test_damaged_entry_is_rebuilt_with_a_warning(damage, generic, counted, tmp_path):
    cache = tmp_path / "cache"
    first, rep = _run(generic, cache)
    assert not rep["cached"] and len(counted) == 1
    again, rep = _run(generic, cache)
    assert rep["cached"] and len(counted) == 1
    np.testing.assert_array_equal(again.nodes, first.nodes)
    damage(_entry(cache))
    with pytest.warns(face.CacheWarning, match="damaged"):
        rebuilt, rep = _run(generic, cache)
    assert not rep["cached"] and len(counted) == 2
    np.testing.assert_array_equal(rebuilt.nodes, first.nodes)    # never the damaged nodes
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, rep = _run(generic, cache)
    assert rep["cached"] and len(counted) == 2


def test_failed_write_leaves_nothing_and_orphans_are_cleaned(generic, counted, tmp_path, monkeypatch):
    import subprocess
    import sys

    cache = tmp_path / "cache"
    cache.mkdir()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()
    orphan = cache / f"0123abcd.tmp-{dead}"
    orphan.mkdir()
    (orphan / "result.npz").write_bytes(b"half")

    def full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(face.np, "savez_compressed", full)
    _, rep = _run(generic, cache)                       # the result is still returned
    assert not rep["cached"]
    assert list(cache.iterdir()) == []                  # neither the orphan nor a half entry
