"""Seed 004 views: Fibonacci cameras, QEM simplification, ray-cast views (eq. 2) and their covered pixels."""

import math

import igl
import numpy as np
import pytest
import trimesh

from jaxdeform.handles.views import (
    RenderedViews,
    fibonacci_cameras,
    fibonacci_directions,
    render_views,
    simplify,
)
from jaxdeform.mesh.io import load_mesh
from tests.conftest import data_dir


def nearest_angles(d):
    c = np.clip(d @ d.T, -1.0, 1.0)
    np.fill_diagonal(c, -1.0)
    return np.arccos(c.max(axis=1))


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    return np.asarray(m.vertices) + [0.3, -0.2, 0.5], np.asarray(m.faces)


@pytest.fixture(scope="module")
def capsule():
    """An elongated mesh (along z), off the origin: the framing must follow its centre and extent."""
    m = trimesh.creation.capsule(height=2.0, radius=0.4, count=[24, 24])
    return np.asarray(m.vertices) + [1.0, 2.0, -3.0], np.asarray(m.faces)


def pixel_rays(cam, yx, height, width):
    """Unit ray directions through image points (y, x) of a pinhole camera (fov across the shorter side)."""
    fwd, right, up = cam.basis()
    s = math.tan(math.radians(cam.fov_deg) / 2.0) / (min(height, width) / 2.0)
    d = fwd + ((yx[:, 1:2] - width / 2.0) * s) * right + ((height / 2.0 - yx[:, 0:1]) * s) * up
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# ------------------------------------------------------------------------------------------- directions


@pytest.mark.parametrize("n", [20, 100, 500])
def test_fibonacci_directions_unit_and_even(n):
    d = fibonacci_directions(n)
    assert d.shape == (n, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert np.linalg.norm(d.mean(axis=0)) < 0.02  # balanced over the sphere
    # equal-area spread: nearest-neighbour angles nearly constant, close to the hexagonal spacing of n points
    a = nearest_angles(d)
    assert a.std() / a.mean() < 0.05 and a.min() / a.max() > 0.85
    hexagonal = math.sqrt(8.0 * math.pi / (math.sqrt(3.0) * n))
    assert 0.8 * hexagonal < a.mean() < 1.05 * hexagonal
    # as a contrast, uniformly random directions spread far less evenly
    r = np.random.default_rng(0).normal(size=(n, 3))
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    b = nearest_angles(r)
    assert b.std() / b.mean() > 5 * (a.std() / a.mean())
    assert len({tuple(x) for x in np.round(d, 9)}) == n
    with pytest.raises(ValueError):
        fibonacci_directions(0)


def test_cameras_look_at_centre_and_frame_the_mesh(capsule):
    v, f = capsule
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    cams = fibonacci_cameras(v, 12, up=(0.0, 0.0, 1.0))
    assert len(cams) == 12
    dirs = np.array([np.subtract(c.eye, centre) for c in cams])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    # the view directions are the Fibonacci directions, turned so that the spiral's axis is the given up
    assert np.allclose(dirs[:, 2], fibonacci_directions(12)[:, 1], atol=1e-9)
    views = render_views(v, f, cams, 64, progress=False)
    for k, cam in enumerate(cams):
        np.testing.assert_allclose(cam.target, centre)
        assert np.dot(cam.basis()[2], [0.0, 0.0, 1.0]) > 0  # upright
        hit = views.tri[k] >= 0
        # the whole mesh is in view (nothing touches the border) and reaches out to the margin (1.05) on one
        # side: the field of view is symmetric about the centre, the perspective projection need not be
        assert not (hit[0].any() or hit[-1].any() or hit[:, 0].any() or hit[:, -1].any())
        ii, jj = np.nonzero(hit)
        reach = max(np.abs(ii + 0.5 - 32).max(), np.abs(jj + 0.5 - 32).max())
        assert 32 / 1.05 - 1.5 < reach < 32 / 1.05 + 0.5
        # every vertex projects inside the image
        fwd, right, up = cam.basis()
        rel = v - np.asarray(cam.eye)
        t = math.tan(math.radians(cam.fov_deg) / 2.0)
        assert np.all(np.abs(rel @ right) / (rel @ fwd) < t) and np.all(np.abs(rel @ up) / (rel @ fwd) < t)
    # without the tight fit every camera keeps the given field of view, so the mesh is smaller
    loose = fibonacci_cameras(v, 12, tight=False, fov_deg=40.0)
    assert all(c.fov_deg == 40.0 for c in loose)
    assert all(c.fov_deg < 40.0 for c in cams)


# -------------------------------------------------------------------------------------------- rendering


@pytest.mark.parametrize("tight", [True, False])
def test_sphere_covers_the_analytic_disc(sphere, tight):
    v, f = sphere
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    cams = fibonacci_cameras(v, 6, tight=tight)
    size = 160
    views = render_views(v, f, cams, size, progress=False)
    for k, cam in enumerate(cams):
        dist = np.linalg.norm(np.subtract(cam.eye, centre))
        alpha = math.asin(1.0 / dist)  # half-angle of the cone tangent to the unit sphere
        rho = math.tan(alpha) / math.tan(math.radians(cam.fov_deg) / 2.0) * size / 2.0  # disc radius in pixels
        expected = math.pi * rho**2 / size**2
        covered = np.mean(views.tri[k] >= 0)
        assert covered == pytest.approx(expected, rel=0.02)
    if tight:  # the disc fills the image up to the margin: radius = size / (2 * 1.05)
        assert np.mean(views.tri >= 0) == pytest.approx(math.pi / (4 * 1.05**2), rel=0.02)


def test_points_are_barycentric_hits_on_the_pixel_rays(capsule):
    v, f = capsule
    cams = fibonacci_cameras(v, 5)
    h, w = 40, 56  # non-square: fov spans the shorter side
    views = render_views(v, f, cams, (h, w), progress=False)
    assert isinstance(views, RenderedViews) and views.image_hw == (h, w)
    assert views.tri.shape == (5, h, w) and views.tri.dtype == np.int32
    assert views.bary.shape == views.points.shape == (5, h, w, 3)
    assert views.bary.dtype == views.points.dtype == np.float32 and views.rgb.dtype == np.uint8
    hit = views.tri >= 0
    b = views.bary[hit].astype(np.float64)
    assert b.min() >= 0.0
    np.testing.assert_allclose(b.sum(axis=1), 1.0, atol=1e-6)
    corners = v[f[views.tri[hit]]]
    scale = np.ptp(v, axis=0).max()
    np.testing.assert_allclose(views.points[hit], np.einsum("pk,pkc->pc", b, corners), atol=1e-6 * scale)
    assert np.all(np.isnan(views.points[~hit])) and np.all(views.bary[~hit] == 0)
    # covered(): flat arrays of the same pixels, pixel centres at (i + 0.5, j + 0.5)
    cov = views.covered()
    p = int(hit.sum())
    assert cov.view.shape == (p,) and cov.pixel_yx.shape == (p, 2) and cov.points.shape == (p, 3)
    assert cov.view.dtype == np.int32 and cov.pixel_yx.dtype == np.float32 and cov.points.dtype == np.float32
    i = (cov.pixel_yx[:, 0] - 0.5).astype(int)
    j = (cov.pixel_yx[:, 1] - 0.5).astype(int)
    np.testing.assert_array_equal(cov.pixel_yx - 0.5, np.stack([i, j], axis=1))
    assert np.all(views.tri[cov.view, i, j] >= 0)
    np.testing.assert_array_equal(cov.points, views.points[cov.view, i, j])
    # each point lies on the ray through its pixel centre, in front of the camera
    for k, cam in enumerate(cams):
        sel = cov.view == k
        rel = cov.points[sel].astype(np.float64) - np.asarray(cam.eye)
        ray = pixel_rays(cam, cov.pixel_yx[sel].astype(np.float64), h, w)
        depth = np.einsum("pc,pc->p", rel, ray)
        assert depth.min() > 0
        off_ray = np.linalg.norm(rel - depth[:, None] * ray, axis=1)
        assert off_ray.max() < 1e-4 * scale
    # the nearest surface: rays through the pixels hit nothing closer (trimesh's own ray test)
    cam = cams[0]
    sel = np.flatnonzero(cov.view == 0)[::7]
    origins = np.broadcast_to(np.asarray(cam.eye), (sel.size, 3))
    ray = pixel_rays(cam, cov.pixel_yx[sel].astype(np.float64), h, w)
    locs, idx, _ = trimesh.Trimesh(v, f, process=False).ray.intersects_location(origins, ray, multiple_hits=False)
    ours = np.linalg.norm(cov.points[sel][idx] - origins[idx], axis=1)
    theirs = np.linalg.norm(locs - origins[idx], axis=1)
    np.testing.assert_allclose(ours, theirs, atol=1e-4 * scale)


def test_rgb_shading_and_vertex_colours(sphere):
    v, f = sphere
    cams = fibonacci_cameras(v, 3)
    plain = render_views(v, f, cams, 48, progress=False)
    hit = plain.tri >= 0
    assert np.all(plain.rgb[~hit] == 255)  # white background
    assert np.all(plain.rgb[hit].astype(int).sum(-1) < 3 * 255)
    # headlight: the disc centre faces the camera and is brighter than the silhouette
    assert plain.rgb[0, 24, 24].astype(int).sum() > plain.rgb[0, 24, np.flatnonzero(hit[0, 24])[0]].astype(int).sum()
    # per-vertex colours: red on one side (x above the centre), blue on the other, interpolated and shaded
    red = (v[:, 0] > 0.3).astype(float)
    colors = np.stack([red, np.zeros_like(red), 1.0 - red], axis=1)
    coloured = render_views(v, f, cams, 48, colors=colors, progress=False)
    px = coloured.rgb[hit].astype(int)
    assert np.all(px[:, 1] == 0) and np.all(px[:, 0] + px[:, 2] > 0)
    assert (px[:, 0] > px[:, 2]).sum() > 100 and (px[:, 2] > px[:, 0]).sum() > 100
    u8 = render_views(v, f, cams, 48, colors=(colors * 255).astype(np.uint8), progress=False)
    np.testing.assert_array_equal(u8.rgb, coloured.rgb)
    np.testing.assert_array_equal(coloured.tri, plain.tri)
    with pytest.raises(ValueError, match="shape"):
        render_views(v, f, cams, 16, colors=colors[:-1], progress=False)


# --------------------------------------------------------------------------------------- simplification


def hausdorff(va, fa, vb, fb):
    return igl.hausdorff(va, fa.astype(np.int64), vb, fb.astype(np.int64))


def test_simplify_meets_target_and_keeps_shape():
    m = trimesh.creation.icosphere(subdivisions=5)  # 20480 faces
    v, f = np.asarray(m.vertices) * [1.0, 2.0, 0.5], np.asarray(m.faces)
    vs, fs = simplify(v, f, target_faces=2000)
    assert fs.shape[0] <= 2000 and fs.shape[0] >= 1800
    assert fs.dtype == np.int64 and vs.dtype == np.float64 and fs.max() < vs.shape[0]
    assert hausdorff(v, f, vs, fs) < 0.01 * np.linalg.norm(np.ptp(v, axis=0))
    # below the target: unchanged
    v2, f2 = simplify(vs, fs, target_faces=5000)
    np.testing.assert_array_equal(v2, vs)
    np.testing.assert_array_equal(f2, fs)


def test_simplify_armadillo():
    v, f = load_mesh(data_dir("test-meshes") / "armadillo.obj")
    vs, fs = simplify(v, f, target_faces=10_000)
    assert 9_000 <= fs.shape[0] <= 10_000
    diag = np.linalg.norm(np.ptp(v, axis=0))
    assert hausdorff(v, f, vs, fs) < 0.01 * diag
