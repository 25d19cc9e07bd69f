"""Tests of latent-space editing by control points (jaxdeform.components.edit; seed 000 Sec. 5.4, Fig. 6).

Tiny synthetic tube (72 vertices) with the real ACAP encode/decode; linear models built from the ACAP
features of a bend and a twist of the tube.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdeform import acap
from jaxdeform.acap import Scaler
from jaxdeform.components import edit as E
from jaxdeform.components.edit import EditInputError
from jaxdeform.data.synthetic import tube
from jaxdeform.errors import JaxDeformError

LENGTH = 2.0
SHIFT = np.array([0.3, -0.2, 0.1])


def bend(v, angle):
    """Bend along x into an arc in the x-y plane (total turning ``angle``)."""
    radius = LENGTH / angle
    th = v[:, 0] / radius
    rr = radius - v[:, 1]
    return np.stack([rr * np.sin(th), radius - rr * np.cos(th), v[:, 2]], 1)


def twist(v, angle):
    """Twist about the x axis, ``angle`` over the whole length."""
    th = angle * v[:, 0] / LENGTH
    c, s = np.cos(th), np.sin(th)
    return np.stack([v[:, 0], c * v[:, 1] - s * v[:, 2], s * v[:, 1] + c * v[:, 2]], 1)


def make_case(dtype):
    v, f = tube(6, 12, 0.1, LENGTH)
    v = v.astype(dtype)
    ac = acap.prepare(v, f)
    feats = np.asarray(acap.encode(v, f, np.stack([v, bend(v, 1.5), twist(v, 1.2)]).astype(dtype)))
    ident = jnp.asarray(feats[0])
    comps = jnp.asarray(np.stack([feats[1] - feats[0], feats[2] - feats[0]]))

    def decode(w):  # features of the rest shape at w = 0: latent0 = zeros is the code of the rest shape
        return ident + jnp.tensordot(w, comps, 1)

    return v, f, ac, decode


@pytest.fixture(scope="module")
def case64():
    return make_case(np.float64)


def ground_truth(ac, decode, w, refine):
    """A shape inside the model's span, moved by SHIFT (the edit must find the translation)."""
    return np.asarray(ac.decode(decode(jnp.asarray(w)), refine=refine)) + SHIFT.astype(ac.rest.dtype)


# --------------------------------------------------------------------------------------------------
# Furthest point sampling
# --------------------------------------------------------------------------------------------------


def fps_brute_force(x, n, start):
    chosen = [start]
    for _ in range(1, n):
        d = np.min(np.linalg.norm(x[:, None] - x[chosen][None], axis=-1), axis=1)
        d[chosen] = -1.0
        chosen.append(int(np.argmax(d)))
    return np.array(chosen)


@pytest.mark.parametrize("start", [0, 7, 49])
def test_fps_matches_brute_force_and_is_greedy(start):
    x = np.random.default_rng(start).normal(size=(50, 3))
    idx = np.asarray(E.furthest_point_sampling(x, 12, start))
    np.testing.assert_array_equal(idx, fps_brute_force(x, 12, start))
    assert idx[0] == start and len(set(idx.tolist())) == 12
    for k in range(1, 12):  # each next point is the furthest from those chosen before it
        d = np.min(np.linalg.norm(x[:, None] - x[idx[:k]][None], axis=-1), axis=1)
        assert d[idx[k]] == pytest.approx(d.max())


def test_fps_deterministic_on_ties_and_distinct_on_duplicates():
    grid = np.stack(np.meshgrid(np.arange(4.0), np.arange(4.0), [0.0], indexing="ij"), -1).reshape(-1, 3)
    a = np.asarray(E.furthest_point_sampling(grid, 16))
    np.testing.assert_array_equal(a, np.asarray(E.furthest_point_sampling(grid, 16)))
    np.testing.assert_array_equal(a, fps_brute_force(grid, 16, 0))
    dup = np.concatenate([grid, grid])  # unwelded mesh: every point twice
    b = np.asarray(E.furthest_point_sampling(dup, 32, 3))
    assert sorted(b.tolist()) == list(range(32))


@pytest.mark.parametrize("args", [(0, 0), (51, 0), (5, -1), (5, 50), (2.5, 0)])
def test_fps_bad_input(args):
    x = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(E.EditInputError, match="must"):
        E.furthest_point_sampling(x, *args)
    with pytest.raises(E.EditInputError, match="NaN"):
        E.furthest_point_sampling(np.full((4, 3), np.nan), 2)


# --------------------------------------------------------------------------------------------------
# Editing through the ACAP reconstruction
# --------------------------------------------------------------------------------------------------


def test_edit_recovers_in_span_weights_with_scaler(case64):
    v, f, ac, decode = case64
    w_true = np.array([0.6, 0.4])
    gt = ground_truth(ac, decode, w_true, refine=1)
    scaler = Scaler.fit(np.stack([decode(jnp.asarray(w)) for w in np.eye(2)]))
    scaled_decode = lambda w: scaler.transform(decode(w))  # noqa: E731 (the model outputs scaled features)
    controls = np.asarray(E.furthest_point_sampling(v, 6))
    res = E.edit(scaled_decode, jnp.zeros(2), ac, scaler, controls, gt[controls])  # (rest, faces) works too
    diag = E.bounding_box_diagonal(v)
    np.testing.assert_allclose(np.asarray(res.latent), w_true, atol=1e-4)
    np.testing.assert_allclose(np.asarray(res.translation), SHIFT, atol=1e-4)
    assert float(res.control_error) < 1e-5 * diag
    assert np.linalg.norm(np.asarray(res.positions) - gt, axis=1).mean() < 1e-5 * diag
    assert 0 < int(res.steps) <= E.DEFAULT_STEPS
    assert bool(res.converged)


@pytest.mark.parametrize("method", ["bfgs", "lm"])
def test_edit_cut_short_is_not_converged(case64, method):
    # an off-span target (a bend the two components do not hold) needs more than one iteration: capped at one,
    # the edit says it did not converge, and stages report it when any stage is cut short
    v, f, ac, decode = case64
    gt = bend(v, 2.5)
    controls = np.asarray(E.furthest_point_sampling(v, 8))
    short = E.edit(decode, jnp.zeros(2), ac, None, controls, gt[controls], steps=1, method=method)
    assert int(short.steps) == 1 and not bool(short.converged)
    full = E.edit(decode, jnp.zeros(2), ac, None, controls, gt[controls], method=method)
    assert bool(full.converged) and 1 < int(full.steps) < E.DEFAULT_STEPS
    assert float(full.objective) < float(short.objective)
    staged = E.edit(decode, jnp.zeros(2), ac, None, controls, gt[controls], steps=1, method=method, stages=(1, 2))
    assert not bool(staged.converged)
    adam = E.edit(decode, jnp.zeros(2), ac, None, controls, gt[controls], steps=5, method="adam")
    assert int(adam.steps) == 5 and not bool(adam.converged)  # a fixed number of steps: no stopping test


def test_deformation_energy_analytic(case64):
    v, f, ac, decode = case64
    rest_features = decode(jnp.zeros(2))
    rec = ac.reconstructor(None)
    edges = np.asarray(v)[np.asarray(rec.edge_i)] - np.asarray(v)[np.asarray(rec.edge_j)]
    weights = np.asarray(rec.sqrt_w) ** 2
    # the rest features' gradients are the identity: zero at the rest shape and any translate of it, and
    # s^2 sum_e w_e |q_i - q_j|^2 for the shape scaled by (1 + s)
    assert abs(float(ac.deformation_energy(rest_features, v + SHIFT))) < 1e-20
    expected = 0.1**2 * np.sum(weights * np.sum(edges**2, axis=1))
    np.testing.assert_allclose(float(ac.deformation_energy(rest_features, 1.1 * v)), expected, rtol=1e-10)
    # batched, and the plain reconstruction (refine=0) minimises it under its anchors: the refined mesh, with the
    # same anchor, is not better
    feats = jnp.stack([decode(jnp.asarray([0.6, 0.4])), rest_features])
    plain, refined = ac.decode(feats, refine=0), ac.decode(feats, refine=1)
    e_plain, e_refined = (
        np.asarray(ac.deformation_energy(feats, plain)),
        np.asarray(ac.deformation_energy(feats, refined)),
    )
    assert e_plain.shape == (2,) and np.all(e_plain <= e_refined + 1e-15) and e_plain[0] > 0


@pytest.mark.parametrize("method, steps", [("bfgs", 500), ("adam", 300)])
def test_deformation_objective_holds_controls_and_recovers_weights(case64, method, steps):
    v, f, ac, decode = case64
    w_true = np.array([0.6, 0.4])
    gt = ground_truth(ac, decode, w_true, refine=0)
    controls = np.asarray(E.furthest_point_sampling(v, 6))
    diag = E.bounding_box_diagonal(v)
    res = E.edit(
        decode,
        jnp.zeros(2),
        ac,
        None,
        controls,
        gt[controls],
        objective="deformation",
        method=method,
        steps=steps,
        learning_rate=0.02,
    )
    # the controls are anchors of the reconstruction (met up to the anchors' finite weight), translation included
    assert float(res.control_error) < 1e-5 * diag
    np.testing.assert_allclose(np.asarray(res.translation), 0.0)
    # the shape lies in the span: the weights that made it explain the controls with (almost) no distortion
    np.testing.assert_allclose(np.asarray(res.latent), w_true, atol=5e-3)
    assert np.linalg.norm(np.asarray(res.positions) - gt, axis=1).mean() < 1e-3 * diag
    assert float(res.objective) < 1e-3  # relative to the rest code's energy with the same controls
    assert bool(res.converged) == (method == "bfgs")
    if method != "bfgs":
        return
    # an off-span target: the controls are still met, where the "controls" objective can only approach them
    far = bend(v, 2.5)
    held = E.edit(decode, jnp.zeros(2), ac, None, controls, far[controls], objective="deformation")
    fitted = E.edit(decode, jnp.zeros(2), ac, None, controls, far[controls])
    assert float(held.control_error) < 1e-5 * diag < float(fitted.control_error)


def test_deformation_objective_staged_and_bad_input(case64):
    v, f, ac, decode = case64
    gt = ground_truth(ac, decode, np.array([0.6, 0.4]), refine=0)
    controls = np.asarray(E.furthest_point_sampling(v, 6))
    staged = E.edit(decode, jnp.zeros(2), ac, None, controls, gt[controls], objective="deformation", stages=(1, 2))
    whole = E.edit(decode, jnp.zeros(2), ac, None, controls, gt[controls], objective="deformation")
    np.testing.assert_allclose(np.asarray(staged.latent), np.asarray(whole.latent), atol=1e-4)
    with pytest.raises(EditInputError, match="least-squares"):
        E.edit(decode, jnp.zeros(2), ac, None, controls, gt[controls], objective="deformation", method="lm")
    dup = np.r_[controls, controls[:1]]
    with pytest.raises(EditInputError, match="distinct"):
        E.edit(decode, jnp.zeros(2), ac, None, dup, gt[dup], objective="deformation")
    with pytest.raises(EditInputError, match="objective"):
        E.edit(decode, jnp.zeros(2), ac, None, controls, gt[controls], objective="energy")


def test_cli_edit_defaults_follow_the_library():
    """The CLI spells its edit defaults out (it parses before importing jax): they must stay the library's."""
    from jaxdeform.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(["components", "edit", "RUN", "--controls", "c.json", "--out", "e.obj"])
    assert args.steps == E.DEFAULT_STEPS
    assert args.objective in E.OBJECTIVES
    for objective in E.OBJECTIVES:  # every library objective is offered; an unknown one is refused
        assert (
            parser.parse_args(
                ["components", "edit", "RUN", "--controls", "c.json", "--out", "e.obj", "--objective", objective]
            ).objective
            == objective
        )
    with pytest.raises(SystemExit):
        parser.parse_args(
            ["components", "edit", "RUN", "--controls", "c.json", "--out", "e.obj", "--objective", "energy"]
        )


def test_more_controls_do_not_increase_error(case64):
    v, f, ac, decode = case64
    gt = ground_truth(ac, decode, [1.3, -0.7], refine=0)
    errors = [E.edit_error(decode, jnp.zeros(2), ac, None, gt, n, refine=0, method="lm").mean_error for n in (1, 3, 9)]
    # one control fixes only the translation: the edit stays at the rest shape
    assert errors[0] > 0.1
    assert max(errors[1:]) < 1e-5
    assert all(b <= a + 1e-7 for a, b in zip(errors, errors[1:]))


def test_second_call_does_not_retrace(case64):
    v, f, ac, decode = case64
    controls = np.asarray(E.furthest_point_sampling(v, 3))  # the compiled editor of the previous test
    gt_a = ground_truth(ac, decode, [0.2, 0.1], refine=0)
    gt_b = ground_truth(ac, decode, [0.9, -0.3], refine=0)
    E.edit(decode, jnp.zeros(2), ac, None, controls, gt_a[controls], refine=0, method="lm")
    size = E._edit_jit._cache_size()
    res = E.edit(
        decode, jnp.asarray([0.1, 0.1]), ac, None, controls[::-1].copy(), gt_b[controls[::-1]], refine=0, method="lm"
    )
    assert E._edit_jit._cache_size() == size
    np.testing.assert_allclose(np.asarray(res.latent), [0.9, -0.3], atol=1e-4)


def test_gradient_through_acap_decode_is_finite_and_correct(case64):
    v, f, ac, decode = case64
    controls = jnp.asarray([0, 30, 71])

    def loss(w):
        return jnp.sum(ac.decode(decode(w))[controls] ** 2)

    w = jnp.zeros(2)  # identity features: the delicate case for rotation logs and polar decompositions
    g = np.asarray(jax.jit(jax.grad(loss))(w))
    assert np.all(np.isfinite(g)) and np.abs(g).max() > 0
    h = 1e-6
    fd = [(loss(w + h * e) - loss(w - h * e)) / (2 * h) for e in jnp.eye(2)]
    np.testing.assert_allclose(g, np.asarray(fd), rtol=1e-5, atol=1e-8)


def test_edit_multiscale_model_latents(case64):
    """The multiscale model's decoder (flattened latent tuple; its mesh convolution has a custom VJP and no
    forward mode, so the editor falls back to the reverse-mode Jacobian)."""
    from jaxdeform.components import model
    from jaxdeform.nn.graph_conv import rings_from_topology

    v, f, ac, _ = case64
    cfg = model.Config(kz=(3, 2), d=(0.4, 0.2))
    params = model.Model(v.shape[0], cfg, key=jax.random.PRNGKey(0), dtype=jnp.float64)
    rings = rings_from_topology(ac.topo)
    sizes = [cfg.blocks(level) * kz for level, kz in enumerate(cfg.kz)]

    def decode(w):
        parts = jnp.split(w, np.cumsum(sizes)[:-1])
        latents = tuple(p.reshape(cfg.blocks(level), 1, cfg.kz[level]) for level, p in enumerate(parts))
        return params.decode_latents(latents, rings)[0]

    scaler = Scaler(-1.0, 1.0, 0.0, 2.0)
    w_true = 0.3 * jax.random.normal(jax.random.PRNGKey(1), (sum(sizes),))
    gt = np.asarray(ac.decode(scaler.inverse(decode(w_true)), refine=0))
    controls = np.asarray(E.furthest_point_sampling(v, 8))
    res = E.edit(decode, jnp.zeros(sum(sizes)), ac, scaler, controls, gt[controls], refine=0, method="lm")
    assert float(res.control_error) < 1e-4 * E.bounding_box_diagonal(v)


# --------------------------------------------------------------------------------------------------
# Coordinate-space models and the Fig. 6 protocol
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method, steps, atol", [("lm", 50, 1e-4), ("bfgs", 50, 1e-4), ("adam", 300, 2e-2)])
def test_staged_edit_is_a_coarse_edit_then_a_full_edit(case64, method, steps, atol):
    """stages=(1, 2) equals an edit of latent 0 alone (latent 1 held at its start) followed by an edit of both
    latents from there, for every optimiser; the in-span target is still recovered, steps add up over the
    stages, and the stages share the one-stage edit's compiled function."""
    v, f, ac, decode = case64
    w_true = np.array([0.6, 0.4])
    gt = ground_truth(ac, decode, w_true, refine=1)
    controls = np.asarray(E.furthest_point_sampling(v, 6))
    w_start = jnp.asarray([0.0, 0.1])
    kw = {"method": method, "steps": steps, "regularization": 0.0}
    E.edit(decode, w_start, ac, None, controls, gt[controls], **kw)  # compiles the one-stage edit
    compiled = E._edit_jit._cache_size()
    staged = E.edit(decode, w_start, ac, None, controls, gt[controls], stages=(1, 2), **kw)
    assert E._edit_jit._cache_size() == compiled  # the mask is traced: no new compile for the stages
    coarse = E.edit(
        lambda u: decode(jnp.concatenate([u, w_start[1:]])), w_start[:1], ac, None, controls, gt[controls], **kw
    )
    assert float(coarse.control_error) > 1e-3  # latent 0 alone cannot meet a twisted target
    w1 = jnp.concatenate([coarse.latent, w_start[1:]])
    full = E.edit(decode, w1, ac, None, controls, gt[controls], **kw)
    np.testing.assert_allclose(np.asarray(staged.latent), np.asarray(full.latent), atol=1e-8)
    np.testing.assert_allclose(np.asarray(staged.positions), np.asarray(full.positions), atol=1e-8)
    assert int(staged.steps) == int(coarse.steps) + int(full.steps)
    np.testing.assert_allclose(np.asarray(staged.latent), w_true, atol=atol)


def test_staged_edit_regularizes_toward_latent0(case64):
    """Every stage's regularization pulls toward latent0, not toward the stage's start: with a strong weight
    the reported objective is |residual|^2 + reg |w - latent0|^2 of the final latents."""
    v, f, ac, decode = case64
    gt = ground_truth(ac, decode, np.array([0.6, 0.4]), refine=1)
    controls = np.asarray(E.furthest_point_sampling(v, 6))
    reg = 1e-2
    res = E.edit(decode, jnp.zeros(2), ac, None, controls, gt[controls], method="lm", regularization=reg, stages=(1, 2))
    r = np.asarray(res.positions)[controls] - gt[controls]
    expected = np.sum(r**2) + reg * np.sum(np.asarray(res.latent) ** 2)
    assert float(res.objective) == pytest.approx(expected, rel=1e-6)


def test_edit_positions_linear_model_and_protocol(case64):
    v, f, ac, _ = case64
    comps = jnp.asarray(np.stack([bend(v, 1.5) - v, twist(v, 1.2) - v]))
    rest = jnp.asarray(v)

    def decode_positions(w):
        return rest + jnp.tensordot(w, comps, 1)

    gt = np.asarray(decode_positions(jnp.asarray([0.7, -0.4]))) + SHIFT
    rep = E.edit_error(decode_positions, jnp.zeros(2), v, None, gt, 5, space="positions", start=3, regularization=0.0)
    np.testing.assert_array_equal(rep.controls, np.asarray(E.furthest_point_sampling(v, 5, 3)))
    np.testing.assert_allclose(np.asarray(rep.result.latent), [0.7, -0.4], atol=1e-5)
    assert rep.diagonal == pytest.approx(np.linalg.norm(v.max(0) - v.min(0)))
    dist = np.linalg.norm(np.asarray(rep.result.positions) - gt, axis=1)
    assert rep.mean_error == pytest.approx(dist.mean() / rep.diagonal)
    assert rep.mean_error < 1e-6 and rep.control_error < 1e-6

    # without free translation the shift cannot be met, the unshifted shape still can
    c = rep.controls
    res = E.edit_positions(decode_positions, jnp.zeros(2), c, gt[c], free_translation=False)
    assert float(res.control_error) > 0.1 and not np.any(np.asarray(res.translation))
    res = E.edit_positions(decode_positions, jnp.zeros(2), c, gt[c] - SHIFT, free_translation=False, regularization=0.0)
    assert float(res.control_error) < 1e-6


@pytest.mark.parametrize("method, steps", [("lm", 50), ("bfgs", 50), ("adam", 400)])
def test_edit_positions_float32_every_method(case64, method, steps):
    v = case64[0].astype(np.float32)
    comps = jnp.asarray(np.stack([bend(v, 1.5) - v, twist(v, 1.2) - v]))
    decode_positions = lambda w: jnp.asarray(v) + jnp.tensordot(w, comps, 1)  # noqa: E731
    gt = np.asarray(decode_positions(jnp.asarray([0.5, 0.3], jnp.float32))) + SHIFT.astype(np.float32)
    controls = np.asarray(E.furthest_point_sampling(v, 6))
    res = E.edit_positions(
        decode_positions,
        jnp.zeros(2, jnp.float32),
        controls,
        gt[controls],
        method=method,
        steps=steps,
        learning_rate=0.02,
    )
    assert res.positions.dtype == jnp.float32 and res.latent.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(res.latent), [0.5, 0.3], atol=1e-3)
    assert int(res.steps) <= steps and (method != "adam" or int(res.steps) == steps)


def test_edit_positions_more_latents_than_control_rows(case64):
    v = case64[0]
    comps = jnp.asarray(np.random.default_rng(1).normal(size=(5, v.shape[0], 3)))
    decode_positions = lambda w: jnp.asarray(v) + jnp.tensordot(w, comps, 1)  # noqa: E731
    target = np.asarray(decode_positions(jnp.asarray([0.3, -0.2, 0.1, 0.0, 0.5])))[[10]]
    for method in ("bfgs", "lm"):  # 5 latents, 3 residual rows: the reverse-mode Jacobian branch
        res = E.edit_positions(
            decode_positions,
            jnp.zeros(5),
            np.array([10]),
            target,
            free_translation=False,
            method=method,
            regularization=1e-8,
        )
        assert float(res.control_error) < 1e-5


# --------------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "change, match",
    [
        ({"controls": np.array([0, 72])}, "control indices must lie"),
        ({"controls": np.array([-1, 3])}, "control indices must lie"),
        ({"controls": np.array([0.0, 1.0])}, "integer"),
        ({"targets": np.array([[0, 0, 0], [np.nan, 0, 0]])}, "NaN"),
        ({"targets": np.zeros((3, 3))}, "2 control indices but 3 targets"),
        ({"targets": np.zeros((2, 2))}, r"\(M, 3\)"),
        ({"latent0": jnp.zeros((1, 2))}, "1-D"),
        ({"latent0": jnp.zeros(3)}, "decode_features failed"),
        ({"decode": lambda w: jnp.zeros((72, 3)) + w[0]}, r"must return \(72, 9\)"),
        ({"steps": 0}, "steps"),
        ({"regularization": -1.0}, "regularization"),
        ({"method": "sgd"}, "unknown method"),
        ({"anchor": 100}, "anchor"),
        ({"stages": (2, 1)}, "stages must be increasing"),
        ({"stages": (1,)}, "up to the latent size 2"),
        ({"stages": "12"}, "integer latent counts"),
        ({"stages": (0.5, 2)}, "integer latent counts"),
    ],
)
def test_bad_input_raises_clear_errors(case64, change, match):
    v, f, ac, decode = case64
    kw = {"decode": decode, "latent0": jnp.zeros(2), "controls": np.array([0, 5]), "targets": np.zeros((2, 3))}
    opts = {k: change.pop(k) for k in ("steps", "regularization", "method", "anchor", "stages") if k in change}
    kw.update(change)
    with pytest.raises(E.EditInputError, match=match) as info:
        E.edit(kw["decode"], kw["latent0"], ac, None, kw["controls"], kw["targets"], **opts)
    assert isinstance(info.value, JaxDeformError) and isinstance(info.value, ValueError)


def test_bad_input_protocol_and_positions(case64):
    v, f, ac, decode = case64
    with pytest.raises(E.EditInputError, match="ground truth"):
        E.edit_error(decode, jnp.zeros(2), ac, None, v[:10], 4)
    with pytest.raises(E.EditInputError, match="NaN"):
        E.edit_error(decode, jnp.zeros(2), ac, None, np.full_like(v, np.nan), 4)
    with pytest.raises(E.EditInputError, match="unknown space"):
        E.edit_error(decode, jnp.zeros(2), ac, None, v, 4, space="coords")
    with pytest.raises(E.EditInputError, match=r"\(V, 3\)"):
        E.edit_positions(decode, jnp.zeros(2), np.array([0]), np.zeros((1, 3)))
    with pytest.raises(E.EditInputError, match="Acap"):
        E.edit(decode, jnp.zeros(2), v, None, np.array([0]), np.zeros((1, 3)))
