"""Cloth simulator (seed 002): obstacle sdf, XPBD physics invariants, collisions, determinism, scenarios."""

import numpy as np
import pytest
from conftest import grid_mesh

from jaxdeform.cloth import obstacles as O
from jaxdeform.cloth import scenarios as S
from jaxdeform.cloth import simulate as sim

N = 7  # one mesh size, one obstacle layout and two static configurations keep compilations (the cost) few
FAR = -100.0


def _obs(sphere=None, capsule=None, cylinder=None, ground=O.NO_GROUND):
    """One sphere, capsule and cylinder always (unused ones far below), so every test shares the executable."""
    far = (0.0, FAR, 0.0)
    return O.make(
        spheres=[sphere or (far, 0.1)],
        capsules=[capsule or (far, (0.0, FAR, 1.0), 0.1)],
        cylinders=[cylinder or (far, 0.1, 0.1)],
        ground=ground,
    )


def _sheet(n=N, size=0.5, y=1.0):
    """A horizontal n x n sheet (xz-plane) centred at the origin at height y."""
    v, f = grid_mesh(n)
    x = np.stack([(v[:, 0] - 0.5) * size, np.full(len(v), y), (v[:, 1] - 0.5) * size], 1)
    return x.astype(np.float32), f


QUIET = sim.ClothParams(damping=0.0, drag=0.0, lift=0.0, turbulence=0.0, substeps=4, iterations=2, self_collision=False)
STD = sim.ClothParams(substeps=10, iterations=2, self_collision=False)


# ------------------------------------------------------------------------------------------------ obstacles


def test_sdf_sphere_capsule_ground():
    obs = O.make(spheres=[((0, 1, 0), 0.5)], capsules=[((3, 0, 0), (3, 2, 0), 0.25)], ground=-1.0)
    pts = np.array([[0, 2, 0], [0, 1.2, 0], [3.5, 1, 0], [3, 2.5, 0], [3, 1, 0.1], [10, -0.5, 10]], np.float32)
    d, n = O.signed_distance(obs, pts)
    np.testing.assert_allclose(d, [0.5, -0.3, 0.25, 0.25, -0.15, 0.5], atol=1e-6)
    np.testing.assert_allclose(n[0], [0, 1, 0], atol=1e-6)
    np.testing.assert_allclose(n[2], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(n[3], [0, 1, 0], atol=1e-6)  # beyond the pole's end: the cap
    np.testing.assert_allclose(n[4], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(n[5], [0, 1, 0], atol=1e-6)  # the ground


def test_query_closest_shape_and_its_surface_motion():
    # a sphere translates, a capsule turns about its end a (so its surface moves by (1 - t) da + t db at parameter
    # t), a cylinder and the ground rise; each point is nearest one of them
    prev = O.make(
        spheres=[((0, 1, 0), 0.5)],
        capsules=[((3, 0, 0), (3, 2, 0), 0.25)],
        cylinders=[((-3, 1, 0), 0.5, 1.0)],
        ground=-1.0,
    )
    now = O.make(
        spheres=[((0.1, 1, 0), 0.5)],
        capsules=[((3, 0, 0), (3.2, 2, 0), 0.25)],
        cylinders=[((-3, 1.05, 0), 0.5, 1.0)],
        ground=-0.9,
    )
    pts = np.array([[0.1, 1.7, 0], [3.5, 1.0, 0], [3.4, 1.5, 0], [-3, 1.3, 0], [10, -0.5, 10]], np.float32)
    d, n, disp, k = O.query(now, prev, pts)
    np.testing.assert_array_equal(k, [0, 1, 1, 2, 3])  # spheres, capsules, cylinders, then the ground
    ab = np.array([0.2, 2.0, 0.0])
    t = [(pts[i] - [3, 0, 0]) @ ab / (ab @ ab) for i in (1, 2)]
    expect = [[0.1, 0, 0], [0.2 * t[0], 0, 0], [0.2 * t[1], 0, 0], [0, 0.05, 0], [0, 0.1, 0]]
    np.testing.assert_allclose(disp, expect, atol=1e-6)
    d_ref, n_ref = O.signed_distance(now, pts)
    np.testing.assert_allclose(d, d_ref, atol=1e-7)
    np.testing.assert_allclose(n, n_ref, atol=1e-7)
    np.testing.assert_allclose(np.asarray(d)[[0, 3, 4]], [0.2, 0.25, 0.4], atol=1e-6)


def test_sdf_capped_cylinder_side_caps_rim_and_inside():
    obs = O.make(cylinders=[((0, 1, 0), 0.5, 1.0)])  # y in [0, 1], radius 0.5
    pts = np.array(
        [
            [1.0, 0.5, 0],  # side: 0.5
            [0.1, 1.3, 0],  # above the top cap: 0.3
            [0.1, -0.2, 0],  # below the bottom cap: 0.2
            [0.8, 1.4, 0],  # outside the top rim: distance to the rim circle 0.5
            [0.4, 0.5, 0],  # inside, nearest the side: -0.1
            [0.0, 0.95, 0],  # inside, nearest the top: -0.05
        ],
        np.float32,
    )
    d, n = O.signed_distance(obs, pts)
    np.testing.assert_allclose(d, [0.5, 0.3, 0.2, 0.5, -0.1, -0.05], atol=1e-6)
    np.testing.assert_allclose(n[3], [0.6, 0.8, 0], atol=1e-6)
    np.testing.assert_allclose(n[2], [0, -1, 0], atol=1e-6)
    np.testing.assert_allclose(n[4], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(n[5], [0, 1, 0], atol=1e-6)


def test_sdf_rounded_cylinder_rim_is_a_torus():
    """Rims rounded to e = 0.1: caps and side where they were, the rim a quarter torus (tube radius 0.1 about the
    circle of radius 0.4 at y = 0.9); the field stays a distance: the normals are its gradients."""
    obs = O.make(cylinders=[((0, 1, 0), 0.5, 1.0, 0.1)])
    c = np.array([0.4, 0.9, 0.0])  # the rim circle's point above the x axis
    dirs = np.array([[1, 1, 0], [3, 1, 0], [1, 3, 0]], np.float64)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = np.concatenate(
        [[[1.0, 0.5, 0], [0.1, 1.3, 0], [0.4, 0.5, 0], [0.0, 0.95, 0]], c + 0.25 * dirs, c + 0.05 * dirs]
    ).astype(np.float32)
    d, n = O.signed_distance(obs, pts)
    np.testing.assert_allclose(d, [0.5, 0.3, -0.1, -0.05, 0.15, 0.15, 0.15, -0.05, -0.05, -0.05], atol=1e-6)
    np.testing.assert_allclose(n[4:7], dirs, atol=1e-6)
    # the sharp cylinder's rim corner lies outside the rounded one: 0.1 (sqrt 2 - 1) ~ 0.041 away
    d_corner = O.signed_distance(obs, np.array([[0.5, 1.0, 0.0]], np.float32))[0]
    np.testing.assert_allclose(d_corner, [0.1 * (np.sqrt(2) - 1)], atol=1e-6)
    with pytest.raises(ValueError, match="rim radius"):
        O.make(cylinders=[((0, 1, 0), 0.5, 1.0, 0.5)])
    with pytest.raises(ValueError, match="top_centre, radius, height"):
        O.make(cylinders=[((0, 1, 0), 0.5)])
    # a track stored before the rounding existed reads as sharp rims
    track = O.to_dict(O.static_track(O.make(cylinders=[((0, 1, 0), 0.5, 1.0)]), 3))
    del track["cylinder_rounding"]
    back = O.from_dict(track)
    assert back.cylinder_rounding.shape == (3, 1) and not back.cylinder_rounding.any()


def test_sdf_normals_are_gradients_and_empty_shapes():
    obs = O.make(
        spheres=[((0.3, 1, 0), 0.4)],
        capsules=[((-1, 0.5, 0), (-1, 0.5, 1), 0.2)],
        cylinders=[((1.5, 1, 0.2), 0.5, 1.0), ((-1.2, 2.0, -0.4), 0.4, 0.8, 0.15)],
        ground=0.0,
        dtype=np.float64,
    )
    rng = np.random.default_rng(0)
    pts = rng.uniform([-2, -0.5, -1], [3, 2.5, 2], (200, 3))
    with _x64():
        d, n = O.signed_distance(obs, pts)
        eps = 1e-6
        fd = np.stack(
            [
                (
                    np.asarray(O.signed_distance(obs, pts + eps * e)[0])
                    - np.asarray(O.signed_distance(obs, pts - eps * e)[0])
                )
                / (2 * eps)
                for e in np.eye(3)
            ],
            1,
        )
    # away from medial surfaces (where the min switches shape) the normal is the gradient
    ok = np.linalg.norm(fd, axis=1) > 0.999
    assert ok.mean() > 0.9
    np.testing.assert_allclose(np.asarray(n)[ok], fd[ok], atol=1e-4)
    d0, n0 = O.signed_distance(O.empty(ground=0.25), np.array([[0, 1, 0]], np.float32))
    np.testing.assert_allclose(d0, [0.75], atol=1e-6)
    assert O.make().sphere_c.shape == (0, 3)


def _x64():
    import contextlib

    import jax

    @contextlib.contextmanager
    def ctx():
        old = jax.config.jax_enable_x64
        jax.config.update("jax_enable_x64", True)
        try:
            yield
        finally:
            jax.config.update("jax_enable_x64", old)

    return ctx()


# ------------------------------------------------------------------------------------------------ physics


def test_free_fall_follows_gravity():
    x, f = _sheet()
    m = sim.build_model(x, f)
    T = 12
    frames = sim.simulate(m, QUIET, x, None, O.static_track(_obs(), T), progress=False)
    n = np.arange(1, T + 1) * QUIET.substeps
    h = QUIET.frame_dt / QUIET.substeps
    g = QUIET.gravity
    # symplectic Euler exactly: y_n = y0 - g h^2 n (n + 1) / 2 (to float32 round-off of v = (p - x) / h, ~1e-7 / h
    # per substep); the continuous law y0 - g t^2 / 2 within the O(h) splitting error g t h / 2
    exact = 1.0 - g * h * h * n * (n + 1) / 2
    np.testing.assert_allclose(frames[:, :, 1], np.broadcast_to(exact[:, None], frames.shape[:2]), atol=2e-4)
    t = np.arange(1, T + 1) * QUIET.frame_dt
    assert np.all(np.abs(frames[:, :, 1].mean(1) - (1.0 - g * t * t / 2)) <= g * t * h + 1e-5)
    np.testing.assert_allclose(
        frames[:, :, [0, 2]], np.broadcast_to(x[:, [0, 2]], (T,) + x[:, [0, 2]].shape), atol=1e-5
    )


def test_hanging_sheet_stays_pinned_and_barely_stretches():
    # released horizontally, held at two adjacent corners: it swings down and hangs (stretch is checked in motion)
    v, f = grid_mesh(N)
    x = np.stack([v[:, 0] - 0.5, np.full(len(v), 1.5), v[:, 1]], 1).astype(np.float32)
    pinned = np.isclose(v[:, 1], 0.0) & (np.isclose(v[:, 0], 0.0) | np.isclose(v[:, 0], 1.0))  # two corners
    m = sim.build_model(x, f)
    frames = sim.simulate(m, STD, x, None, O.static_track(_obs(), 40), pinned, progress=False)
    np.testing.assert_array_equal(frames[:, pinned], np.broadcast_to(x[pinned], (40, 2, 3)))
    mean, mx = sim.edge_strain(m, frames)
    assert mean < 0.01 and mx < 0.05
    assert frames[-1, ~pinned, 1].mean() < 1.5 - 0.3  # it swung down


@pytest.mark.parametrize("shape", ["ground", "sphere", "cylinder"])
def test_dropped_cloth_never_penetrates(shape):
    x, f = _sheet(N, 0.8, 0.5)
    obs = {
        "ground": _obs(ground=0.0),
        "sphere": _obs(sphere=((0.05, 0.2, 0), 0.2), ground=0.0),
        "cylinder": _obs(cylinder=((0.0, 0.3, 0.0), 0.2, 0.3), ground=0.0),
    }[shape]
    m = sim.build_model(x, f)
    track = O.static_track(obs, 30)
    frames = sim.simulate(m, STD, x, None, track, progress=False)
    edge = float(m.mean_edge)
    assert S.max_penetration(frames, track) <= 0.01 * edge
    assert frames[-1, :, 1].min() < 0.3  # it reached the obstacle
    d, _ = O.signed_distance(obs, frames[-1])
    assert float(np.min(d)) >= sim.ClothParams().thickness - 1e-4


def test_moving_sphere_pushes_hanging_sheet_without_penetration():
    v, f = grid_mesh(N)
    x = np.stack([v[:, 0] - 0.5, v[:, 1] + 0.5, np.zeros(len(v))], 1).astype(np.float32)
    pinned = np.isclose(x[:, 1], 1.5)
    T = 25
    z = np.linspace(-0.4, 0.5, T)
    track = O.stack([_obs(sphere=((0.0, 1.0, zz), 0.2), ground=0.0) for zz in z])
    m = sim.build_model(x, f)
    frames = sim.simulate(m, STD, x, None, track, pinned, progress=False)
    assert S.max_penetration(frames, track) <= 0.01 * float(m.mean_edge)
    assert frames[-1, :, 2].max() > 0.3  # the sheet was pushed along


def test_face_barycentrics_grid():
    for n in (2, 4, 8):
        b = sim.face_barycentrics(n)
        assert b.shape == ((n + 1) * (n + 2) // 2 - 3, 3)
        np.testing.assert_allclose(b.sum(1), 1.0, atol=1e-6)
        assert b.min() >= 0 and b.max() < 1  # no corner: the vertices are tested already
        assert len(np.unique(np.round(b * n).astype(int), axis=0)) == len(b)
    assert sim.face_barycentrics(1).shape == (0, 3)
    with pytest.raises(sim.SimulationError):
        sim.face_barycentrics(-1)


@pytest.mark.parametrize("shape", ["right", "equilateral"])
def test_face_samples_rule_bounds_the_sag(shape):
    """The sphere of radius r through the corners of a sub-triangle of the chosen grid rises at most thickness / 2
    above the sub-triangle's plane, and one order less would not do; a small enough mesh needs no samples."""
    if shape == "right":
        x, f = _sheet(3, 1.0)  # legs 0.5
        R = 0.5 * np.sqrt(2) / 2  # half the hypotenuse
    else:
        x = np.array([[0, 0, 0], [0.5, 0, 0], [0.25, 0, 0.25 * np.sqrt(3)]], np.float32)
        f = np.array([[0, 1, 2]])
        R = 0.5 / np.sqrt(3)  # circumradius
    t, r = 0.005, 0.14
    n = sim.face_samples_for(x, f, t, r)

    def sag(k):
        return r - np.sqrt(r * r - (R / k) ** 2)  # exact rise of the sphere over the sub-triangle's plane

    assert n > 1 and sag(n) <= t / 2 * 1.02 and sag(n - 1) > t / 2  # (R/n)^2 / 2r underestimates the exact sag
    assert sim.face_samples_for(x * 0.01, f, t, r) == 0


def test_max_penetration_inside_a_triangle_analytic():
    """All three corners lie outside the unit sphere, but the triangle's plane passes 0.9 from its centre and its
    centroid (a point of the order-12 grid) is the foot of the perpendicular: 0 at the vertices, 0.1 inside."""
    foot = np.array([0.0, 0.9, 0.0])
    v0, v1 = np.array([2.0, 0.9, 0.0]), np.array([-1.0, 0.9, 2.0])
    frames = np.stack([v0, v1, 3 * foot - v0 - v1])[None].astype(np.float32)
    assert min(np.linalg.norm(frames[0], axis=1)) > 1.0
    track = O.static_track(O.make(spheres=[((0, 0, 0), 1.0)]), 1)
    assert S.PENETRATION_SAMPLES % 3 == 0
    assert S.max_penetration(frames, track) == 0.0
    assert S.max_penetration(frames, track, np.array([[0, 1, 2]])) == pytest.approx(0.1, abs=1e-6)


def test_face_contacts_keep_a_coarse_sheet_out_of_a_sphere():
    """A sheet of 8 cm edges dropped on a 10 cm sphere under a triangle: with vertex contacts alone the sphere
    sinks into the triangles between their corners (by ~1.4 cm, the sag minus the thickness); with the contact
    points of ``face_samples_for`` nothing inside any triangle penetrates, and the vertices stay out too."""
    x, f = _sheet(N, 0.5, 0.4)
    m = sim.build_model(x, f)
    c = x[f[len(f) // 2]].mean(0)  # a triangle's centroid near the middle
    obs = _obs(sphere=((float(c[0]), 0.2, float(c[2])), 0.1), ground=0.0)
    track = O.static_track(obs, 20)
    n = sim.face_samples_for(x, f, STD.thickness, 0.1)
    assert n >= 2
    depth = {}
    for k in (0, n):
        frames = sim.simulate(m, STD.replace(face_samples=k), x, None, track, progress=False)
        assert S.max_penetration(frames, track) <= 1e-6  # vertices: out either way
        assert frames[-1, :, 1].max() < 0.33  # no vertex is left above the sphere's top (0.3) + a margin
        depth[k] = S.max_penetration(frames, track, f)
    assert depth[0] > 0.1 * float(m.mean_edge)
    assert depth[n] <= 0.01 * float(m.mean_edge)


def test_face_contacts_keep_a_coarse_sheet_out_of_a_rounded_table_rim():
    """The same sheet dropped across the rounded rim (5 cm) of a table, part of it hanging off: with vertex contacts
    alone the rim sinks into the triangles that fold over it; with the points of ``face_samples_for`` for the rim's
    radius nothing inside any triangle penetrates by more than 1 % of the edge (the DISK scenes' table)."""
    x, f = _sheet(N, 0.5, 0.4)
    m = sim.build_model(x, f)
    e = 0.05
    obs = _obs(cylinder=((-0.3, 0.3, 0.0), 0.3, 0.3, e), ground=0.0)  # rim under the sheet's middle row (x = 0)
    track = O.static_track(obs, 20)
    n = sim.face_samples_for(x, f, STD.thickness, e)
    depth = {}
    for k in (0, n):
        frames = sim.simulate(m, STD.replace(face_samples=k), x, None, track, progress=False)
        assert S.max_penetration(frames, track) <= 1e-6
        assert frames[-1, :, 1].min() < 0.2  # the free half hangs down past the rim
        depth[k] = S.max_penetration(frames, track, f)
    assert depth[0] > 0.1 * float(m.mean_edge)
    assert depth[n] <= 0.01 * float(m.mean_edge)


def test_face_friction_carries_a_triangle_resting_on_its_interior():
    """A rigid triangle (circumradius 10 cm) lies on the top of a sphere of radius 0.5 m, touching it only inside
    (its corners are 1 cm above the surface), and the sphere accelerates sideways at 0.6 m/s^2 < mu g (3.9). With
    friction at the contact points the triangle rides along (Coulomb: it sticks); without it the sphere slides
    out from under the triangle, which tips off on the other side."""
    R = 0.1
    ang = np.deg2rad([90.0, 210.0, 330.0])
    y0 = 0.5 + STD.thickness + 1e-3
    x = np.stack([R * np.cos(ang), np.full(3, y0), R * np.sin(ang)], 1).astype(np.float32)
    f = np.array([[0, 2, 1]])
    m = sim.build_model(x, f)
    T, a = 15, 0.6
    t = np.arange(T) * STD.frame_dt
    track = O.stack([_obs(sphere=((0.5 * a * tt * tt, 0.0, 0.0), 0.5)) for tt in t])
    moved = {}
    for friction in (True, False):
        p = STD.replace(face_samples=6, face_friction=friction)
        frames = sim.simulate(m, p, x, None, track, progress=False)
        assert S.max_penetration(frames, track, f) <= 1e-6
        moved[friction] = float(frames[-1, :, 0].mean())
    s = 0.5 * a * t[-1] ** 2  # the sphere's travel, 5.9 cm
    assert moved[True] == pytest.approx(s, rel=0.1)
    assert moved[False] < 0.2 * s


def test_disk_scenes_have_a_rounded_table_and_contacts_for_it():
    sc = S.scenario("disk", 0, n_frames=2)
    assert sc.track.cylinder_rounding[0, 0] == pytest.approx(S.TABLE_RIM_RADIUS) and sc.meta["table_rim_radius"] > 0
    cv, cf, fv, ff = S.meshes("disk")
    assert sc.params.face_samples == sim.face_samples_for(cv, cf, sc.params.thickness, S.TABLE_RIM_RADIUS) > 1
    assert sc.meta["fine_face_samples"] == sim.face_samples_for(fv, ff, sc.params.thickness, S.TABLE_RIM_RADIUS)


def test_determinism_turbulence_and_no_retrace():
    x, f = _sheet()
    m = sim.build_model(x, f)
    p = QUIET.replace(turbulence=3.0, wind=(2.0, 0.0, 0.0), drag=1.0, lift=0.5)
    track = O.static_track(_obs(), 12)  # 12 frames: a whole chunk and a padded one
    import jax

    a = sim.simulate(m, p, x, None, track, key=jax.random.PRNGKey(1), progress=False)
    n = sim.trace_count()
    b = sim.simulate(m, p, x, None, track, key=jax.random.PRNGKey(1), progress=False)
    c = sim.simulate(m, p.replace(turbulence=2.0), x, None, track, key=jax.random.PRNGKey(2), progress=False)
    assert sim.trace_count() == n  # other key and another wind strength reuse the executable
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-4
    assert a[-1, :, 0].mean() > x[:, 0].mean() + 0.01  # the wind blew along +x


def test_air_drag_slows_a_falling_sheet():
    x, f = _sheet(N, 0.5, 2.0)
    m = sim.build_model(x, f)
    track = O.static_track(_obs(), 15)
    free = sim.simulate(m, QUIET, x, None, track, progress=False)
    air = sim.simulate(m, QUIET.replace(drag=1.0), x, None, track, progress=False)
    # terminal speed of a flat plate sqrt(2 m g / (rho C_d A)) = sqrt(2 * 0.2 * 9.81 / 1.2) = 1.8 m/s
    v_air = (air[-1, :, 1].mean() - air[-2, :, 1].mean()) / QUIET.frame_dt
    assert free[-1, :, 1].mean() < air[-1, :, 1].mean()
    assert -1.9 < v_air < -1.2


def test_bending_constraint_is_zero_at_rest_and_measures_hinge_angle():
    import jax.numpy as jnp

    x, f = _sheet(4, 0.3, 0.0)
    m = sim.build_model(x, f)
    c0 = np.einsum("hk,hkd->hd", np.asarray(m.hinge_k), x[np.asarray(m.hinges)]) - np.asarray(m.hinge_rest)
    np.testing.assert_allclose(c0, 0, atol=1e-6)
    # rotate the wing x3 of hinge 0 by theta about the edge: |c| = |e| theta to first order
    h = np.asarray(m.hinges)[0].astype(int)
    p = x.astype(np.float64).copy()
    e = p[h[1]] - p[h[0]]
    a = e / np.linalg.norm(e)
    th = 1e-3
    r = p[h[3]] - p[h[0]]
    p[h[3]] = p[h[0]] + r * np.cos(th) + np.cross(a, r) * np.sin(th) + a * (a @ r) * (1 - np.cos(th))
    c = np.asarray(m.hinge_k)[0] @ p[h] - np.asarray(m.hinge_rest)[0]
    assert abs(np.linalg.norm(c) - np.linalg.norm(e) * th) < 1e-2 * np.linalg.norm(e) * th
    assert jnp.all(m.hinge_count > 0)


def test_self_collision_keeps_layers_apart():
    # a strip dropped on a thin pole folds over it; both halves fall together and must not pass through
    v, f = grid_mesh(13)
    x = np.stack([(v[:, 0] - 0.5) * 0.9, np.full(len(v), 0.6), (v[:, 1] - 0.5) * 0.3], 1).astype(np.float32)
    m = sim.build_model(x, f)
    track = O.static_track(O.make(capsules=[((0.0, 0.5, -0.5), (0.0, 0.5, 0.5), 0.02)], ground=0.0), 45)
    p = sim.ClothParams(substeps=10, iterations=2, friction=0.8)
    frames = sim.simulate(m, p, x, None, track, progress=False)
    r = p.self_radius * float(m.mean_edge)
    nbr, mask = sim.self_candidates(m, frames[-1], r)  # recheck with the final positions
    last = frames[-1]
    d = np.linalg.norm(last[:, None] - last[np.asarray(nbr)], axis=-1)
    assert np.all(d[np.asarray(mask)] > 0.5 * r)
    # the two halves (x < 0 and x > 0 at rest) hang on either side; in the pile on the ground no vertex of one
    # half may lie on the other half's side of the pole's vertical plane by more than the radius
    left = x[:, 0] < -0.05
    right = x[:, 0] > 0.05
    assert last[left, 0].max() < 0.1 and last[right, 0].min() > -0.1


# ------------------------------------------------------------------------------------------------ scenarios


def test_loop_counts_and_original_vertices_first():
    cv, cf, fv, ff = S.meshes("sheet")
    assert len(cv) == 81 and len(fv) == 4225 and len(ff) == 8192
    interior = (np.abs(cv[:, 0]) < 0.49) & (cv[:, 1] > 0.41) & (cv[:, 1] < 1.39)
    np.testing.assert_allclose(fv[: len(cv)][interior], cv[interior], atol=1e-9)  # flat regular grid stays
    dv, df, dfv, dff = S.meshes("disk")
    assert len(dv) == 148 and len(dfv) == 7729


def test_scenarios_are_deterministic_and_varied():
    a = S.scenario("sheet", 3, seed=1, n_frames=20)
    b = S.scenario("sheet", 3, seed=1, n_frames=20)
    c = S.scenario("sheet", 4, seed=1, n_frames=20)
    np.testing.assert_array_equal(a.track.capsule_a, b.track.capsule_a)
    assert a.meta == b.meta and a.meta["obstacle"] == "pole" and c.meta["obstacle"] == "sphere"
    import json

    json.dumps(a.meta)
    for kind in ("sheet", "disk"):
        sc = S.scenario(kind, 0, n_frames=10)
        assert sc.pinned_fine.sum() > 0 and sc.pinned_coarse.sum() > 0
        assert sc.wind.shape == (10, 3)
    radii = [S.scenario("sheet", i, n_frames=2).meta["radius"] for i in range(4)]
    assert min(radii) > S.SHEET_SIZE / (S.SHEET_N - 1)  # no tunnelling through the coarse mesh


def test_max_penetration_analytic():
    track = O.static_track(O.make(spheres=[((0, 0, 0), 1.0)]), 2)
    frames = np.array([[[0, 0.7, 0], [2, 0, 0]], [[0, 1.5, 0], [0, 0, 0.9]]], np.float32)
    assert S.max_penetration(frames, track) == pytest.approx(0.3, abs=1e-6)


def test_simulate_fine_repeats_the_pair_and_a_perturbed_start_moves_it():
    """simulate_fine without perturbation is the fine run of simulate_pair; a 0.1 mm start perturbation moves
    the free vertices only, and by more than nothing; a negative perturbation is refused."""
    sc = S.scenario("sheet", 0, n_frames=6, levels=1)
    pair = S.simulate_pair(sc, progress=False)
    np.testing.assert_allclose(S.simulate_fine(sc), pair["fine"], atol=1e-6)
    moved = S.simulate_fine(sc, perturbation=1e-4)
    d = np.linalg.norm(moved - pair["fine"], axis=-1)
    assert d[:, sc.pinned_fine].max() == 0.0 and d[:, ~sc.pinned_fine].max() > 1e-6
    with pytest.raises(S.ScenarioError):
        S.simulate_fine(sc, perturbation=-1.0)
