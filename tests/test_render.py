"""Ray-cast renderer: hits, barycentrics, shading, colormaps, colour bar and PNG output."""

import numpy as np
import pytest
import trimesh
from PIL import Image

from jaxdeform.errors import MeshFormatError
from jaxdeform.mesh.render import (
    Camera,
    auto_camera,
    cast_rays,
    colormap,
    guess_up_axis,
    render,
    render_png,
    save_png,
)

BG = np.array([255, 255, 255], dtype=np.uint8)


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(subdivisions=3)
    return np.asarray(m.vertices), np.asarray(m.faces)


@pytest.fixture(scope="module")
def cube():
    m = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    return np.asarray(m.vertices), np.asarray(m.faces)


def plane(n=11):
    """A unit square in z = 0 facing +z, triangulated on an n x n grid."""
    x, y = np.meshgrid(np.linspace(-0.5, 0.5, n), np.linspace(-0.5, 0.5, n), indexing="ij")
    v = np.c_[x.ravel(), y.ravel(), np.zeros(n * n)]
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return v, np.r_[np.c_[a, b, c], np.c_[a, c, d]]


FRONT = Camera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=30.0)


@pytest.mark.parametrize("mesh", ["sphere", "cube"])
def test_auto_camera_frames_mesh(mesh, request):
    v, f = request.getfixturevalue(mesh)
    cam = auto_camera(v)
    hits = cast_rays(v, f, cam, 160, 120)
    assert hits.triangle.shape == (120, 160) and hits.triangle.dtype == np.int64
    assert hits.triangle[60, 80] >= 0
    for r, c in [(0, 0), (0, -1), (-1, 0), (-1, -1)]:
        assert hits.triangle[r, c] == -1
    # the whole bounding sphere is in view: no hit on the image border
    border = np.r_[hits.triangle[0], hits.triangle[-1], hits.triangle[:, 0], hits.triangle[:, -1]]
    assert np.all(border == -1)


@pytest.mark.parametrize("view", [(30.0, 20.0), (90.0, 10.0), (-140.0, 60.0)])
def test_box_fit_camera_fills_a_square_view(view):
    # a long thin box: every vertex projects inside the view, and the widest one lands on the margin's border
    m = trimesh.creation.box(extents=(0.3, 1.0, 4.0))
    v = np.asarray(m.vertices) + np.array([5.0, -2.0, 1.0])
    az, el = view
    margin = 1.1
    cam = auto_camera(v, azimuth_deg=az, elevation_deg=el, up_axis="y", fit="box", margin=margin)
    fwd, right, up = cam.basis()
    rel = v - np.asarray(cam.eye)
    depth = rel @ fwd
    assert np.all(depth > 0)
    x, y = (rel @ right) / depth, (rel @ up) / depth
    edge = np.tan(np.radians(cam.fov_deg) / 2)
    reach = np.maximum(np.abs(x), np.abs(y)).max()
    np.testing.assert_allclose(reach, edge / margin, rtol=1e-9)
    # the view is centred on the projected extent along the panel's wider side
    wide = x if np.ptp(x) >= np.ptp(y) else y
    np.testing.assert_allclose(wide.max(), -wide.min(), rtol=0.02)
    # the same direction as the sphere fit, from closer
    sphere = auto_camera(v, azimuth_deg=az, elevation_deg=el, up_axis="y", margin=margin)
    np.testing.assert_allclose(sphere.basis()[0], fwd, atol=1e-12)
    assert np.linalg.norm(np.subtract(cam.eye, cam.target)) < np.linalg.norm(np.subtract(sphere.eye, sphere.target))
    with pytest.raises(ValueError, match="fit must be"):
        auto_camera(v, fit="tight")


def _table(up: int):
    """Four legs under a top, standing along axis ``up`` (1: y, 2: z), longer (4) than tall (2) and wide (1)."""
    parts = [
        trimesh.creation.box(extents=(1.0, 0.2, 4.0), transform=trimesh.transformations.translation_matrix((0, 1.9, 0)))
    ]
    for sx in (-0.4, 0.4):
        for sz in (-1.8, 1.8):
            t = trimesh.transformations.translation_matrix((sx, 0.9, sz))
            parts.append(trimesh.creation.box(extents=(0.1, 1.8, 0.1), transform=t))
    m = trimesh.util.concatenate(parts)
    v = np.asarray(m.vertices)
    if up == 2:  # y up -> z up: (x, y, z) -> (x, -z, y)
        v = np.c_[v[:, 0], -v[:, 2], v[:, 1]]
    return v, np.asarray(m.faces)


@pytest.mark.parametrize("up", [1, 2])
def test_guess_up_axis_finds_the_legs(up):
    v, f = _table(up)
    assert guess_up_axis(v, f) == "yz"[up - 1]
    with pytest.raises(ValueError, match="slab"):
        guess_up_axis(v, f, slab=0.0)


def test_guess_up_axis_on_shared_data():
    from conftest import data_dir

    from jaxdeform.components import run

    for name, up in (("horse-gallop", "y"), ("samba", "y"), ("cactus", "z")):
        v, f = run.load_data(data_dir(name))
        assert guess_up_axis(v[0], f) == up, name


def test_barycentrics_and_points(sphere):
    v, f = sphere
    cam = auto_camera(v, azimuth_deg=-50, elevation_deg=35)
    hits = cast_rays(v, f, cam, 120, 90)
    hit = hits.hit
    assert hit.sum() > 1000
    b = hits.barycentric[hit]
    np.testing.assert_allclose(b.sum(axis=-1), 1.0, atol=1e-12)
    assert b.min() >= 0.0
    rebuilt = np.einsum("nk,nkc->nc", b, v[f[hits.triangle[hit]]])
    np.testing.assert_allclose(hits.points[hit], rebuilt, atol=1e-4)
    along_ray = np.asarray(cam.eye) + hits.depth[hit][:, None] * hits.directions[hit]
    np.testing.assert_allclose(hits.points[hit], along_ray, atol=1e-4)
    assert np.all(np.isinf(hits.depth[~hit])) and np.all(np.isnan(hits.points[~hit]))
    # front-most surface: every hit is on the hemisphere facing the camera
    to_eye = np.asarray(cam.eye) - hits.points[hit]
    assert np.all(np.einsum("nc,nc->n", hits.points[hit], to_eye) > -1e-3)


def test_ray_through_triangle_centre_hits_it():
    v = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0], [5.0, 5.0, 0.0]])
    f = np.array([[0, 1, 2], [1, 3, 2]])
    centre = v[f[0]].mean(axis=0)
    cam = Camera(eye=centre + [0.0, 0.0, 4.0], target=centre, up=(0.0, 1.0, 0.0))
    hits = cast_rays(v, f, cam, 5, 5)  # odd size: the middle pixel's ray goes through the centroid
    assert hits.triangle[2, 2] == 0
    np.testing.assert_allclose(hits.barycentric[2, 2], [1 / 3, 1 / 3, 1 / 3], atol=1e-5)
    np.testing.assert_allclose(hits.points[2, 2], centre, atol=1e-5)
    assert hits.depth[2, 2] == pytest.approx(4.0, abs=1e-5)
    # seen from behind (two-sided): still hit
    back = Camera(eye=centre - [0.0, 0.0, 4.0], target=centre, up=(0.0, 1.0, 0.0))
    assert cast_rays(v, f, back, 5, 5).triangle[2, 2] == 0


def test_render_plain(sphere):
    v, f = sphere
    img = render(v, f, width=200, height=150)
    assert img.shape == (150, 200, 3) and img.dtype == np.uint8
    assert np.array_equal(img[0, 0], BG) and np.array_equal(img[-1, -1], BG)
    centre = img[75, 100].astype(float)
    assert not np.array_equal(img[75, 100], BG)
    # headlight: the centre faces the camera and is brighter than a point near the silhouette
    hits = cast_rays(v, f, auto_camera(v), 200, 150)
    row = np.flatnonzero(hits.hit[75])
    assert centre.sum() > img[75, row[1]].astype(float).sum()
    # no colour bar without a scalar: the right strip is background
    assert np.all(img[:, -10:] == BG)


def test_colormap_endpoints_and_range():
    c = colormap(np.linspace(0, 1, 50), "viridis")
    assert c.shape == (50, 3) and c.min() >= 0.0 and c.max() <= 1.0
    np.testing.assert_allclose(colormap(0.0) * 255, [68, 1, 84])
    np.testing.assert_allclose(colormap(1.0) * 255, [253, 231, 37])
    cw = colormap(np.array([0.0, 0.5, 1.0]), "coolwarm")
    assert cw[0, 2] > cw[0, 0] and cw[2, 0] > cw[2, 2] and cw[1].min() > 0.8
    np.testing.assert_allclose(colormap(0.2, "viridis_r"), colormap(0.8, "viridis"))
    with pytest.raises(ValueError):
        colormap(0.5, "jet")


@pytest.mark.parametrize("cmap", ["viridis", "coolwarm"])
def test_scalar_colours_follow_colormap(cmap):
    v, f = plane()
    lut = colormap(np.linspace(0, 1, 1001), cmap) * 255
    img = render(v, f, scalar=v[:, 0], camera=FRONT, width=120, height=90, cmap=cmap, colorbar=False, shading=False)
    hits = cast_rays(v, f, FRONT, 120, 90)
    cols = np.flatnonzero(hits.hit[45])
    assert cols.size > 20
    px = img[45, cols].astype(float)
    nearest = np.argmin(((px[:, None, :] - lut[None]) ** 2).sum(-1), axis=1)
    assert np.all(np.diff(nearest) >= 0) and nearest[-1] - nearest[0] > 800
    # shaded: the plane faces the headlight, so colours are the colormap's times a near-constant factor
    shaded = render(v, f, scalar=v[:, 0], camera=FRONT, width=120, height=90, cmap=cmap, colorbar=False)
    ratio = shaded[45, cols].astype(float).sum(-1) / np.maximum(px.sum(-1), 1)
    assert np.all(ratio > 0.95) and np.all(ratio <= 1.01)


def test_colorbar_does_not_cover_mesh(sphere):
    v, f = sphere
    plain = render(v, f, width=300, height=200, scalar=v[:, 2], colorbar=False)
    with_bar = render(v, f, width=300, height=200, scalar=v[:, 2], label="height")
    assert with_bar.shape == plain.shape
    assert np.all(plain[:, -25:] == BG)
    used = np.any(np.any(with_bar != BG, axis=-1), axis=0)  # columns holding anything but background
    assert np.any(used[-25:])  # the colour bar and its labels
    # mesh and bar are separated by background columns: the bar never covers the mesh
    starts = np.flatnonzero(np.diff(used.astype(int)) == 1) + 1
    assert not used[0] and starts.size >= 2  # groups of columns: mesh, bar (+ tick labels)
    mesh_start, bar_start = starts[0], starts[1]
    assert bar_start > 300 * 0.6 and used[mesh_start:bar_start].sum() > 100
    # the bar shows the colormap: its rows hold both ends of viridis
    bar_col = with_bar[:, bar_start + 3].astype(float)
    lut = colormap(np.array([0.0, 1.0])) * 255
    for end in lut:
        assert np.min(np.abs(bar_col - end).sum(-1)) < 12


def test_png_round_trip(tmp_path, sphere):
    v, f = sphere
    path = tmp_path / "sub" / "sphere.png"
    img = render_png(path, v, f, scalar=v[:, 0], width=90, height=60, cmap="coolwarm")
    back = np.asarray(Image.open(path).convert("RGB"))
    np.testing.assert_array_equal(back, img)
    assert [p.name for p in path.parent.iterdir()] == ["sphere.png"]  # no temporary file left
    save_png(img[:, :, 0], tmp_path / "grey.png")
    assert Image.open(tmp_path / "grey.png").size == (90, 60)
    with pytest.raises(ValueError):
        save_png(img.astype(np.float32), tmp_path / "bad.png")


def test_bad_input(sphere):
    v, f = sphere
    bad = v.copy()
    bad[4, 0] = np.nan
    with pytest.raises(MeshFormatError, match="NaN"):
        render(bad, f, width=20, height=20)
    with pytest.raises(MeshFormatError, match="NaN"):
        cast_rays(bad, f, FRONT, 10, 10)
    s = v[:, 0].copy()
    s[7] = np.nan
    with pytest.raises(MeshFormatError, match="NaN"):
        render(v, f, scalar=s, width=20, height=20)
    with pytest.raises(MeshFormatError, match="values"):
        render(v, f, scalar=s[:-1], width=20, height=20)


def test_constant_scalar_and_vrange(sphere):
    v, f = sphere
    img = render(v, f, scalar=np.ones(len(v)), width=120, height=80)
    assert img.shape == (80, 120, 3)
    img2 = render(v, f, scalar=v[:, 0], vmin=-0.5, vmax=0.5, width=120, height=80, supersample=2)
    assert img2.shape == (80, 120, 3)


# ------------------------------------------------------------------------------ categorical vertex colours


def test_categorical_colors_distinct_and_deterministic():
    from jaxdeform.mesh.render import categorical_colors

    c = categorical_colors(12)
    assert c.shape == (12, 3) and c.min() >= 0.0 and c.max() <= 1.0
    np.testing.assert_array_equal(c, categorical_colors(12))
    np.testing.assert_array_equal(c[:5], categorical_colors(5))  # a prefix does not depend on n
    d = np.sqrt(((c[:, None] - c[None]) ** 2).sum(-1))
    assert d[~np.eye(12, dtype=bool)].min() > 0.1
    assert categorical_colors(0).shape == (0, 3)


def _best_scaled_match(px, palette):
    """Per pixel: distance (0-255 units) to the closest ``s * colour`` over colours and scales s >= 0."""
    px = px.astype(float)
    cols = palette * 255.0
    s = np.clip((px @ cols.T) / (cols * cols).sum(-1), 0.0, None)  # (n, k) least-squares scale
    res = np.linalg.norm(px[:, None, :] - s[..., None] * cols[None], axis=-1)
    return res.min(axis=1), res.argmin(axis=1)


@pytest.mark.parametrize("shading", [True, False])
def test_vertex_colors_two_labels(sphere, shading):
    from jaxdeform.mesh.render import categorical_colors

    v, f = sphere
    labels = (v[:, 0] > 0.1).astype(int)
    palette = categorical_colors(2)
    cam = auto_camera(v, azimuth_deg=0, elevation_deg=0)
    img = render(v, f, vertex_colors=palette[labels], camera=cam, width=160, height=120, shading=shading)
    assert img.shape == (120, 160, 3)
    hits = cast_rays(v, f, cam, 160, 120)
    px = img[hits.hit]
    assert np.all(img[~hits.hit] == BG)
    assert np.all(img[:, -10:] == BG)  # no colour bar
    err, which = _best_scaled_match(px, palette)
    assert err.max() < 2.5  # every pixel is a shade of one of the two colours: no blends, no other hues
    assert (which == 0).sum() > 500 and (which == 1).sum() > 500
    if not shading:  # flat: exactly the two colours
        exact = np.round(palette * 255).astype(np.uint8)
        assert {tuple(p) for p in px} == {tuple(c) for c in exact}
    # left half of the image (x < 0 seen from +z) holds label 0, the far right label 1
    row = img[60]
    left, right = np.flatnonzero(hits.hit[60])[[2, -3]]
    assert _best_scaled_match(row[[left]], palette)[1][0] == 0
    assert _best_scaled_match(row[[right]], palette)[1][0] == 1


def test_vertex_colors_errors(sphere):
    v, f = sphere
    good = np.full((len(v), 3), 0.5)
    with pytest.raises(ValueError, match="scalar"):
        render(v, f, scalar=v[:, 0], vertex_colors=good, width=20, height=20)
    with pytest.raises(ValueError, match="shape"):
        render(v, f, vertex_colors=good[:-1], width=20, height=20)
    with pytest.raises(ValueError, match="shape"):
        render(v, f, vertex_colors=good[:, :2], width=20, height=20)
    with pytest.raises(ValueError):
        render(v, f, vertex_colors=good * 3.0, width=20, height=20)
