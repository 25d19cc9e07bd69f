"""Cloth dataset files, representations (TS-ACAP / ACAP / coordinates), collision refinement and errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxdeform.cloth import data as cdata
from jaxdeform.cloth import evaluate as ceval
from jaxdeform.cloth import features as cfeat
from jaxdeform.cloth import obstacles as obst
from jaxdeform.cloth.refine import Refiner
from jaxdeform.errors import ConnectivityError, MeshFormatError

igl = pytest.importorskip("igl")


def grid(n: int = 5, size: float = 1.0):
    x, z = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n))
    v = np.c_[x.ravel(), np.zeros(n * n), z.ravel()]
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            f += [[a, a + n, a + 1], [a + 1, a + n, a + n + 1]]
    return v, np.array(f, np.int64)


def pair(t=4, n=5, seed=0, fine_frames=None):
    rng = np.random.default_rng(seed)
    cv, cf = grid(n)
    fv, ff = igl.loop(cv, cf)
    return {
        "coarse": cv[None] + 0.01 * rng.standard_normal((t, len(cv), 3)),
        "fine": fv[None] + 0.01 * rng.standard_normal((fine_frames or t, len(fv), 3)),
        "coarse_rest": cv,
        "fine_rest": fv,
        "coarse_faces": cf,
        "fine_faces": ff,
        "obstacles": obst.to_dict(obst.static_track(obst.make(spheres=[((0, 0, 0), 0.2)]), t)),
        "meta": {"kind": "sheet", "index": seed},
    }


def write(tmp_path, pairs):
    names = []
    for i, p in enumerate(pairs):
        names.append(f"seq_{i:03d}.npz")
        cdata.write_sequence(tmp_path / names[-1], p)
    cdata.write_index(tmp_path, "sheet", names)
    return names


def test_dataset_round_trip_and_split(tmp_path):
    pairs = [pair(seed=s) for s in range(5)]
    names = write(tmp_path, pairs)
    ds = cdata.load_dataset(tmp_path)
    assert [s.name for s in ds.sequences] == names
    assert ds.split == {"train": names[:2] + names[3:], "test": [names[2]]}  # every 5th from the 3rd
    assert [s.name for s in ds.subset("test")] == [names[2]]
    np.testing.assert_array_equal(ds.sequences[2].coarse, pairs[2]["coarse"].astype(np.float32))
    np.testing.assert_array_equal(ds.fine_faces, pairs[0]["fine_faces"])
    assert ds.sequences[3].meta == {"kind": "sheet", "index": 3}
    assert ds.sequences[0].obstacles["sphere_r"].shape == (4, 1)
    assert json.loads((tmp_path / "dataset.json").read_text())["format"] == cdata.FORMAT


def test_default_split_interleaves_and_never_takes_all():
    names = [f"s{i}" for i in range(12)]
    split = cdata.default_split(names)
    assert split["test"] == ["s2", "s7"] and sorted(split["train"] + split["test"]) == sorted(names)
    assert cdata.default_split(names[:2]) == {"train": ["s0"], "test": ["s1"]}  # no index 2: the last one
    assert cdata.default_split(names[:1]) == {"train": ["s0"], "test": []}


def test_dataset_refuses_unequal_lengths(tmp_path):
    write(tmp_path, [pair(), pair(fine_frames=3)])
    with pytest.raises(ConnectivityError, match="3 fine frames; coarse and fine sequences must have equal lengths"):
        cdata.load_dataset(tmp_path)


def test_dataset_refuses_other_connectivity(tmp_path):
    write(tmp_path, [pair(n=5), pair(n=6)])
    with pytest.raises(ConnectivityError, match="must share one connectivity"):
        cdata.load_dataset(tmp_path)


def test_dataset_refuses_nan_and_truncated_files(tmp_path):
    p = pair()
    p["fine"][1, 3, 0] = np.nan
    write(tmp_path, [p])
    with pytest.raises(MeshFormatError, match="NaN"):
        cdata.load_dataset(tmp_path)
    raw = (tmp_path / "seq_000.npz").read_bytes()
    (tmp_path / "seq_000.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(MeshFormatError, match="not a readable .npz"):
        cdata.load_dataset(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(MeshFormatError, match="no cloth sequences"):
        cdata.load_dataset(empty)


def test_obstacle_tracks_without_rims_read_as_sharp_and_bad_rims_are_refused(tmp_path):
    p = pair()
    p["obstacles"] = obst.to_dict(obst.static_track(obst.make(cylinders=[((0, 1, 0), 0.5, 1.0)]), 4))
    del p["obstacles"]["cylinder_rounding"]  # a file written before the rounded rims
    write(tmp_path, [p])
    track = cdata.load_dataset(tmp_path).sequences[0].obstacles
    assert track["cylinder_rounding"].shape == (4, 1) and not track["cylinder_rounding"].any()
    p["obstacles"]["cylinder_rounding"] = np.full((4, 1), 0.6, np.float32)  # wider than the radius
    write(tmp_path, [p])
    with pytest.raises(MeshFormatError, match="rim radius"):
        cdata.load_dataset(tmp_path)


def test_upsampler_is_libigl_loop_and_reaches_sheet_resolution():
    cv, cf = grid(9)
    fv, ff = cv, cf
    for _ in range(3):
        fv, ff = igl.loop(fv, ff)
    assert fv.shape[0] == 4225  # 65 x 65, the paper's fine SHEET
    up = ceval.Upsampler(cf, len(cv), ff)
    rng = np.random.default_rng(1)
    frames = cv[None] + 0.05 * rng.standard_normal((3, len(cv), 3))
    out = up(frames)
    for k in range(3):
        g, gf = frames[k], cf
        for _ in range(3):
            g, gf = igl.loop(g, gf)
        np.testing.assert_allclose(out[k], g, atol=1e-5)
    with pytest.raises(ValueError, match="does not give the fine connectivity"):
        ceval.Upsampler(cf, len(cv), grid(6)[1])


def test_linear_residual_recovers_a_linear_detail_and_falls_back_to_the_mean():
    """Fine = Loop(coarse) + an affine function of the coarse frame (rank 3): the closed-form reference recovers
    it on unseen frames; with a detail that ignores the coarse frame it predicts the training mean."""
    cv, cf = grid(5)
    fv, ff = igl.loop(cv, cf)
    up = ceval.Upsampler(cf, len(cv), ff)
    rng = np.random.default_rng(3)
    basis = rng.standard_normal((3, len(fv) * 3)) * 0.01
    probe = rng.standard_normal((len(cv) * 3, 3))

    def seq(n, detail):
        c = cv[None] + 0.05 * rng.standard_normal((n, len(cv), 3))
        return c, up(c) + detail(c).reshape(n, -1, 3)

    linear = lambda c: 0.002 + (c.reshape(len(c), -1) @ probe) @ basis  # noqa: E731
    train = [seq(30, linear) for _ in range(8)]
    ref = ceval.LinearResidual(up, [c for c, _ in train], [f for _, f in train], k=8)
    c, f = seq(10, linear)
    assert np.sqrt(np.mean((ref(c) - f) ** 2)) < 0.02 * np.sqrt(np.mean((up(c) - f) ** 2))
    const = rng.standard_normal((1, len(fv) * 3)) * 0.01
    train = [seq(30, lambda c: np.repeat(const, len(c), 0)) for _ in range(8)]
    ref = ceval.LinearResidual(up, [c for c, _ in train], [f for _, f in train], k=8)
    c, f = seq(10, lambda c: np.repeat(const, len(c), 0))
    np.testing.assert_allclose(ref(c), f, atol=1e-4)


def test_coarse_level_split_is_the_orthogonal_projection_onto_upsampled_offsets():
    cv, cf = grid(5)
    fv, ff = igl.loop(cv, cf)
    up = ceval.Upsampler(cf, len(cv), ff)
    u = up.matrix.toarray()
    rng = np.random.default_rng(4)
    coarse_offsets = rng.standard_normal((4, len(cv), 3))
    low, high = ceval.coarse_level_split(up, up(coarse_offsets))  # already at the coarse scale: all of it is "low"
    np.testing.assert_allclose(low, up(coarse_offsets), atol=1e-5)
    np.testing.assert_allclose(high, 0.0, atol=1e-5)
    d = rng.standard_normal((4, len(fv), 3))
    low, high = ceval.coarse_level_split(up, d)
    np.testing.assert_allclose(low + high, d, atol=1e-12)
    np.testing.assert_allclose(np.einsum("vc,tvk->tck", u, high), 0.0, atol=1e-9)  # orthogonal to every column of U
    again, rest = ceval.coarse_level_split(up, low)  # a projection: applying it twice changes nothing
    np.testing.assert_allclose(again, low, atol=1e-9)
    np.testing.assert_allclose(rest, 0.0, atol=1e-9)
    with pytest.raises(ValueError, match="offsets must be"):
        ceval.coarse_level_split(up, d[:, :-1])


def test_dihedral_angles_of_a_folded_sheet():
    """A flat grid bends nowhere; folded by phi along the line x = 0.5 its hinges on that line bend by phi, the rest
    by 0; every interior edge has one hinge."""
    v, f = grid(5)
    h = ceval.hinge_faces(f)
    edges = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
    boundary = 4 * 4  # a 5 x 5 grid has 16 boundary edges
    assert len(h) == len(edges) - boundary
    np.testing.assert_allclose(ceval.dihedral_angles(v[None], f), 0.0, atol=1e-7)
    phi = 0.7
    folded = v.copy()
    right = v[:, 0] > 0.5
    dx = v[right, 0] - 0.5
    folded[right, 0] = 0.5 + dx * np.cos(phi)
    folded[right, 1] = dx * np.sin(phi)
    ang = ceval.dihedral_angles(folded[None], f, h)[0]
    shared = [len(set(f[a]) & set(f[b]) & set(np.flatnonzero(np.isclose(v[:, 0], 0.5)))) == 2 for a, b in h]
    np.testing.assert_allclose(ang[np.array(shared)], phi, atol=1e-9)
    np.testing.assert_allclose(ang[~np.array(shared)], 0.0, atol=1e-7)
    assert np.sum(shared) == 4  # the four grid edges on the fold line


def test_detail_errors_identities():
    """Zero against itself and under a rigid motion; the Loop-upsampled coarse cloth has no fine-scale part, so
    its detail error is the reference's whole fine-scale part."""
    from scipy.spatial.transform import Rotation

    cv, cf = grid(5)
    fv, ff = igl.loop(cv, cf)
    up = ceval.Upsampler(cf, len(cv), ff)
    rng = np.random.default_rng(7)
    fine = fv[None] + 0.02 * rng.standard_normal((3, len(fv), 3))
    same = ceval.detail_errors(fine, fine, ff, up)
    assert same["dihedral_w1"] == 0.0 and same["fine_scale_rmse"] == 0.0 and same["fine_scale_rms_ref"] > 0.005
    r = Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix()
    moved = ceval.detail_errors(fine, fine @ r.T + [0.5, -2.0, 1.0], ff, up)
    assert moved["dihedral_w1"] < 1e-9
    assert moved["fine_scale_rms"] == pytest.approx(same["fine_scale_rms_ref"], rel=1e-9)
    coarse = cv[None] + 0.02 * rng.standard_normal((3, len(cv), 3))
    smooth = ceval.detail_errors(fine, up(coarse), ff, up)
    assert smooth["fine_scale_rms"] < 1e-6
    assert smooth["fine_scale_rmse"] == pytest.approx(smooth["fine_scale_rms_ref"], rel=1e-4)
    assert smooth["dihedral_w1"] > 0.05  # the noisy reference bends much more than the smooth subdivision
    pooled = ceval.pool_details([same, smooth])
    assert pooled["frames"] == 6 and pooled["sequences"] == 2
    assert pooled["fine_scale_rmse"] == pytest.approx(smooth["fine_scale_rmse"] / np.sqrt(2), rel=1e-9)
    with pytest.raises(ValueError, match="shapes differ"):
        ceval.detail_errors(fine, fine[:2], ff, up)


def test_errors_analytic():
    cv, cf = grid(5)
    rng = np.random.default_rng(2)
    ref = cv[None] + 0.01 * rng.standard_normal((6, len(cv), 3))
    same = ceval.sequence_errors(ref, ref, cf)
    assert same["rmse"] == 0.0 and same["hausdorff"] == 0.0 and same["sted"] == 0.0
    off = np.array([0.03, -0.04, 0.0])  # |off| = 0.05
    moved = ceval.sequence_errors(ref, ref + off, cf)
    assert moved["rmse"] == pytest.approx(0.05, rel=1e-9)
    assert moved["sted"] == pytest.approx(0.0, abs=1e-12)  # translation: no edge or temporal-edge change
    a = ceval.sequence_errors(ref[:2], ref[:2] + off, cf)
    b = ceval.sequence_errors(ref[2:], ref[2:] + 2 * off, cf)
    pooled = ceval.pool([a, b])
    assert pooled["rmse"] == pytest.approx(np.sqrt((2 * 0.05**2 + 4 * 0.1**2) / 6), rel=1e-9)
    pairs = [(ref[:2], ref[:2] + off), (ref[2:], ref[2:] + 2 * off)]
    assert ceval.pooled_rmse(pairs) == pytest.approx(pooled["rmse"], rel=1e-12)
    with pytest.raises(ValueError):
        ceval.pooled_rmse([])
    with pytest.raises(ValueError):
        ceval.pooled_rmse([(ref, ref[:, :1])])  # no silent broadcasting


def rotating_grid(frames=24):
    v, f = grid(6)
    v = v - v.mean(axis=0)
    out = []
    for t in range(frames):
        a = 1.6 * np.pi * t / (frames - 1)  # a rigid turn about y past pi (not near 2 pi, where any axis-angle
        # unwrapping of a tilted axis is ill-posed)
        r = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        bend = 0.1 * np.sin(np.pi * v[:, 0])[:, None] * np.array([0, 1, 0])
        out.append((v + bend) @ r.T)
    return v, f, np.array(out)


def test_ts_acap_is_smooth_where_acap_jumps():
    v, f, frames = rotating_grid()
    ts = cfeat.encode_sequence("ts-acap", v, f, frames)
    sp = cfeat.encode_sequence("acap", v, f, frames)
    step = 1.6 * np.pi / 23
    assert cfeat.largest_frame_change(ts) < 2.5 * step
    assert cfeat.largest_frame_change(sp) > 4.0  # the angle wraps from ~pi to ~-pi (a 2 pi jump)
    st_ts, st_sp = cfeat.frame_change_stats([ts]), cfeat.frame_change_stats([sp])
    assert st_ts["fraction_above_pi"] == 0.0 and st_sp["fraction_above_pi"] > 0.0
    assert st_sp["max"] == pytest.approx(cfeat.largest_frame_change(sp)) and st_ts["count"] == 23 * len(v)
    np.testing.assert_allclose(cfeat.encode_sequence("coords", v, f, frames), frames.astype(np.float32))


def test_scaling_round_trip_and_decode_fine():
    v, f, frames = rotating_grid(8)
    for kind in cfeat.KINDS:
        raw = cfeat.encode_sequence(kind, v, f, frames)
        sc = cfeat.Scaling.fit(kind, [raw], mode="minmax")
        x = sc.transform(raw)
        assert np.abs(x).max() <= cfeat.LIMIT + 1e-6
        np.testing.assert_allclose(sc.inverse(x), raw, atol=1e-5)
        st = cfeat.Scaling.fit(kind, [raw])  # mean -+ 3 std -> -+0.95, clipped at -+1
        y = st.transform(raw)
        assert np.abs(y).max() <= 1.0
        np.testing.assert_allclose(y.reshape(-1, y.shape[-1]).std(axis=0), cfeat.LIMIT / cfeat.STD_RANGE, rtol=0.2)
        inside = np.abs(y) < 1.0
        np.testing.assert_allclose(st.inverse(y)[inside], raw[inside], atol=1e-5)
    sc = cfeat.Scaling.fit("ts-acap", [cfeat.encode_sequence("ts-acap", v, f, frames)], mode="minmax")
    rep = cfeat.Representation("ts-acap", v, f, v, f, sc, sc)
    scaled = rep.encode("fine", frames)
    back = rep.decode_fine(scaled, frames)  # "coarse" = the frames themselves: the centroid placement is exact
    scale = np.ptp(v, axis=0).max()
    assert np.abs(back - frames).max() < 5e-3 * scale  # ACAP least squares on a 6x6 grid, bent


def sphere_sdf(c, r):
    def sdf(x):
        d = x - c
        n = np.linalg.norm(d, axis=-1)
        return n - r, d / n[:, None]

    return sdf


@pytest.mark.parametrize("exact", [True, False])
def test_refinement_pushes_out_and_keeps_detail(exact):
    v, f = grid(17, 1.0)
    n = len(v)
    rng = np.random.default_rng(3)
    p0 = v + 0.002 * rng.standard_normal(v.shape)  # detail to keep
    ref = Refiner(f, n, exact=exact)
    c, r = np.array([0.5, -0.25, 0.5]), 0.3  # pokes 5 cm up through the sheet's middle
    sdf = sphere_sdf(c, r)
    p, st = ref(p0, sdf, margin=0.005)
    d, _ = sdf(p)
    assert st.collided > 0 and st.max_depth_before > 0.05 - 0.01
    assert d.min() > -1e-3  # outside up to a millimetre after at most 3 iterations
    if exact:  # the first iteration's vertices sit on their targets: the margin off the sphere
        inside = sdf(p0)[0] < 0
        np.testing.assert_allclose(d[inside], 0.005, atol=1e-9)
    far = np.linalg.norm(v - c, axis=1) > 0.6
    assert np.abs(p[far] - p0[far]).max() < 0.25 * np.abs(p - p0).max()  # the push is local
    # detail: the Laplacian of the displacement is small compared to the detail itself
    from jaxdeform.cloth.refine import uniform_laplacian

    lap = uniform_laplacian(f, n)
    assert np.abs(lap @ (p - p0)).mean() < 0.5 * np.abs(lap @ (p0 - v)).mean()
    # a frame without collisions comes back unchanged
    q, st2 = ref(p0, sphere_sdf(np.array([0.5, -2.0, 0.5]), 0.3), margin=0.005)
    assert st2.iterations == 0 and np.array_equal(q, p0)


def hinged_grid(frames=6):
    """A 6x6 grid folding about its x = 0 column, which stays where it is (the pinned vertices)."""
    v, f = grid(6)
    out = []
    for t in range(frames):
        a = 0.3 * np.pi * t / (frames - 1)
        x = v[:, 0] * (0.3 + 0.7 * np.cos(a * v[:, 0]))
        y = v[:, 0] * np.sin(a * v[:, 0])
        out.append(np.c_[x, y, v[:, 2]])
    return v, f, np.array(out), np.flatnonzero(v[:, 0] == 0)


def test_position_term_vanishes_on_the_fine_features_and_has_exact_gradients():
    import jax
    import jax.numpy as jnp

    from jaxdeform.acap import features as acapf
    from jaxdeform.cloth import train as ctrain

    v, f, frames, pins = hinged_grid()
    edge = np.mean(np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1))
    rows = jnp.arange(1, len(frames) + 1)  # frame k sits at row k + 1 (a zero row precedes the sequence)
    for kind in ("ts-acap", "coords"):
        raw = cfeat.encode_sequence(kind, v, f, frames)
        sc = cfeat.Scaling.fit(kind, [raw])
        x = jnp.asarray(sc.transform(raw))
        rec = None if kind == "coords" else acapf.cached(v, f).reconstructor(pins)
        pos = ctrain.PositionTarget.build(
            [frames], None, sc.lo, sc.hi, rec, None if rec is None else frames[0][pins], edge
        )
        err = float(ctrain.position_error(pos, x, rows))
        assert err < (2.5e-3 if kind == "ts-acap" else 1e-10), (kind, err)  # plain least-squares round trip, edges^2
        d = 0.2 * jax.random.normal(jax.random.PRNGKey(1), x.shape)
        assert float(ctrain.position_error(pos, x + d, rows)) > 10 * err + 1e-4
        # implicit differentiation through the anchored solve against central differences
        g = jax.grad(lambda y: ctrain.position_error(pos, y, rows))(x + d)
        h = 1e-2
        fd = (ctrain.position_error(pos, x + d + h * d, rows) - ctrain.position_error(pos, x + d - h * d, rows)) / (
            2 * h
        )
        assert float(jnp.sum(g * d)) == pytest.approx(float(fd), rel=2e-2)
    # a residual target adds its base before decoding: base = the features, residual 0 -> the same positions
    raw = cfeat.encode_sequence("ts-acap", v, f, frames)
    sc = cfeat.Scaling(-np.ones(9), np.ones(9))
    zero = jnp.asarray(sc.transform(np.zeros_like(raw)))
    rec = acapf.cached(v, f).reconstructor(pins)
    pos = ctrain.PositionTarget.build([frames], [raw], sc.lo, sc.hi, rec, frames[0][pins], edge)
    assert float(ctrain.position_error(pos, zero, rows)) < 2.5e-3
