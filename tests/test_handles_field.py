"""Seed 004 feature field: bilinear patch upsampling, the field, barycentric distillation (eq. 3), persistence."""

import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from scipy.ndimage import map_coordinates

from jaxdeform.errors import JaxDeformError
from jaxdeform.handles import field as fieldmod
from jaxdeform.handles.field import (
    FieldConfig,
    distill,
    evaluate_field,
    load_field,
    new_field,
    sample_pixel_features,
    save_field,
)
from jaxdeform.handles.views import fibonacci_cameras, render_views

C = 16


# ------------------------------------------------------------------------------------------ upsampling


def reference_bilinear(patch, view, yx, hw):
    """Per channel scipy ``map_coordinates`` (order 1, edge replication) at patch coords y h / H - 1/2."""
    n, h, w, c = patch.shape
    a = yx[:, 0] * h / hw[0] - 0.5
    b = yx[:, 1] * w / hw[1] - 0.5
    out = np.empty((yx.shape[0], c))
    for k in range(n):
        sel = view == k
        for ch in range(c):
            out[sel, ch] = map_coordinates(patch[k, :, :, ch], [a[sel], b[sel]], order=1, mode="nearest")
    return out


@pytest.mark.parametrize("grid,image", [((5, 7), (40, 63)), ((16, 16), (512, 512))])
def test_sample_pixel_features_matches_numpy_bilinear(grid, image):
    rng = np.random.default_rng(1)
    patch = rng.normal(size=(3, *grid, 6)).astype(np.float32)
    p = 2000
    view = rng.integers(0, 3, p).astype(np.int32)
    yx = rng.uniform(0.0, 1.0, (p, 2)) * image  # the whole image, borders included (edge clamp)
    fn = jax.jit(sample_pixel_features, static_argnums=3)
    got = np.asarray(fn(jnp.asarray(patch), jnp.asarray(view), jnp.asarray(yx, jnp.float32), image))
    np.testing.assert_allclose(got, reference_bilinear(patch.astype(np.float64), view, yx, image), atol=2e-5)
    # at patch centres ((a + 1/2) H / h, (b + 1/2) W / w) the patch value itself is returned
    a, b = np.meshgrid(np.arange(grid[0]), np.arange(grid[1]), indexing="ij")
    centres = np.stack([(a.ravel() + 0.5) * image[0] / grid[0], (b.ravel() + 0.5) * image[1] / grid[1]], axis=1)
    for k in range(3):
        vals = sample_pixel_features(jnp.asarray(patch), jnp.full(centres.shape[0], k), jnp.asarray(centres), image)
        np.testing.assert_allclose(np.asarray(vals), patch[k].reshape(-1, 6), atol=1e-5)
    # beyond the outer patch centres the value is constant (clamped), e.g. in the image corner
    near_origin = jnp.asarray([[0.0, 0.0], [0.2, 0.1]])
    corner = sample_pixel_features(jnp.asarray(patch), jnp.zeros(2, jnp.int32), near_origin, image)
    np.testing.assert_allclose(np.asarray(corner), patch[0, 0, 0][None].repeat(2, 0), atol=1e-6)


# ------------------------------------------------------------------------------------------ the field


def test_field_outputs_unit_vectors_and_is_scale_free():
    cfg = FieldConfig(hidden=32, fourier_features=8)
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([1.0, 3.0, 2.5])
    fld = new_field(C, lo, hi, cfg)
    x = np.random.default_rng(0).normal(size=(500, 3)) * 5.0  # inside and far outside the box
    z = evaluate_field(fld, x)
    assert z.shape == (500, C) and z.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(z, axis=1), 1.0, atol=1e-5)
    assert np.abs(z[0] - z[1]).max() > 1e-3  # not a constant
    # same parameters, box scaled and moved with the points: same features
    s, t = 7.5, np.array([10.0, -4.0, 3.0])
    moved = new_field(C, lo * s + t, hi * s + t, cfg)
    np.testing.assert_allclose(evaluate_field(moved, x * s + t), z, atol=2e-4)  # float32, Fourier phases up to ~500
    # the direct module call agrees with the chunked, jitted evaluation
    np.testing.assert_allclose(np.asarray(fld(jnp.asarray(x, jnp.float32))), z, atol=1e-5)
    # App. J architecture: 4 hidden Linear -> ReLU -> LayerNorm of width 256, linear output to C
    default = new_field(384, lo, hi)
    assert len(default.hidden) == len(default.norms) == 4
    assert default.hidden[0].kernel.shape == (3, 256) and default.out.kernel.shape == (256, 384)


def test_evaluate_field_chunks_and_large_inputs():
    fld = new_field(C, np.zeros(3), np.ones(3), FieldConfig(hidden=16, layers=2))
    x = np.random.default_rng(2).uniform(size=(1000, 3))
    full = evaluate_field(fld, x, batch=4096)
    np.testing.assert_allclose(evaluate_field(fld, x, batch=300), full, atol=1e-6)  # uneven last chunk
    big = np.random.default_rng(3).uniform(size=(600_000, 3)).astype(np.float32)
    out = evaluate_field(fld, big)
    assert out.shape == (600_000, C) and np.all(np.isfinite(out))
    np.testing.assert_allclose(out[-1000:], evaluate_field(fld, big[-1000:]), atol=1e-6)
    assert evaluate_field(fld, np.zeros((0, 3))).shape == (0, C)


# ------------------------------------------------------------------------------------------ distillation


def analytic_features(points, centre):
    """A smooth, non-linear map R^3 -> R^C (random two-layer net), the 'backbone' of the test."""
    rng = np.random.default_rng(7)
    a, b, m = rng.normal(size=(3, 8)), rng.normal(size=8), rng.normal(size=(8, C))
    return np.tanh((np.asarray(points, np.float64) - centre) @ a * 1.5 + b) @ m


@pytest.fixture(scope="module")
def analytic_views():
    """A capsule seen from 24 views at 48 x 48, with a patch grid = the pixel grid holding the analytic features
    at every covered pixel's surface point (so the upsampled target of a pixel is exactly Z(P_ij))."""
    m = trimesh.creation.capsule(height=1.0, radius=0.4, count=[16, 16])
    v, f = np.asarray(m.vertices) * 3.0 + [1.0, -2.0, 0.5], np.asarray(m.faces)
    centre = v.mean(axis=0)
    views = render_views(v, f, fibonacci_cameras(v, 24), 48, progress=False)
    cov = views.covered()
    patch = np.zeros((24, 48, 48, C), np.float32)
    i, j = (cov.pixel_yx - 0.5).astype(int).T
    patch[cov.view, i, j] = analytic_features(cov.points, centre)
    return v, f, centre, cov, patch


def test_distill_analytic_features(analytic_views):
    v, f, centre, cov, patch = analytic_views
    cfg = FieldConfig(steps=300, batch_size=512, seed=3, jitter=0.0)  # plain eq. (3), on the surface only
    before = fieldmod.TRACE_COUNT["train_step"]
    fld, hist = distill(
        cov.points, cov.view, cov.pixel_yx, patch, (48, 48), cfg, progress=False, bbox=(v.min(axis=0), v.max(axis=0))
    )
    assert fieldmod.TRACE_COUNT["train_step"] - before <= 1  # one trace for all 300 steps
    assert hist.loss.shape == (300,) and hist.seconds > 0
    assert hist.loss[:10].mean() > 0.3 and hist.loss[-50:].mean() < 0.01
    # the learned field reproduces the analytic features at the mesh vertices (not the training pixels)
    z = analytic_features(v, centre)
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    cos = np.sum(evaluate_field(fld, v) * z, axis=1)
    assert cos.mean() > 0.99 and cos.min() > 0.95
    # the full eq. (3) loss over all covered pixels, divided by |Omega|, is what the minibatches estimated
    zp = analytic_features(cov.points, centre)
    zp /= np.linalg.norm(zp, axis=1, keepdims=True)
    full = np.mean(np.sum((evaluate_field(fld, cov.points) - zp) ** 2, axis=1))
    assert full < 0.01


def test_jitter_is_checked_and_changes_only_the_samples(analytic_views):
    """The jitter offsets the sampled points (same pixel draws, same targets): 0 reproduces plain eq. (3)."""
    v, f, centre, cov, patch = analytic_views
    with pytest.raises(ValueError, match="jitter"):
        FieldConfig(jitter=-0.1)
    runs = {
        j: distill(
            cov.points,
            cov.view,
            cov.pixel_yx,
            patch,
            (48, 48),
            FieldConfig(hidden=32, steps=5, batch_size=256, seed=2, jitter=j),
            progress=False,
        )[1].loss
        for j in (0.0, 0.0, 0.05)
    }
    assert runs[0.0][0] == pytest.approx(runs[0.05][0], rel=0.2)  # step 0: same draws, slightly moved points
    assert not np.array_equal(runs[0.0], runs[0.05])


def test_distill_deterministic_and_compiled_once(analytic_views):
    v, f, centre, cov, patch = analytic_views
    cfg = FieldConfig(hidden=32, steps=20, batch_size=256, seed=11)
    a, ha = distill(cov.points, cov.view, cov.pixel_yx, patch, (48, 48), cfg, progress=False)
    before = fieldmod.TRACE_COUNT["train_step"]
    b, hb = distill(cov.points, cov.view, cov.pixel_yx, patch, (48, 48), cfg, progress=False)
    assert fieldmod.TRACE_COUNT["train_step"] == before  # same shapes and configuration: no new trace
    np.testing.assert_array_equal(ha.loss, hb.loss)
    np.testing.assert_array_equal(evaluate_field(a, v), evaluate_field(b, v))
    c, _ = distill(
        cov.points,
        cov.view,
        cov.pixel_yx,
        patch,
        (48, 48),
        FieldConfig(hidden=32, steps=20, batch_size=256, seed=12),
        progress=False,
    )
    assert np.abs(evaluate_field(c, v) - evaluate_field(a, v)).max() > 1e-3
    with pytest.raises(ValueError, match="view_idx"):
        distill(cov.points, cov.view + 24, cov.pixel_yx, patch, (48, 48), cfg, progress=False)
    with pytest.raises(ValueError, match="pixel_yx"):
        distill(cov.points, cov.view, cov.pixel_yx[:-1], patch, (48, 48), cfg, progress=False)


# ------------------------------------------------------------------------------------------ persistence


@pytest.mark.parametrize("fourier", [0, 6])
def test_save_load_round_trip(tmp_path, fourier):
    cfg = FieldConfig(hidden=24, layers=3, fourier_features=fourier, steps=7, seed=5)
    fld = new_field(C, [-1.0, -2.0, -3.0], [1.0, 2.0, 4.0], cfg)
    # perturb every parameter so that the loaded values cannot come from a fresh initialisation
    from flax import nnx

    params = nnx.state(fld, nnx.Param)
    nnx.update(fld, jax.tree_util.tree_map(lambda p: p + 0.01 * jnp.arange(p.size).reshape(p.shape) / p.size, params))
    meta = {"n_vertices": 123, "n_faces": 242, "backbone": "test-backbone", "note": [1, 2]}
    path = save_field(tmp_path / "sub" / "field", fld, meta)
    assert path.is_dir() and [p.name for p in path.parent.iterdir()] == ["field"]  # no temporary left
    back, meta2 = load_field(path)
    x = np.random.default_rng(4).normal(size=(300, 3))
    np.testing.assert_array_equal(evaluate_field(back, x), evaluate_field(fld, x))
    assert back.config == cfg and back.features == C
    for k, val in meta.items():
        assert meta2[k] == val
    assert meta2["bbox"] == [[-1.0, -2.0, -3.0], [1.0, 2.0, 4.0]]
    assert FieldConfig(**meta2["config"]) == cfg
    with pytest.raises(ValueError, match="backbone"):
        save_field(tmp_path / "x", fld, {"n_vertices": 1, "n_faces": 1})


def test_load_rejects_other_and_damaged_files(tmp_path):
    from jaxdeform.nn.archive import read_archive, save_tree

    fld = new_field(C, np.zeros(3), np.ones(3), FieldConfig(hidden=8, layers=1))
    good = save_field(tmp_path / "good", fld, {"n_vertices": 3, "n_faces": 1, "backbone": "b"})
    meta, arrays = read_archive(good, "feature-field", fieldmod.FORMAT, fieldmod.FORMAT_VERSION, key="meta")
    shutil.copytree(good, tmp_path / "truncated")
    manifest = tmp_path / "truncated" / "arrays" / "manifest.ocdbt"
    manifest.write_bytes(manifest.read_bytes()[:20])
    (tmp_path / "text").write_text("hello")
    (tmp_path / "empty").mkdir()
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    save_tree(tmp_path / "wrong_format", arrays, {**meta, "format": "x"}, key="meta")
    name = next(k for k in arrays if k.endswith("['out']['kernel'].value"))
    save_tree(tmp_path / "misshapen", {**arrays, name: arrays[name][:, :-1]}, meta, key="meta")
    save_tree(tmp_path / "missing", {k: a for k, a in arrays.items() if k != name}, meta, key="meta")
    for bad in ["truncated", "text", "empty", "other.npz", "wrong_format", "misshapen", "missing", "absent"]:
        with pytest.raises(JaxDeformError) as err:
            load_field(tmp_path / bad)
        msg = str(err.value)
        assert msg.count(". ") == 0 and msg.endswith(".") and "\n" not in msg, msg
