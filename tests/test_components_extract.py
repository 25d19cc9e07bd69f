"""Seed 000 component extraction (eqs. (4), (7), Sec. 4.3, Fig. 3) and component figures, on tiny meshes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import grid_mesh
from PIL import Image

from jaxdeform.acap import Scaler
from jaxdeform.components import extract, figures, model
from jaxdeform.errors import ConnectivityError, DegenerateMeshError
from jaxdeform.mesh.render import auto_camera, cast_rays
from jaxdeform.mesh.topology import build_topology
from jaxdeform.nn.graph_conv import rings_from_topology


def _grid(n=6):
    return grid_mesh(n)


@pytest.fixture(scope="module")
def setup():
    pts, faces = _grid()
    rings = rings_from_topology(build_topology(faces, len(pts)))
    config = model.Config(kz=(3, 2), d=(0.4, 0.2))
    return pts, faces, rings, config, _random_params(config, len(pts))


def _random_params(config, n_vertices, seed=0):
    """A :class:`model.Model` whose arrays are redrawn in numpy (larger than the initial draws), float64."""
    rng = np.random.default_rng(seed)
    m = model.Model(n_vertices, config, key=jax.random.PRNGKey(0), dtype=jnp.float64)

    def conv(c, n):
        c.W_point.set_value(jnp.asarray(rng.normal(scale=0.3, size=(n, 9, 9))))
        c.W_neighbor.set_value(jnp.asarray(rng.normal(scale=0.3, size=(n, 9, 9))))
        c.b.set_value(jnp.asarray(rng.normal(scale=0.1, size=(n, 9))))

    for level, kz in enumerate(config.kz):
        n = config.blocks(level)
        block = m.levels[level]
        conv(block.conv_enc, n)
        conv(block.conv_dec, n)
        block.C.set_value(jnp.asarray(rng.normal(scale=0.2, size=(n, kz, 9 * n_vertices))))
    return m


def _one_hot_latents(params, level, block, scale):
    """decode_latents codes: zero everywhere except block ``block`` of ``level``, row k = scale * e_k."""
    out = []
    kz_target = params.levels[level].C[...].shape[1]
    for lv, p in enumerate(params.levels):
        n, kz = p.C[...].shape[:2]
        z = np.zeros((n, kz_target, kz))
        if lv == level:
            z[block] = scale * np.eye(kz)
        out.append(jnp.asarray(z))
    return tuple(out)


# ------------------------------------------------------------------------------------------------ extraction


@pytest.mark.parametrize("level, block, scale", [(0, 0, 1.0), (0, 0, 5.0), (1, 2, 2.5), (1, 0, -1.0)])
def test_block_components_are_one_hot_decodes_minus_zero_code(setup, level, block, scale):
    pts, faces, rings, config, params = setup
    got = np.asarray(extract.block_components(params, rings, level, block, scale))
    one_hot = _one_hot_latents(params, level, block, scale)
    zeros = tuple(jnp.zeros_like(z) for z in one_hot)
    decode = jax.jit(lambda m, z, r: m.decode_latents(z, r))
    want = np.asarray(decode(params, one_hot, rings) - decode(params, zeros, rings))
    assert got.shape == (params.levels[level].C[...].shape[1], len(pts), 9)
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert np.abs(got).max() > 1e-6  # a random block does deform


def test_all_components_order_and_scaler(setup):
    pts, faces, rings, config, params = setup
    cs = extract.all_components(params, rings, scale=2.0)
    assert len(cs) == 3 + 3 * 2 and cs.domain == "scaled"
    assert list(cs.level) == [0, 0, 0, 1, 1, 1, 1, 1, 1]
    assert list(cs.block) == [0, 0, 0, 0, 0, 1, 1, 2, 2] and list(cs.index) == [0, 1, 2, 0, 1, 0, 1, 0, 1]
    np.testing.assert_allclose(cs.values[7:9], extract.block_components(params, rings, 1, 2, 2.0), atol=1e-12)
    assert cs.groups()[:4] == ["AE0", "AE0", "AE0", "AE1"] and cs.names()[-1] == "AE3 #1"
    # default magnitude: theta (5), the latent bound of V(Z)
    np.testing.assert_allclose(extract.all_components(params, rings).magnitude, config.theta)
    # unscaled: the affine Scaler's offset cancels, per-channel factors (hi - lo) / (2 * 0.95) remain
    scaler = Scaler(-1.0, 3.0, 0.5, 1.5)
    un = extract.all_components(params, rings, scale=2.0, scaler=scaler)
    factor = np.array([4.0] * 3 + [1.0] * 6) / 1.9
    assert un.domain == "acap"
    np.testing.assert_allclose(un.values, cs.values * factor, atol=1e-12)


def test_latent_extremes_follow_tan_et_al(setup):
    pts, faces, rings, config, params = setup
    rng = np.random.default_rng(3)
    latents = tuple(
        jnp.asarray(rng.normal(scale=2.0, size=(p.C[...].shape[0], 7, p.C[...].shape[1]))) for p in params.levels
    )
    cs = extract.all_components(params, rings, latents=latents)
    for lv, z in enumerate(latents):
        sel = cs.level == lv
        lo, hi = np.asarray(z).min(axis=1).ravel(), np.asarray(z).max(axis=1).ravel()
        mag = cs.magnitude[sel]
        assert np.all((mag == lo) | (mag == hi))
        for i, (b, k) in enumerate(zip(cs.block[sel], cs.index[sel])):
            other = hi[i] if mag[i] == lo[i] else lo[i]
            alt = np.asarray(extract.block_components(params, rings, lv, int(b), other))[k]
            assert np.sum(cs.values[sel][i] ** 2) >= np.sum(alt**2) - 1e-12
    # with a reference shape: its code is the base, one entry replaced
    ref = extract.all_components(params, rings, latents=latents, reference=4)
    base = np.asarray(latents[1][2, 4])
    k = 1
    s = ref.magnitude[(ref.level == 1) & (ref.block == 2)][k]
    want = np.asarray(extract.block_components(params, rings, 1, 2, s, base=base))[k]
    np.testing.assert_allclose(ref.values[(ref.level == 1) & (ref.block == 2)][k], want, atol=1e-12)
    with pytest.raises(ValueError, match="needs the training codes"):
        extract.all_components(params, rings, reference=0)


def test_bad_locations_raise(setup):
    pts, faces, rings, config, params = setup
    with pytest.raises(ValueError, match="level 2 does not exist"):
        extract.block_components(params, rings, 2, 0)
    with pytest.raises(ValueError, match="block 3 does not exist"):
        extract.block_components(params, rings, 1, 3)


# ------------------------------------------------------------------------------------------------- strength


def test_deformation_strength_eq7():
    v = 5
    d = np.zeros((4, v, 9))
    d[1, 0, 0], d[1, 2, 4] = 3.0, 4.0  # norms 3 and 4 on two vertices -> mean over moving vertices 3.5
    d[2] = d[1]
    d[2, 4, 8] = 1e-7  # below eps1: not counted
    d[3, :, 3] = 2.0  # every vertex moves by 2
    s = np.asarray(extract.deformation_strength(d))
    np.testing.assert_allclose(s, [0.0, 3.5, 3.5, 2.0])
    np.testing.assert_allclose(extract.vertex_strength(d)[1], [3, 0, 4, 0, 0])
    assert not np.asarray(extract.active_vertices(d))[2, 4]
    # homogeneous of degree one while no norm crosses eps1; the zero component stays zero
    np.testing.assert_allclose(extract.deformation_strength(2.5 * d[:2]), 2.5 * s[:2])
    # eps1 decides which vertices count
    np.testing.assert_allclose(extract.deformation_strength(d[1:2], eps1=3.5), [4.0])


# -------------------------------------------------------------------------------------------------- removal


def _linear_set(v=12, seed=0):
    rng = np.random.default_rng(seed)
    a = np.zeros((v, 3))
    a[:4] = rng.normal(size=(4, 3))
    b = np.zeros((v, 3))
    b[6:10] = rng.normal(size=(4, 3))
    weak = np.zeros((v, 3))
    weak[11, 0] = 0.005
    comps = np.stack([a, b, a, np.zeros((v, 3)), weak, -b, a + 0.3 * b])
    return extract.from_arrays(comps, "xyz", method="PCA")


def test_remove_redundant_drops_duplicates_and_slight_components():
    cs = _linear_set()
    r = extract.remove_redundant(cs)
    assert list(r.keep) == [True, True, False, False, False, False, True]
    assert r.kept == {(0, 0): (0, 1, 6)}
    assert set(r.removed) == {(0, 0, 2), (0, 0, 3), (0, 0, 4), (0, 0, 5)}
    assert r.removed[(0, 0, 2)].startswith("duplicate of PCA #0")
    assert r.removed[(0, 0, 5)].startswith("duplicate of PCA #1")  # a sign flip spans the same direction
    assert "slight deformation" in r.removed[(0, 0, 3)] and "< eps2 = 0.01" in r.removed[(0, 0, 4)]
    assert r.strength[3] == 0.0 and r.strength[4] == pytest.approx(0.005)
    # the paper's rule alone keeps duplicates; eps2 is the only threshold then
    paper = extract.remove_redundant(cs, duplicate_cos=None)
    assert paper.kept == {(0, 0): (0, 1, 2, 5, 6)}
    assert extract.remove_redundant(cs, eps2=0.001, duplicate_cos=None).kept == {(0, 0): (0, 1, 2, 4, 5, 6)}
    assert r.as_dict()["kept"] == {"0/0": [0, 1, 6]}


def test_removal_reports_every_block(setup):
    pts, faces, rings, config, params = setup
    params = jax.tree_util.tree_map(jnp.asarray, params)  # a copy (nnx Modules are pytrees)
    params.levels[1].C.set_value(params.levels[1].C[...].at[1].set(0.0))  # AE2 has no components at all
    cs = extract.all_components(params, rings, scaler=Scaler(-1.0, 1.0, 0.0, 2.0))
    r = extract.remove_redundant(cs)
    assert set(r.kept) == {(0, 0), (1, 0), (1, 1), (1, 2)}
    assert r.kept[(1, 1)] == () and "slight deformation" in r.removed[(1, 1, 0)]
    assert r.kept[(0, 0)] == (0, 1, 2)


def test_component_set_validation():
    with pytest.raises(DegenerateMeshError, match="NaN"):
        extract.from_arrays(np.full((2, 4, 3), np.nan), "xyz")
    with pytest.raises(ValueError, match="need 3 values per vertex"):
        extract.from_arrays(np.zeros((2, 4, 9)), "xyz")
    with pytest.raises(ValueError, match="'acap' or 'xyz'"):
        extract.from_arrays(np.zeros((2, 4, 9)), "scaled")


# ----------------------------------------------------------------------------------------------- similarity


def test_similarity_matrix_matches_numpy():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(5, 7, 9))
    x[3] = 0.0
    s = np.asarray(extract.similarity_matrix(x))
    flat = x.reshape(5, -1)
    norm = np.linalg.norm(flat, axis=1)
    ref = np.zeros((5, 5))
    nz = norm > 0
    ref[np.ix_(nz, nz)] = (flat[nz] @ flat[nz].T) / np.outer(norm[nz], norm[nz])
    np.fill_diagonal(ref, 1.0)
    np.testing.assert_allclose(s, ref, atol=1e-12)
    np.testing.assert_allclose(s, s.T)
    np.testing.assert_allclose(np.diag(s), 1.0)
    assert np.all(np.abs(s) <= 1.0)
    assert np.asarray(extract.similarity_matrix(np.stack([x[0], 2 * x[0], -x[0]])))[0, 1:] == pytest.approx([1, -1])


# ---------------------------------------------------------------------------------------------------- meshes


def test_component_meshes(setup):
    pts, faces, rings, config, params = setup
    rng = np.random.default_rng(2)
    disp = rng.normal(scale=0.01, size=(3, len(pts), 3))
    xyz = extract.from_arrays(disp, "xyz", weight=[1.0, 2.0, 0.0])
    want = pts + disp * np.array([1.0, 2.0, 0.0])[:, None, None]
    np.testing.assert_allclose(extract.component_meshes(xyz, pts, faces), want)
    # network components decode to finite meshes once unscaled; the zero ACAP difference is the reference
    cs = extract.all_components(params, rings, scale=0.5)
    scaler = Scaler(-0.5, 0.5, 0.8, 1.2)
    diffs = np.concatenate([np.zeros((1, len(pts), 9)), np.asarray(extract.unscale_values(cs.values, scaler))])
    meshes = extract.component_meshes(extract.from_arrays(diffs, "acap"), pts, faces)
    assert meshes.shape == (len(cs) + 1, len(pts), 3) and np.all(np.isfinite(meshes))
    np.testing.assert_allclose(meshes[0], pts, atol=1e-9)
    assert np.abs(meshes[1:] - pts).max() > 1e-4
    with pytest.raises(ValueError, match="need the Scaler"):
        extract.component_meshes(cs, pts, faces)
    with pytest.raises(ConnectivityError, match="vertices"):
        extract.component_meshes(xyz, pts[:-1], faces)


# --------------------------------------------------------------------------------------------------- figures


def _icosphere(subdiv=2):
    t = (1 + 5**0.5) / 2
    v = np.array(
        [
            [-1, t, 0],
            [1, t, 0],
            [-1, -t, 0],
            [1, -t, 0],
            [0, -1, t],
            [0, 1, t],
            [0, -1, -t],
            [0, 1, -t],
            [t, 0, -1],
            [t, 0, 1],
            [-t, 0, -1],
            [-t, 0, 1],
        ],
        float,
    )
    f = [
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ]
    verts, faces = list(v / np.linalg.norm(v, axis=1, keepdims=True)), np.array(f)
    for _ in range(subdiv):
        cache, new = {}, []
        for tri in faces:
            mids = []
            for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
                key = (min(a, b), max(a, b))
                if key not in cache:
                    m = verts[a] + verts[b]
                    verts.append(m / np.linalg.norm(m))
                    cache[key] = len(verts) - 1
                mids.append(cache[key])
            new += [[tri[0], mids[0], mids[2]], [tri[1], mids[1], mids[0]], [tri[2], mids[2], mids[1]], mids]
        faces = np.array(new)
    return np.array(verts), faces


@pytest.fixture(scope="module")
def sphere_set():
    v, f = _icosphere()
    bumps = [np.exp(-8 * np.sum((v - c) ** 2, axis=1)) for c in ([0, 0, 1], [1, 0, 0], [0, 1, 0], [0, -1, 0])]
    disp = np.stack([0.3 * b[:, None] * v for b in bumps])
    cs = extract.from_arrays(disp, "xyz", method="PCA")
    return v, f, cs


def test_components_figure_writes_png(tmp_path, sphere_set):
    v, f, cs = sphere_set
    meshes = extract.component_meshes(cs, v, f)
    strength = np.asarray(extract.vertex_strength(cs.values))
    path = tmp_path / "out" / "components.png"
    img = figures.components_figure(
        meshes,
        f,
        strength,
        path,
        groups=["AE0", "AE0", "AE1", "AE3"],
        rows=["AE0", "AE1", "AE2", "AE3"],
        panel=64,
        max_columns=3,
        title="components",
    )
    with Image.open(path) as im:
        assert im.format == "PNG" and im.size == (img.shape[1], img.shape[0]) and im.mode == "RGB"
    assert img.shape[1] >= 2 * 64 and img.shape[0] >= 4 * 64  # two columns, four rows (AE2 empty)
    # a panel: exact size, grey body where nothing moves, the colormap's top where the bump peaks
    cam = auto_camera(v, azimuth_deg=0.0, elevation_deg=0.0)
    panel = figures.render_component(meshes[0], f, strength[0], cam, 48, 40)
    assert panel.shape == (40, 48, 3) and panel.dtype == np.uint8
    centre = panel[18:22, 22:26].reshape(-1, 3).astype(float)
    assert np.all(centre[:, 2] < centre[:, 0])  # viridis' yellow at the peak (blue channel lowest)


def test_component_set_figure_with_removal(tmp_path, sphere_set):
    v, f, cs = sphere_set
    doubled = extract.from_arrays(np.concatenate([cs.values, cs.values[:1]]), "xyz", method="PCA")
    r = extract.remove_redundant(doubled)
    assert not r.keep[-1]
    meshes = extract.component_meshes(doubled, v, f)
    img = figures.component_set_figure(doubled, meshes, f, tmp_path / "set.png", removal=r, panel=48)
    with Image.open(tmp_path / "set.png") as im:
        assert im.size == (img.shape[1], img.shape[0])


def test_each_panel_framed_to_fill_it(sphere_set):
    # an ellipsoid long along x and two copies 10x its size: with frame="each" all fill their panels alike, with
    # one shared camera the small one is a dot; azimuth 0 faces the first mesh's broad side (it looks along z)
    v, f, _ = sphere_set
    small = v * np.array([3.0, 1.0, 1.0])
    x = np.stack([small, 10.0 * small, 10.0 * small + 1.0])
    each = figures._panel_cameras(x, f, "front", "y", None, "each")
    shared = figures._panel_cameras(x, f, "front", "y", None, "shared")
    assert abs(each[0].basis()[0] @ np.array([0.0, 0.0, 1.0])) > 0.98

    def filled(cam, m):
        return cast_rays(m, f, cam, 64, 64).hit.mean()

    fills = [filled(c, m) for c, m in zip(each, x)]
    np.testing.assert_allclose(fills, fills[0], rtol=0.05)
    assert fills[0] > 0.2
    assert filled(shared[0], x[0]) < 0.1 * fills[0]
    turned = figures._panel_cameras(x[:, :, [2, 1, 0]], f, "front", "y", None, "each")
    assert abs(turned[0].basis()[0] @ np.array([1.0, 0.0, 0.0])) > 0.98  # long along z: looks along x
    with pytest.raises(ValueError, match="frame must be"):
        figures._panel_cameras(x, f, "front", "y", None, "tight")
    with pytest.raises(ValueError, match="up_axis"):
        figures._panel_cameras(x, f, "front", "x", None, "each")


def test_similarity_figure(tmp_path, sphere_set):
    v, f, cs = sphere_set
    s = np.asarray(extract.similarity_matrix(cs.values))
    path = tmp_path / "sim.png"
    img = figures.similarity_figure(s, path, labels=cs.names(), cell=20)
    with Image.open(path) as im:
        assert im.format == "PNG" and im.size == (img.shape[1], img.shape[0])
    assert img.shape[0] > 4 * 20 and img.shape[1] > 4 * 20
    signed = figures.similarity_figure(np.array([[1.0, -0.5], [-0.5, 1.0]]), tmp_path / "signed.png")
    assert signed.ndim == 3


def test_invalid_inputs_write_nothing(tmp_path, sphere_set):
    v, f, cs = sphere_set
    meshes = extract.component_meshes(cs, v, f)
    strength = np.asarray(extract.vertex_strength(cs.values))
    bad = meshes.copy()
    bad[1, 5, 0] = np.nan
    path = tmp_path / "c.png"
    with pytest.raises(DegenerateMeshError, match="component mesh 1"):
        figures.components_figure(bad, f, strength, path)
    bad_s = strength.copy()
    bad_s[2, 0] = np.inf
    with pytest.raises(DegenerateMeshError, match="strength of component 2"):
        figures.components_figure(meshes, f, bad_s, path)
    with pytest.raises(ValueError, match="rows not listed"):
        figures.components_figure(meshes, f, strength, path, groups=["a", "a", "b", "b"], rows=["a"])
    with pytest.raises(DegenerateMeshError, match="NaN"):
        figures.similarity_figure(np.array([[1.0, np.nan], [np.nan, 1.0]]), tmp_path / "s.png")
    with pytest.raises(ValueError, match=r"\[-1, 1\]"):
        figures.similarity_figure(np.array([[1.0, 2.0], [2.0, 1.0]]), tmp_path / "s.png")
    with pytest.raises(ValueError, match="square"):
        figures.similarity_figure(np.ones((2, 3)), tmp_path / "s.png")
    assert list(tmp_path.iterdir()) == []  # no file, no temporary left behind


def test_figure_camera_frames_typical_meshes_not_an_outlier():
    cube = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    meshes = np.stack([cube, cube + 0.1, cube * 1.2, cube * 10.0])  # the last one is a wild component
    framed = figures._framed_points(meshes)
    assert framed.shape == (24, 3) and framed.max() == pytest.approx(1.2)
    same = np.stack([cube, cube * 1.1])  # nothing to drop
    assert figures._framed_points(same).shape == (16, 3)


@pytest.mark.parametrize("option", [{"tie_conv": True}, {"decoder_tanh": False}])
def test_all_components_refuses_a_variant_decoder(setup, option):
    """Components are one-hot decodes of the default block: a variant decoder is refused, not silently replaced."""
    import dataclasses

    config = dataclasses.replace(model.Config(kz=(2,), d=(0.4,)), **option)
    with pytest.raises(ValueError, match="default decoder"):
        extract.all_components(model.Model(3, config, key=jax.random.PRNGKey(0)), None)
