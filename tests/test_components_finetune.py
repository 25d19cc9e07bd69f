"""jaxdeform.components.finetune and `jaxdeform components finetune`: regional mixes, the position term, the
written run, and the CLI's refusals."""

import json

import jax
import numpy as np
import pytest

from experiments.components import run as exp
from jaxdeform import acap
from jaxdeform.cli import main as cli_main


def run_cli(argv, capsys):
    code = cli_main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.fixture(scope="module")
def tube_run(tmp_path_factory):
    """(data folder, run folder): one multiscale run of the synthetic tube (test config, 30 epochs), trained once for
    the module; tests read it and write elsewhere (the fine-tuning test checks that its source stays untouched)."""
    from jaxdeform.components import run as crun

    root = tmp_path_factory.mktemp("tube")
    data = exp.synthetic_tube(root)
    crun.fit(data, "test", root / "run", method="multiscale", epochs=30, progress=False, log=lambda s: None)
    return data, root / "run"


def test_regional_mixes_are_convex_and_smooth():
    from jaxdeform.components.finetune import regional_mixes

    rng = np.random.default_rng(3)
    pos = np.linspace(0.0, 1.0, 40)
    dist = np.abs(pos[:, None] - pos[None, :])  # a path of 40 vertices, geodesics on [0, 1]
    x = rng.normal(size=(4, 40, 9))
    mixes = regional_mixes(x, dist, 6, np.random.default_rng(0), (2, 5), 0.2, 0.5)
    assert mixes.shape == (6, 40, 9)
    # every vertex is a convex combination of the shapes: within their range, channel by channel
    assert np.all(mixes >= x.min(axis=0) - 1e-12) and np.all(mixes <= x.max(axis=0) + 1e-12)
    # and the combination is recoverable and convex: solve per vertex for the 4 weights (9 channels, 4 unknowns)
    for m in mixes[:2]:
        w = np.stack([np.linalg.lstsq(x[:, v].T, m[v], rcond=None)[0] for v in range(40)])
        assert np.allclose(w.sum(axis=1), 1.0) and np.all(w > -1e-9)
        assert np.abs(np.diff(w, axis=0)).max() < 0.5  # smooth along the path (sigma 0.2, spacing 0.026)
    # identical shapes mix to themselves; two draws from one seed are equal, other seeds differ
    same = np.broadcast_to(x[:1], x.shape)
    assert np.allclose(regional_mixes(same, dist, 3, np.random.default_rng(1)), x[0])
    again = regional_mixes(x, dist, 6, np.random.default_rng(0), (2, 5), 0.2, 0.5)
    assert np.array_equal(again, mixes)
    assert not np.allclose(regional_mixes(x, dist, 6, np.random.default_rng(1), (2, 5), 0.2, 0.5), mixes)


def test_rigid_residual_is_the_erms_alignment_and_its_gradient_is_the_minimum_s():
    """rigid_residual: zero for a rotated and moved copy; the same alignment as metrics.normalize_pair (whose Erms
    it reproduces); its squared sum's gradient (rotation held, the envelope theorem) matches central differences of
    the minimum over rotations computed afresh for each perturbed input."""
    import jax.numpy as jnp
    from scipy.spatial.transform import Rotation

    from jaxdeform import metrics
    from jaxdeform.components.finetune import rigid_residual

    rng = np.random.default_rng(7)
    g = rng.normal(size=(3, 30, 3))
    rot = Rotation.random(3, random_state=1).as_matrix()
    moved = np.einsum("bxy,bvy->bvx", rot, g) + rng.normal(size=(3, 1, 3))
    assert np.abs(np.asarray(rigid_residual(jnp.asarray(moved), jnp.asarray(g)))).max() < 1e-10
    p = moved + 0.2 * rng.normal(size=g.shape)
    res = np.asarray(rigid_residual(jnp.asarray(p), jnp.asarray(g)))
    ref, rec = metrics.normalize_pair(g, p)
    radius = float(np.sqrt(((g - g.mean(axis=1, keepdims=True)) ** 2).sum(axis=-1)).max())
    np.testing.assert_allclose(res / radius, rec - ref, atol=1e-12)

    def minimum(q):
        return float(np.sum(np.asarray(rigid_residual(jnp.asarray(q), jnp.asarray(g))) ** 2))

    grad = np.asarray(jax.grad(lambda q: jnp.sum(rigid_residual(q, jnp.asarray(g)) ** 2))(jnp.asarray(p)))
    h = 1e-6
    for b, v, c in [(0, 0, 0), (1, 17, 2), (2, 29, 1), (2, 3, 0)]:
        e = np.zeros_like(p)
        e[b, v, c] = h
        fd = (minimum(p + e) - minimum(p - e)) / (2 * h)
        assert abs(fd - grad[b, v, c]) < 1e-6 * max(1.0, abs(fd))


@pytest.mark.parametrize("rigid", [False, True])
def test_staged_step_has_the_gradient_of_the_loss(tube_run, rigid):
    """make_step's three stages (forward with VJP, position term, pullback and update) give the gradient of the one
    differentiable loss: with plain SGD of rate 1 the update is minus that gradient, and the terms are its terms;
    the rotation-free term (rigid) is no larger than the translation-free one."""
    import jax.numpy as jnp
    import optax
    from flax import nnx

    from jaxdeform.components import finetune as ft
    from jaxdeform.components import run as crun
    from jaxdeform.mesh.topology import build_topology
    from jaxdeform.nn.graph_conv import rings_from_topology

    run = crun.load(tube_run[1])
    vertices, _ = crun.run_data(run, None)
    x = jnp.asarray(crun.scaled_features(run, vertices[:6]), jnp.float32)
    dist = jnp.asarray(crun.normalized_geodesics(run.rest, run.faces, np.float32))
    rings = rings_from_topology(build_topology(run.faces, run.rest.shape[0]))
    loss, positions, _ = ft.position_loss_fn(run, rings, dist, 50.0, rigid)
    g = positions(x[::-1])  # other shapes' positions: a position term far from zero
    params = nnx.state(run.model)
    (total, terms), grad = jax.value_and_grad(loss, has_aux=True)(params, x, g)
    opt = optax.sgd(1.0)
    new, _, staged_terms = ft.make_step(run, rings, dist, 50.0, opt, rigid)(params, opt.init(params), x, g)
    np.testing.assert_allclose(np.asarray(staged_terms), np.asarray(terms), rtol=1e-5)
    assert float(terms[1]) > 1e-3
    other = ft.position_loss_fn(run, rings, dist, 50.0, not rigid)[0](params, x, g)[1][1]
    assert (float(terms[1]) <= float(other) * (1 + 1e-6)) if rigid else (float(other) <= float(terms[1]) * (1 + 1e-6))
    for p0, p1, gr in zip(jax.tree.leaves(params), jax.tree.leaves(new), jax.tree.leaves(grad)):
        np.testing.assert_allclose(np.asarray(p0 - p1), np.asarray(gr), rtol=2e-3, atol=1e-6 * float(np.abs(gr).max()))


def test_staged_step_is_the_same_with_every_solver(tube_run):
    """The reconstruction's solver (host factor, dense XLA factor, conjugate gradients) changes neither the
    position targets nor the step: the same terms and the same updated parameters, to float32 accuracy."""
    import jax.numpy as jnp
    import optax
    from flax import nnx

    from jaxdeform.components import finetune as ft
    from jaxdeform.components import run as crun
    from jaxdeform.mesh.topology import build_topology
    from jaxdeform.nn.graph_conv import rings_from_topology

    run = crun.load(tube_run[1])
    vertices, _ = crun.run_data(run, None)
    x = jnp.asarray(crun.scaled_features(run, vertices[:4]), jnp.float32)
    dist = jnp.asarray(crun.normalized_geodesics(run.rest, run.faces, np.float32))
    rings = rings_from_topology(build_topology(run.faces, run.rest.shape[0]))
    params = nnx.state(run.model)
    opt = optax.sgd(1.0)
    results = {}
    for solver in ("host", "dense", "cg"):
        _, positions, _ = ft.position_loss_fn(run, rings, dist, 50.0, solver=solver)
        g = positions(x[::-1])
        new, _, terms = ft.make_step(run, rings, dist, 50.0, opt, solver=solver)(params, opt.init(params), x, g)
        results[solver] = (np.asarray(g), np.asarray(terms), [np.asarray(a) for a in jax.tree.leaves(new)])
    g0, t0, p0 = results["host"]
    assert float(t0[1]) > 1e-3
    for solver in ("dense", "cg"):
        g, t, p = results[solver]
        scale = float(np.abs(g0).max())
        np.testing.assert_allclose(g, g0, atol=1e-4 * scale)
        np.testing.assert_allclose(t, t0, rtol=1e-3)
        for a, b in zip(p, p0):
            np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-3 * float(np.abs(b).max()) + 1e-7)


def test_finetune_benchmark_smoke(tube_run, tmp_path):
    """benchmarks/finetune.py runs on a tiny run and writes every field (it measures nothing here)."""
    from benchmarks import finetune as bench
    from jaxdeform.components import run as crun

    out = tmp_path / "bench" / "finetune.json"
    argv = [str(tube_run[1]), "--json", str(out), "--solvers", "dense,host", "--repeats", "1", "--batch", "3"]
    x64 = jax.config.jax_enable_x64
    payload = bench.main(argv + ["--mixes", "2", "--project", "10"])
    assert jax.config.jax_enable_x64 == x64  # the script restores the setting it found
    on_disk = json.loads(out.read_text())
    assert on_disk == json.loads(json.dumps(payload))
    assert [r["solver"] for r in on_disk["records"]] == ["host", "dense"]
    assert on_disk["vertices"] == crun.load(tube_run[1]).rest.shape[0] and on_disk["batch"] == 3
    for r in on_disk["records"]:
        assert r["setup_s"] > 0 and r["compile_s"] > 0 and r["step_ms_median"] > 0 and r["targets"]["ms_median"] > 0
        assert r["projected_s"] >= r["compile_s"] and len(r["first_terms"]) == len(r["last_terms"]) == 2
    assert "| host |" in on_disk["table"] and "| dense |" in on_disk["table"]


def test_generated_meshes_are_the_decoded_codes_own_features(tube_run):
    """generated_meshes: without noise a generated mesh is the model's reconstruction of a mix (encoder codes through
    decode_latents, chunk by chunk, equal the model's one-pass reconstruction), decoded to vertices and entering as
    those vertices' own features; with noise the meshes move; one seed gives one result."""
    import jax.numpy as jnp

    from jaxdeform.components import finetune as ft
    from jaxdeform.components import run as crun
    from jaxdeform.mesh.topology import build_topology
    from jaxdeform.nn.graph_conv import rings_from_topology

    run = crun.load(tube_run[1])
    vertices, _ = crun.run_data(run, None)
    x = np.asarray(crun.scaled_features(run, vertices[run.train_idx]))
    dist = crun.normalized_geodesics(run.rest, run.faces, np.float32)
    rings = rings_from_topology(build_topology(run.faces, run.rest.shape[0]))
    still = ft.generated_meshes(run, x, dist, 5, 0.0, np.random.default_rng(4), rings, chunk=2)
    assert still.shape == (5,) + x.shape[1:] and still.dtype == x.dtype
    mixes = ft.regional_mixes(x, dist, 5, np.random.default_rng(4))
    decoded = crun.positions_from_scaled(run, run.model.reconstruction(jnp.asarray(mixes), rings))
    own = np.asarray(crun.scaled_features(run, decoded))
    assert np.abs(own - mixes).max() > 0.05  # the decoded meshes are not the mixes
    np.testing.assert_allclose(still, own, atol=2e-4)
    moved = ft.generated_meshes(run, x, dist, 5, 1.0, np.random.default_rng(4), rings)
    assert np.abs(moved - still).max() > 1e-2
    np.testing.assert_array_equal(moved, ft.generated_meshes(run, x, dist, 5, 1.0, np.random.default_rng(4), rings))


def test_finetune_lowers_the_position_term_and_writes_a_run(tube_run, tmp_path, capsys):
    """On the training shapes alone (a full, fixed batch) the position term falls; the output is a run that
    `components evaluate` scores, and the source run is untouched."""
    from jaxdeform.components import run as crun

    data, src = tube_run
    before = (src / "run.json").read_text()
    out = tmp_path / "tuned"
    code, text, err = run_cli(
        [
            "components",
            "finetune",
            str(src),
            "--out",
            str(out),
            "--mixes",
            "0",
            "--steps",
            "25",
            "--batch",
            "8",
            "--lr",
            "1e-3",
            "--position-weight",
            "1e3",
            "--quiet",
        ],
        capsys,
    )
    assert code == 0, err
    assert "fine-tuned" in text and str(out) in text
    tuned = crun.load(out)
    rec = tuned.record["finetune"]
    assert rec["steps"] == 25 and rec["mixes"] == 0 and rec["source"] == str(src)
    assert rec["last_terms"][1] < 0.5 * rec["first_terms"][1]
    assert (src / "run.json").read_text() == before
    original = crun.load(src)
    assert any(
        not np.array_equal(np.asarray(a), np.asarray(b))
        for a, b in zip(jax.tree_util.tree_leaves(tuned.model), jax.tree_util.tree_leaves(original.model))
    )
    result = crun.evaluate(tuned, data)
    assert np.isfinite(result["test"]["erms"]) and np.isfinite(result["train"]["erms"])
    codes = np.load(out / "codes.npz")
    assert sorted(codes.files) == ["level0", "level1"]
    # with mixes (and the data named): a short run still writes a loadable run
    code, _, err = run_cli(
        [
            "components",
            "finetune",
            str(src),
            "--out",
            str(tmp_path / "mixed"),
            "--data",
            str(data),
            "--mixes",
            "6",
            "--generated",
            "3",
            "--rigid",
            "--solver",
            "dense",
            "--steps",
            "2",
            "--batch",
            "3",
            "--quiet",
        ],
        capsys,
    )
    assert code == 0, err
    mixed = json.loads((tmp_path / "mixed" / "run.json").read_text())["finetune"]
    assert mixed["mixes"] == 6 and mixed["generated"] == 3 and mixed["rigid"] is True and mixed["solver"] == "dense"
    assert rec["solver"] == acap.default_solver(tuned.rest.shape[0])
    assert rec["lr_final"] == rec["lr"] == 1e-3  # constant unless --lr-final


def test_finetune_schedule():
    """Constant without lr_final; with it, lr at step 0, lr_final at the last step, the half-cosine midpoint between."""
    from jaxdeform.components.finetune import schedule

    assert schedule(2e-4, 100) == 2e-4 and schedule(2e-4, 100, 2e-4) == 2e-4
    s = schedule(2e-4, 101, 2e-5)
    assert float(s(0)) == pytest.approx(2e-4) and float(s(100)) == pytest.approx(2e-5)
    assert float(s(50)) == pytest.approx(0.5 * (2e-4 + 2e-5))
    assert all(float(s(k + 1)) < float(s(k)) for k in range(100))


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--steps", "0"], "--steps and --batch must be positive"),
        (["--mixes", "-1"], "--mixes and --generated must be non-negative"),
        (["--generated", "-3"], "--mixes and --generated must be non-negative"),
        (["--code-noise", "inf"], "--code-noise must be a non-negative"),
        (["--position-weight", "nan"], "--position-weight must be a non-negative"),
        (["--lr", "0"], "--lr must be a positive"),
        (["--lr-final", "1e-3"], "--lr-final must be a positive number no larger than --lr"),
        (["--lr-final", "0"], "--lr-final must be a positive number"),
        (["--seed", "-2"], "--seed must be a non-negative"),
    ],
)
def test_finetune_refuses_bad_options(tmp_path, capsys, extra, message):
    code, _, err = run_cli(["components", "finetune", str(tmp_path), "--out", str(tmp_path / "o")] + extra, capsys)
    assert code == 2 and err.count("\n") == 1 and message in err
    assert not (tmp_path / "o").exists()


def test_finetune_refuses_a_linear_run_and_a_busy_out(tmp_path, capsys):
    from jaxdeform.components import run as crun

    data = exp.synthetic_tube(tmp_path)
    (tmp_path / "pca").mkdir()
    crun.fit(data, "test", tmp_path / "pca", method="pca", progress=False, log=lambda s: None)
    code, _, err = run_cli(["components", "finetune", str(tmp_path / "pca"), "--out", str(tmp_path / "p2")], capsys)
    assert code == 2 and err.count("\n") == 1 and "only multiscale and tan runs" in err
    assert not (tmp_path / "p2").exists()
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "keep.txt").write_text("x")
    code, _, err = run_cli(["components", "finetune", str(tmp_path / "pca"), "--out", str(tmp_path / "busy")], capsys)
    assert code == 2 and err.count("\n") == 1 and (tmp_path / "busy" / "keep.txt").read_text() == "x"
