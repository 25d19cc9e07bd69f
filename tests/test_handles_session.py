"""The handle-editing page's state without HTTP (jaxdeform.handles.session.EditSession).

One session on a small synthetic ellipsoid (362 vertices) with cheap smooth features stands in for a mesh and
its distilled field. Deformations are compared with ``weights.Deformer.deform`` of the session's reported
arguments and with what the blending guarantees exactly (a handle has weight 1 at itself, an anchor weight 0);
frames with ``render`` of the reported state.
"""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from PIL import Image
from test_handles_server import check_one_sentence, ellipsoid, smooth_features

from jaxdeform.handles.session import EditSession
from jaxdeform.handles.viewport import WEIGHT_COLORMAP, WEIGHT_RANGE
from jaxdeform.mesh.render import render

WIDTH, HEIGHT = 96, 64
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def mesh():
    v, f = ellipsoid()
    return v, f, smooth_features(v)


@pytest.fixture(scope="module")
def module_session(mesh):
    v, f, z = mesh
    return EditSession(v, f, z, width=WIDTH, height=HEIGHT)


@pytest.fixture()
def session(module_session):
    module_session.reset("all")
    module_session.reset("view")
    return module_session


@pytest.fixture(scope="module")
def picks(mesh):
    """(handle vertex, anchor vertex): the +x tip, and the vertex whose features differ most from it (so the
    anchor leaves the handle's own weight at 1)."""
    v, _, z = mesh
    h = int(np.argmax(v[:, 0]))
    dist = np.linalg.norm(z.astype(np.float64) - z[h], axis=1)
    a = int(np.argmax(dist))
    assert dist[a] > 1.0 and np.linalg.norm(v[a] - v[h]) > 0.5
    return h, a


def expected(session: EditSession) -> np.ndarray:
    a = session.deform_args()
    if not a["handles"]:
        return session.rest
    d = session.deformer
    anchors = np.asarray(a["anchors"], dtype=np.int64) if a["anchors"] else ()
    return np.asarray(
        d.deform(
            np.asarray(a["handles"]),
            np.asarray(a["transforms"]),
            anchors=anchors,
            locality=a["locality"],
            symmetric=a["symmetric"],
            pou=a["pou"],
        ),
        dtype=np.float64,
    )


def deformed(session: EditSession) -> np.ndarray:
    return session.deformed_vertices(np.float64)


# ------------------------------------------------------------------------------------------- deformation


def test_without_a_moved_handle_the_mesh_is_the_rest_mesh(session, mesh, picks):
    v, _, _ = mesh
    h, _ = picks
    np.testing.assert_array_equal(deformed(session), v)  # no handle: the rest mesh itself
    assert session.weights().shape == (v.shape[0], 0) and session.selected_weights() is None
    assert session.add_handle(h) == 0 and session.selected == 0
    np.testing.assert_allclose(deformed(session), v, atol=1e-6)  # identity transform: no motion (float32)
    w = session.weights()
    assert w.shape == (v.shape[0], 1) and w[h, 0] == 1.0 and 0.0 <= w.min() and w.max() <= 1.0
    np.testing.assert_array_equal(session.selected_weights(), w[:, 0])


def test_translating_a_handle_moves_it_by_t_and_leaves_an_anchor_fixed(session, mesh, picks):
    v, _, _ = mesh
    h, a = picks
    assert session.toggle_anchor(a) is True
    k = session.add_handle(h)
    t = np.array([0.3, -0.2, 0.1])
    session.translate_handle(t)
    got = deformed(session)
    np.testing.assert_allclose(got[h], v[h] + t, atol=1e-5)
    np.testing.assert_allclose(got[a], v[a], atol=1e-6)
    np.testing.assert_allclose(got, expected(session), atol=1e-6)
    w = session.weights()[:, k]
    np.testing.assert_allclose(got - v, w[:, None] * t, atol=1e-5)  # every vertex moves by its weight times t
    assert np.count_nonzero(w > 0.5) > 1 and w[a] == 0.0
    session.translate_handle(t, handle=k)  # steps compose: the transform is the translation by 2 t
    np.testing.assert_allclose(np.asarray(session.transforms[k]), np.c_[np.eye(3), 2 * t], atol=1e-12)
    np.testing.assert_allclose(deformed(session)[h], v[h] + 2 * t, atol=1e-5)


def test_rotating_a_handle_turns_it_about_its_own_position(session, mesh, picks):
    v, _, _ = mesh
    h, _ = picks
    session.add_handle(h)
    session.translate_handle([0.0, 0.2, 0.0])
    before = deformed(session)[h]
    session.rotate_handle([0.0, 0.0, 1.0], 90.0)
    T = np.asarray(session.transforms[0])
    np.testing.assert_allclose(T[:, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(T[:, :3] @ v[h] + T[:, 3], before, atol=1e-6)  # the handle is the centre
    np.testing.assert_allclose(deformed(session)[h], before, atol=1e-5)
    np.testing.assert_allclose(deformed(session), expected(session), atol=1e-6)
    assert np.abs(deformed(session) - v).max() > 0.3


def test_resets_restore_the_rest_mesh(session, mesh, picks):
    v, _, _ = mesh
    h, a = picks
    session.toggle_anchor(a)
    session.add_handle(h)
    session.set_options(locality=True, lam=3.0, pou=True)
    for undo in (
        lambda: session.reset_handle(),
        lambda: session.reset("transforms"),
        lambda: session.set_transform(0, np.eye(3, 4)),
    ):
        session.translate_handle([0.2, 0.1, 0.0])
        assert np.abs(deformed(session) - v).max() > 0.1
        undo()
        np.testing.assert_allclose(deformed(session), v, atol=1e-6)
        assert session.handles == [h] and session.anchors == [a]
    session.translate_handle([0.2, 0.1, 0.0])
    session.remove_handle()
    np.testing.assert_array_equal(deformed(session), v)
    assert session.handles == [] and session.selected is None
    session.add_handle(h)
    session.translate_handle([0.2, 0.1, 0.0])
    session.reset("all")
    np.testing.assert_array_equal(deformed(session), v)
    assert (session.handles, session.anchors, session.selected) == ([], [], None)
    assert session.options.as_json() == {
        "locality": False,
        "lambda": 2.0,
        "symmetric": False,
        "pou": False,
        "show_weights": True,
    }


def test_options_change_the_deformation_as_the_deformer_does(session, mesh, picks):
    h, a = picks
    session.toggle_anchor(a)
    session.add_handle(h)
    session.translate_handle([0.2, 0.1, -0.1])
    version = session.version
    previous = deformed(session)
    # (one handle's weights sum to at most 1, so partition of unity leaves its deformation as it is)
    for options, changes in (
        ({"locality": True, "lam": 3.0}, True),
        ({"lam": 6.0}, True),
        ({"pou": True}, False),
        ({"locality": False}, True),
    ):
        assert session.set_options(**options)["lambda"] == session.options.lam
        got = deformed(session)
        np.testing.assert_allclose(got, expected(session), atol=1e-6)
        assert (np.abs(got - previous).max() > 1e-4) == changes and session.version > version
        previous, version = got, session.version
    assert session.deform_args()["pou"] and session.deform_args()["locality"] == 0.0
    session.set_options(show_weights=False)  # display only: the same mesh, a new version (another image)
    np.testing.assert_array_equal(deformed(session), previous)
    assert session.version == version + 1


# ------------------------------------------------------------------------------------------- bad requests

BAD_CALLS = {
    "vertex out of range": lambda s: s.add_handle(10**9),
    "negative vertex": lambda s: s.toggle_anchor(-1),
    "vertex not an integer": lambda s: s.add_handle(2.5),
    "vertex a bool": lambda s: s.add_handle(True),
    "unknown handle": lambda s: s.select_handle(5),
    "handle a float": lambda s: s.remove_handle(0.0),
    "non-finite translation": lambda s: s.translate_handle([math.nan, 0.0, 0.0]),
    "translation of 2 numbers": lambda s: s.translate_handle([1.0, 2.0]),
    "non-finite transform": lambda s: s.set_transform(0, np.full((3, 4), math.inf)),
    "transform of the wrong shape": lambda s: s.set_transform(0, [[1, 0, 0]]),
    "transform not numbers": lambda s: s.set_transform(0, "identity"),
    "zero rotation axis": lambda s: s.rotate_handle([0, 0, 0], 10.0),
    "non-finite angle": lambda s: s.rotate_handle([0, 0, 1], math.inf),
    "anchor on a handle": lambda s: s.toggle_anchor(s.handles[0]),
    "handle on an anchor": lambda s: s.add_handle(s.anchors[0]),
    "pick off the image": lambda s: s.pick(-1.0, 3.0),
    "pick at nan": lambda s: s.pick(math.nan, 3.0),
    "unknown pick action": lambda s: s.pick(3.0, 3.0, "explode"),
    "unknown drag mode": lambda s: s.drag("fly", (0, 0), (1, 1)),
    "drag to nowhere": lambda s: s.drag("translate", (0, 0), (math.nan, 1)),
    "negative lambda": lambda s: s.set_options(lam=-1.0),
    "symmetry without a field": lambda s: s.set_options(symmetric=True),
    "zero zoom": lambda s: s.set_view(zoom=0.0),
    "elevation over the pole": lambda s: s.set_view(elevation=100.0),
    "unknown reset": lambda s: s.reset("everything"),
    "unknown preview scale": lambda s: s.image_bytes(3),
    "unknown image format": lambda s: s.image_bytes(1, "gif"),
}


def snapshot(session: EditSession) -> dict:
    st = session.state()
    del st["timings"]
    return {"state": st, "vertices": deformed(session)}


@pytest.mark.parametrize("case", sorted(BAD_CALLS))
def test_bad_requests_raise_one_sentence_and_change_nothing(session, picks, case):
    h, a = picks
    session.toggle_anchor(a)
    session.add_handle(h)
    session.translate_handle([0.1, 0.0, 0.0])
    before = snapshot(session)
    with pytest.raises(ValueError) as info:
        BAD_CALLS[case](session)
    check_one_sentence(str(info.value))
    after = snapshot(session)
    assert after["state"] == before["state"]
    np.testing.assert_array_equal(after["vertices"], before["vertices"])


def test_nothing_selected_is_refused(session):
    for call in (
        lambda: session.translate_handle([0.1, 0, 0]),
        lambda: session.drag("rotate", (0, 0), (1, 1)),
        lambda: session.reset_handle(),
    ):
        with pytest.raises(ValueError, match="no handle is selected") as info:
            call()
        check_one_sentence(str(info.value))


def test_too_small_an_image_is_refused(mesh):
    v, f, z = mesh
    with pytest.raises(ValueError, match="16 x 16") as info:
        EditSession(v, f, z, width=8, height=64)
    check_one_sentence(str(info.value))


# ----------------------------------------------------------------------------------------- screen and frames


def decode(data: bytes) -> Image.Image:
    img = Image.open(io.BytesIO(data))
    img.load()
    return img


def test_frames_are_png_images_of_the_requested_size(session, mesh, picks):
    v, f, _ = mesh
    h, _ = picks
    version, png = session.image_bytes()
    assert version == session.version and png.startswith(PNG_SIGNATURE)
    img = decode(png)
    assert img.format == "PNG" and img.size == (WIDTH, HEIGHT) and img.mode == "RGB"
    assert session.image_bytes()[1] is png  # rendered once per version
    for scale in (2, 4):
        img = decode(session.image_bytes(scale, "png")[1])
        assert img.size == (WIDTH // scale, HEIGHT // scale)
    jpeg = decode(session.image_bytes(2, "jpeg")[1])
    assert jpeg.format == "JPEG" and jpeg.size == (WIDTH // 2, HEIGHT // 2)
    plain = session.image()
    assert plain.shape == (HEIGHT, WIDTH, 3) and np.any(plain < 250)  # the mesh is in view
    session.add_handle(h)
    session.translate_handle([0.3, 0.0, 0.0])
    version2, png2 = session.image_bytes()
    assert version2 > version and png2 != png
    ref = render(
        deformed(session),
        f,
        camera=session.view.camera,
        width=WIDTH,
        height=HEIGHT,
        scalar=session.selected_weights(),
        cmap=WEIGHT_COLORMAP,
        vmin=WEIGHT_RANGE[0],
        vmax=WEIGHT_RANGE[1],
        colorbar=False,
    )
    np.testing.assert_array_equal(session.image(), ref)


def test_pick_adds_the_vertex_under_the_cursor_and_a_drag_follows_it(session, mesh):
    v, f, _ = mesh
    x, y = session.mesh_info()["covered_pixel"]
    query = session.pick(x, y)
    assert query["hit"] and query["handle"] is None and session.handles == []
    r = session.pick(x, y, "handle")
    assert r["handle"] == 0 and session.handles == [query["vertex"]] and r["vertex"] == query["vertex"]
    assert session.pick(x + 2.0, y - 1.0, "handle")["handle"] == 0 and len(session.handles) == 1  # the marker
    hv = session.handles[0]
    start = session.view.project(v[hv][None])[0][0]
    session.drag("translate", (x, y), (x + 11.0, y - 6.0))
    end = session.view.project(deformed(session)[hv][None])[0][0]
    np.testing.assert_allclose(end - start, [11.0, -6.0], atol=1e-3)
    azimuth = session.state()["camera"]["azimuth"]
    session.drag("orbit", (0, 0), (10, 0))
    assert session.state()["camera"]["azimuth"] == pytest.approx(azimuth - 4.0)
