"""The CT surface cache is never silently wrong: a damaged entry is detected and rebuilt.

CT segmentation is replaced by a counting stand-in (the cache is under test): a damaged
`KEY.npz` (truncated, bit-flipped, empty, wrong arrays, no digest) gives a CacheWarning, is
deleted and extracted again; the rebuilt entry is reused.
"""
import warnings

import numpy as np
import pytest
import trimesh

import planner.case as case_mod
from registration.face import file_sha256


@pytest.fixture
def extract(monkeypatch):
    import facemodel.ct as ct

    calls = []

    class Surfaces:
        skin = trimesh.creation.icosphere(subdivisions=2, radius=90.0)
        bone = trimesh.creation.icosphere(subdivisions=1, radius=70.0)

    def fake(path, **options):
        calls.append(options)
        return Surfaces()

    monkeypatch.setattr(ct, "ct_surfaces", fake)
    return calls


def _run(tmp_path):
    ct = tmp_path / "ct.nii.gz"
    if not ct.exists():
        ct.write_bytes(b"not read: segmentation is stubbed")
    return case_mod._surfaces_from_ct(ct, {}, tmp_path / "cache")


def _truncate(p):
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 3])


def _bitflip(p):
    b = bytearray(p.read_bytes())
    b[len(b) // 2] ^= 0x01
    p.write_bytes(bytes(b))


def _empty(p):
    p.write_bytes(b"")


def _wrong_arrays_with_digest(p):
    np.savez_compressed(p, skin_vertices=np.zeros((4, 2)), skin_faces=np.zeros((1, 3), int),
                        bone_vertices=np.zeros((3, 3)), bone_faces=np.array([[0, 1, 7]]))
    p.with_suffix(".sha256").write_text(file_sha256(p))   # a consistent digest: the shape check catches it


def _no_digest(p):
    p.with_suffix(".sha256").unlink()


@pytest.mark.parametrize("damage", [_truncate, _bitflip, _empty, _wrong_arrays_with_digest, _no_digest])
def test_damaged_ct_entry_is_rebuilt(damage, extract, tmp_path):
    first = _run(tmp_path)
    assert len(extract) == 1
    _run(tmp_path)
    assert len(extract) == 1
    (entry,) = (tmp_path / "cache").glob("*.npz")
    damage(entry)
    with pytest.warns(case_mod.CacheWarning, match="damaged"):
        again = _run(tmp_path)
    assert len(extract) == 2
    np.testing.assert_allclose(again["skin"].vertices, first["skin"].vertices)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _run(tmp_path)
    assert len(extract) == 2
    assert sorted(p.suffix for p in (tmp_path / "cache").iterdir()) == [".npz", ".sha256"]
