"""Off-screen renders and charts produce real (non-blank) pictures, views look where they should."""
import numpy as np
import pytest

from planner import render


def _png(path):
    import matplotlib.image as mpimg

    img = mpimg.imread(str(path))
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    return img[..., :3]


def _non_background_fraction(img):
    # the background is white; anything darker than 0.9 in any channel is drawn content
    return float(np.mean(np.any(img < 0.9, axis=-1)))


@pytest.fixture(scope="module")
def face():
    import trimesh

    # a half ellipsoid facing +y (anterior) with a nose bump: a stand-in face
    m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    v = m.vertices * np.array([70.0, 50.0, 100.0])
    keep = v[:, 1] > 0
    faces = m.faces[np.all(keep[m.faces], axis=1)]
    v = v + np.where((np.abs(v[:, 0]) < 15) & (np.abs(v[:, 2]) < 20), 1.0, 0.0)[:, None] * [0, 10, 0]
    return trimesh.Trimesh(v, faces, process=True)


def test_render_views_writes_three_nonblank_pngs(tmp_path, face):
    d = face.vertices[:, 2] / 30.0
    out = render.render_views(face, tmp_path / "img" / "dist", scalars=d, clim=(-3, 3), title="test")
    assert set(out) == {"frontal", "profile", "three_quarter"}
    fractions = {}
    for view, p in out.items():
        img = _png(p)
        fractions[view] = _non_background_fraction(img)
        # the face fills a good part of the picture and is not one flat colour
        assert fractions[view] > 0.1, view
        assert img.std() > 0.05, view
    # a colour map: both reddish and bluish pixels exist (diverging map over +-3 mm)
    img = _png(out["frontal"])
    reds = np.mean(img[..., 0] > img[..., 2] + 0.15)
    blues = np.mean(img[..., 2] > img[..., 0] + 0.15)
    assert reds > 0.005 and blues > 0.005


def test_camera_directions_in_ras(face):
    # frontal camera on +y (in front of the face), profile on +x (patient's right), z up
    pos, focal, up = render._camera(render.to_polydata(face), "frontal")
    assert np.argmax(np.abs(np.subtract(pos, focal))) == 1 and pos[1] > focal[1]
    pos, focal, up = render._camera(render.to_polydata(face), "profile")
    assert np.argmax(np.abs(np.subtract(pos, focal))) == 0 and pos[0] > focal[0]
    assert tuple(up) == (0.0, 0.0, 1.0)


def test_frontal_is_wider_than_profile_for_wide_face(tmp_path, face):
    # the stand-in face is 140 mm wide (x) and 50 mm deep (y): seen from the front the drawn
    # area is wider than seen from the side -- checks that the views really differ.
    out = render.render_views(face, tmp_path / "plain", views=("frontal", "profile"))
    widths = {}
    for view, p in out.items():
        img = _png(p)
        cols = np.where(np.any(np.any(img < 0.9, axis=-1)[50:-50], axis=0))[0]
        widths[view] = cols.max() - cols.min()
    assert widths["frontal"] > 1.5 * widths["profile"]


def test_overlay_and_charts(tmp_path, face):
    moved = face.copy()
    moved.vertices = moved.vertices + [0, 3, 0]
    out = render.render_overlay([face, moved], tmp_path / "overlay", labels=["pre", "post"])
    for p in out.values():
        assert _non_background_fraction(_png(p)) > 0.05
    pr = render.profile_chart([face, moved], tmp_path / "p.png", labels=["pre", "post"])
    assert 0.01 < _non_background_fraction(_png(pr)) < 0.9
    h = render.histogram_chart(np.random.default_rng(0).normal(size=500), tmp_path / "h.png")
    b = render.bar_chart(["a", "b"], [1.0, 2.5], tmp_path / "b.png", errors=[0.1, 0.2])
    for p in (h, b):
        img = _png(p)
        assert 0.01 < _non_background_fraction(img) < 0.9
