"""Classical handle baselines of seed 004 (ARAP and biharmonic-type weights + LBS through libigl): weights
interpolate the handles and sum to one, biharmonic coordinates have linear precision, the weight solve equals
igl.harmonic's, zero motion is the identity, a common rigid / affine motion of all handles moves the mesh by
that motion, ARAP meets its hard constraints and converges to the rigid motion, timings and input errors;
plus the deformation-survey bar with its own handle / fixed regions and handle transform."""

import igl
import numpy as np
import pytest
import trimesh
from conftest import data_dir, grid_mesh
from scipy.spatial.transform import Rotation

from jaxdeform.errors import ConnectivityError, DegenerateMeshError, JaxDeformError
from jaxdeform.handles import baselines as B
from jaxdeform.mesh.io import load_mesh

KINDS = B.WEIGHT_KINDS
# libigl's arap_solve fits the local rotations in single precision, so ARAP reproduces rigid motions (and zero
# motion) only to ~1e-5 of the mesh size; constrained vertices are exact.
ARAP_TOL = 1e-4


def _ellipsoid(subdivisions: int = 2):
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(m.vertices) * [1.0, 0.7, 0.5], np.asarray(m.faces, dtype=np.int64)


def _diag(v):
    return float(np.linalg.norm(np.ptp(v, axis=0)))


def _affine(matrix, translation):
    return np.concatenate([np.asarray(matrix, float), np.asarray(translation, float)[:, None]], axis=1)


RIGID = _affine(Rotation.from_rotvec([0.3, -0.2, 0.4]).as_matrix(), [0.5, 0.2, -0.1])
SHEAR = _affine([[1.2, 0.3, 0.0], [0.0, 0.9, -0.2], [0.1, 0.0, 1.1]], [0.3, -0.4, 0.2])
HANDLES = np.array([0, 5, 17, 40, 100])


def _apply(d, v):
    return v @ d[:, :3].T + d[:, 3]


# --------------------------------------------------------------------------------- weights


@pytest.mark.parametrize("volume", [False, True])
@pytest.mark.parametrize("kind", KINDS)
def test_weights_interpolate_handles_and_sum_to_one(kind, volume):
    v, f = _ellipsoid()
    model = B.BiharmonicBaseline(v, f, kind=kind, volume=volume).bind(HANDLES, fixed=[150])
    w = np.concatenate([model.weights, model.fixed_weights], axis=1)
    assert w.shape == (v.shape[0], HANDLES.size + 1)
    np.testing.assert_allclose(w[np.append(HANDLES, 150)], np.eye(HANDLES.size + 1), atol=1e-8)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-8)
    if volume:
        assert model.n_domain_vertices > v.shape[0]  # TetGen added interior points
    if kind == "bounded":
        assert w.min() > -1e-6 and w.max() < 1 + 1e-6
    else:
        assert w.min() < -1e-3  # unbounded biharmonic weights do go negative: the bounds above are BBW's


@pytest.mark.parametrize("volume", [False, True])
def test_biharmonic_split_solve_equals_igl_harmonic(volume):
    v, f = _ellipsoid()
    model = B.BiharmonicBaseline(v, f, kind="biharmonic", volume=volume).bind(HANDLES)
    tv, tt = B.tetrahedralize(v, f) if volume else (v, f)
    reference = igl.harmonic(tv, tt, HANDLES, np.eye(HANDLES.size), 2)[: v.shape[0]]
    np.testing.assert_allclose(model.weights, reference, atol=1e-9)
    if not volume:  # the free rows satisfy the biharmonic equation Q W = L M^-1 L W = 0
        L, M = igl.cotmatrix(v, f), igl.massmatrix(v, f)
        q_w = L @ (L @ model.weights / M.diagonal()[:, None])
        free = np.setdiff1d(np.arange(v.shape[0]), HANDLES)
        assert np.abs(q_w[free]).max() < 1e-8 * np.abs(q_w[HANDLES]).max()


def test_biharmonic_coordinates_have_linear_precision():
    # Wang et al. 2015: sum_k W_ik p_k = v_i, on a volume mesh and on a flat surface
    v, f = _ellipsoid()
    w = B.BiharmonicBaseline(v, f, kind="coordinates", volume=True).bind(HANDLES).weights
    np.testing.assert_allclose(w @ v[HANDLES], v, atol=1e-9)
    g, gf = grid_mesh(12)
    hg = np.array([0, 11, 143, 60, 37])
    wg = B.BiharmonicBaseline(g, gf, kind="coordinates").bind(hg).weights
    np.testing.assert_allclose(wg @ g[hg], g, atol=1e-9)
    # the plain biharmonic weights (Neumann-type boundary) do not have it: the test can tell them apart
    wb = B.BiharmonicBaseline(g, gf, kind="biharmonic").bind(hg).weights
    assert np.abs(wb @ g[hg] - g).max() > 1e-3


# ------------------------------------------------------------------------------------- LBS


@pytest.mark.parametrize("kind", KINDS)
def test_lbs_identity_rigid_and_affine(kind):
    v, f = _ellipsoid()
    model = B.BiharmonicBaseline(v, f, kind=kind).bind(HANDLES, fixed=[150])
    k = HANDLES.size
    np.testing.assert_allclose(model.pose(np.tile(np.eye(3, 4), (k, 1, 1))), v, atol=1e-12)
    # all handles AND the fixed vertex free: a common motion is reproduced (partition of unity)
    model.bind(HANDLES)
    for d in (RIGID, SHEAR):
        np.testing.assert_allclose(model.pose(np.tile(d, (k, 1, 1))), _apply(d, v), atol=1e-8)


def test_lbs_matches_direct_blend():
    v, f = _ellipsoid()
    model = B.BiharmonicBaseline(v, f).bind(HANDLES, fixed=[150, 151])
    d = np.random.default_rng(0).normal(size=(HANDLES.size, 3, 4))
    w, w_fixed = model.weights, model.fixed_weights
    # plain LBS with the fixed vertices as identity handles, one handle at a time
    expected = sum(w[:, [j]] * _apply(d[j], v) for j in range(HANDLES.size)) + w_fixed.sum(1, keepdims=True) * v
    np.testing.assert_allclose(model.pose(d), expected, atol=1e-8)
    np.testing.assert_allclose(model.pose(d)[HANDLES], B.handle_targets(v, HANDLES, d), atol=1e-8)


# ------------------------------------------------------------------------------------ ARAP


def test_arap_constraints_are_exact_and_identity_is_kept():
    v, f = _ellipsoid()
    model = B.ARAPBaseline(v, f).bind(HANDLES, fixed=[150, 151])
    d = np.tile(np.eye(3, 4), (HANDLES.size, 1, 1))
    assert np.abs(model.pose(d) - v).max() < 1e-5 * _diag(v)
    d = np.random.default_rng(1).normal(scale=0.2, size=(HANDLES.size, 3, 4)) + np.eye(3, 4)
    out = model.pose(d)
    assert out.shape == v.shape and out.dtype == np.float64 and np.all(np.isfinite(out))
    np.testing.assert_allclose(out[HANDLES], B.handle_targets(v, HANDLES, d), atol=1e-6)
    np.testing.assert_allclose(out[[150, 151]], v[[150, 151]], atol=1e-6)


def test_arap_rigid_motion_is_a_fixed_point_and_is_reached_from_rest():
    v, f = _ellipsoid()
    handles = np.arange(0, v.shape[0], 7)
    model = B.ARAPBaseline(v, f).bind(handles)
    d = np.tile(RIGID, (handles.size, 1, 1))
    target = _apply(RIGID, v)
    assert np.abs(model.pose(d, initial=target) - target).max() < ARAP_TOL * _diag(v)
    errors = [np.abs(model.pose(d, iterations=n) - target).max() for n in (1, 10, 50)]
    assert errors[0] > errors[1] > errors[2] and errors[2] < ARAP_TOL * _diag(v)
    assert errors[0] > 100 * ARAP_TOL * _diag(v)  # one iteration from rest is far off: the loop does the work


# ------------------------------------------------------------------------------ timings, run


@pytest.mark.parametrize("method", B.METHODS)
def test_run_baseline_reports_three_phases(method):
    v, f = _ellipsoid(1)
    d = np.tile(SHEAR, (3, 1, 1))
    out, timings = B.run_baseline(method, v, f, [0, 5, 17], d, fixed=[30])
    assert out.shape == v.shape and out.dtype == np.float64
    assert set(timings) == set(B.PHASES) and all(isinstance(t, float) and t >= 0 for t in timings.values())
    np.testing.assert_allclose(out[[0, 5, 17]], B.handle_targets(v, [0, 5, 17], d), atol=1e-6)
    np.testing.assert_allclose(out[30], v[30], atol=1e-6)


# ----------------------------------------------------------------------------------- errors


def test_input_errors_are_clear():
    v, f = _ellipsoid(1)
    n = v.shape[0]
    for cls in (B.ARAPBaseline, B.BiharmonicBaseline):
        model = cls(v, f)
        with pytest.raises(B.HandleError, match="bind"):
            model.pose(np.zeros((1, 3, 4)))
        with pytest.raises(B.HandleError, match=f"handle vertex {n} is out of range"):
            model.bind([0, n])
        with pytest.raises(B.HandleError, match="out of range"):
            model.bind([-1])
        with pytest.raises(B.HandleError, match="more than once"):
            model.bind([3, 3])
        with pytest.raises(B.HandleError, match="both a handle and a fixed"):
            model.bind([3], fixed=[3])
        with pytest.raises(B.HandleError, match="at least one handle"):
            model.bind([])
        model.bind([0, 1])
        with pytest.raises(B.HandleError, match=r"shape \(2, 3, 4\)"):
            model.pose(np.zeros((3, 3, 4)))
        with pytest.raises(DegenerateMeshError, match="no faces"):
            cls(v, np.zeros((0, 3), dtype=np.int64))
        with pytest.raises(ConnectivityError):
            cls(v, np.array([[0, 1, n]]))
    # two disjoint shells, handles only on the first: the second is undetermined
    two_v, two_f = np.concatenate([v, v + 3.0]), np.concatenate([f, f + n])
    for method in B.METHODS:
        with pytest.raises(B.HandleError, match="connected component"):
            B.make_baseline(method, two_v, two_f).bind([0, 1])
    g, gf = grid_mesh(5)
    with pytest.raises(DegenerateMeshError, match="TetGen"):
        B.BiharmonicBaseline(g, gf, volume=True)  # an open surface has no inside
    with pytest.raises(ValueError, match="method must be one of"):
        B.make_baseline("mls", v, f)
    assert issubclass(B.HandleError, JaxDeformError)


# --------------------------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def bar():
    d = data_dir("deformation-survey")
    v, f = load_mesh(d / "bar.off")
    sel = np.array([int(line) for line in (d / "bar.sel").read_text().splitlines() if line.strip() and line[0] != "#"])
    m = np.array(
        [
            float(t)
            for line in (d / "bar.def").read_text().splitlines()
            if not line.startswith("#")
            for t in line.split()
        ]
    ).reshape(4, 4)
    assert sel.shape == (v.shape[0],) and np.allclose(m[3], [0, 0, 0, 1])
    return v, f, np.flatnonzero(sel == 2), np.flatnonzero(sel == 0), m[:3]


def test_bar_arap_and_biharmonic_follow_the_survey_handles(bar):
    v, f, handles, fixed, d = bar
    assert handles.size > 0 and fixed.size > 0
    transforms = np.tile(d, (handles.size, 1, 1))
    target = _apply(d, v[handles])
    for method in ("arap", "biharmonic"):
        out, timings = B.run_baseline(method, v, f, handles, transforms, fixed=fixed)
        assert np.all(np.isfinite(out)) and set(timings) == set(B.PHASES)
        np.testing.assert_allclose(out[handles], target, atol=1e-6)
        np.testing.assert_allclose(out[fixed], v[fixed], atol=1e-6)
        free = np.setdiff1d(np.arange(v.shape[0]), np.concatenate([handles, fixed]))
        assert np.abs(out[free] - v[free]).max() > 1.0  # the deformable region did move
