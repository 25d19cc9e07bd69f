import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxdeform.acap.rotations import det3, exp_rotation, inv3, log_rotation, polar, rotation_angle


def rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def official_polar(t):
    """Reference: SVD polar with the official reflection fix."""
    u, s, vt = np.linalg.svd(t)
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, 2] *= -1
        s[2] *= -1
        r = u @ vt
    return r, vt.T @ np.diag(s) @ vt


def test_inverse_and_determinant():
    a = np.random.default_rng(0).normal(size=(50, 3, 3))
    np.testing.assert_allclose(np.asarray(inv3(jnp.asarray(a))), np.linalg.inv(a), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(det3(jnp.asarray(a))), np.linalg.det(a), rtol=1e-12)


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-9), (np.float32, 2e-4)])
def test_polar_matches_svd_reference(dtype, tol):
    rng = np.random.default_rng(1)
    t = np.stack(
        [
            rot(rng.normal(size=3), rng.uniform(0, np.pi)) @ (np.eye(3) + 0.3 * rng.normal(size=(3, 3)))
            for _ in range(200)
        ]
    )
    r, s = polar(jnp.asarray(t.astype(dtype)))
    for k in range(0, 200, 7):
        rr, ss = official_polar(t[k])
        np.testing.assert_allclose(np.asarray(r[k]), rr, atol=tol * 10)
        np.testing.assert_allclose(np.asarray(s[k]), ss, atol=tol * 10)
    np.testing.assert_allclose(np.asarray(r @ s), t, atol=tol * 10)
    assert np.all(np.abs(np.asarray(det3(r)) - 1) < tol * 10)


def test_polar_reflection_follows_official_convention():
    t = rot([1, 2, 3], 0.7) @ np.diag([2.0, 1.0, -0.5])
    r, s = polar(jnp.asarray(t))
    rr, ss = official_polar(t)
    np.testing.assert_allclose(np.asarray(r), rr, atol=1e-9)
    np.testing.assert_allclose(np.asarray(s), ss, atol=1e-9)
    assert np.isclose(float(det3(r)), 1.0)


@pytest.mark.parametrize("n_reflected", [0, 3, 40, 64])
def test_polar_reflections_few_or_many(n_reflected):
    """Both reflection paths (gathered when few, whole batch when many) match the SVD reference."""
    rng = np.random.default_rng(5)
    t = np.stack(
        [rot(rng.normal(size=3), rng.uniform(0, np.pi)) @ np.diag(rng.uniform(0.5, 2.0, 3)) for _ in range(64)]
    )
    t[:n_reflected] = t[:n_reflected] @ np.diag([1.0, -1.0, 1.0])
    r, s = polar(jnp.asarray(t))
    for k in range(64):
        rr, ss = official_polar(t[k])
        np.testing.assert_allclose(np.asarray(r[k]), rr, atol=1e-8)
        np.testing.assert_allclose(np.asarray(s[k]), ss, atol=1e-8)


def test_polar_identity_and_rigid():
    r, s = polar(jnp.eye(3)[None])
    np.testing.assert_allclose(np.asarray(r[0]), np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.asarray(s[0]), np.eye(3), atol=1e-12)
    q = rot([0, 1, 1], 2.5)
    r, s = polar(jnp.asarray(q))
    np.testing.assert_allclose(np.asarray(s), np.eye(3), atol=1e-10)


@settings(max_examples=60, deadline=None)
@given(
    st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(lambda a: np.linalg.norm(a) > 1e-3),
    st.one_of(st.floats(0, np.pi), st.sampled_from([0.0, 1e-9, 1e-5, np.pi - 1e-9, np.pi - 1e-5, np.pi])),
)
def test_log_exp_round_trip(axis, angle):
    r = rot(axis, angle)
    v = np.asarray(log_rotation(jnp.asarray(r)))
    assert np.linalg.norm(v) <= np.pi + 1e-9
    np.testing.assert_allclose(np.asarray(exp_rotation(jnp.asarray(v))), r, atol=1e-7)
    np.testing.assert_allclose(float(rotation_angle(jnp.asarray(r))), angle, atol=1e-6)


def test_known_log():
    v = np.asarray(log_rotation(jnp.asarray(rot([0, 0, 1], 1.2))))
    np.testing.assert_allclose(v, [0, 0, 1.2], atol=1e-12)


def test_exp_of_large_angles():
    # consistent angles run past 2 pi: exp must still be the rotation about the axis
    for ang in (4.0, 2 * np.pi + 0.3, 9.0):
        np.testing.assert_allclose(
            np.asarray(exp_rotation(jnp.asarray([ang, 0.0, 0.0]))), rot([1, 0, 0], ang), atol=1e-10
        )


@pytest.mark.parametrize("angle", [0.0, np.pi])
def test_finite_gradients_at_identity_and_half_turn(angle):
    r0 = jnp.asarray(rot([1, 2, 2], angle))
    g = jax.grad(lambda r: jnp.sum(log_rotation(r) ** 2) + jnp.sum(log_rotation(r)))(r0)
    assert np.all(np.isfinite(np.asarray(g)))
    g2 = jax.grad(lambda t: jnp.sum(polar(t)[0]) + jnp.sum(polar(t)[1]))(r0)
    assert np.all(np.isfinite(np.asarray(g2)))
    ge = jax.grad(lambda v: jnp.sum(exp_rotation(v)))(jnp.zeros(3) if angle == 0 else jnp.asarray([np.pi, 0, 0]))
    assert np.all(np.isfinite(np.asarray(ge)))


def test_exp_gradient_matches_finite_differences():
    v = jnp.asarray([0.3, -1.1, 2.0])
    f = lambda v: jnp.sum(exp_rotation(v) * jnp.arange(9.0).reshape(3, 3))  # noqa: E731
    g = np.asarray(jax.grad(f)(v))
    eps = 1e-6
    fd = [(f(v.at[i].add(eps)) - f(v.at[i].add(-eps))) / (2 * eps) for i in range(3)]
    np.testing.assert_allclose(g, np.asarray(fd), rtol=1e-6)
