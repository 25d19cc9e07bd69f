"""jaxdeform.cloth.garments and the garment scenarios: meshes around the body, waistbands that follow the pelvis,
and a short paired simulation on the moving body."""

import numpy as np
import pytest

from jaxdeform.cloth import body, garments
from jaxdeform.cloth import obstacles as obst
from jaxdeform.cloth import scenarios as S


def _edges(faces):
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    return uniq, counts


def _rest_body():
    return obst.obstacles_at(body.track(body.animate([body.Motion("walk", 1.0)], 2)), 0)


@pytest.mark.parametrize("name, n_vertices, n_boundaries", [("skirt", 128, 2), ("pants", 225, 3)])
def test_garments_are_oriented_manifolds_outside_the_rest_body(name, n_vertices, n_boundaries):
    g = garments.GARMENTS[name]()
    v, f = g.vertices, g.faces
    assert v.shape == (n_vertices, 3) and f.min() == 0 and f.max() == n_vertices - 1
    edges, counts = _edges(f)
    assert counts.max() == 2  # a manifold with boundary
    # Euler characteristic of a sphere with n_boundaries holes: 2 - n_boundaries
    assert len(v) - len(edges) + len(f) == 2 - n_boundaries
    # consistent winding: every interior edge is walked once in each direction
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)
    # normals point away from the body: along the gradient of its signed distance at the face centres
    tri = v[f]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    centres = tri.mean(axis=1).astype(np.float32)
    rest = _rest_body()
    _, grad = obst.signed_distance(rest, centres)
    assert np.mean(np.sum(normals * np.asarray(grad), axis=1) > 0) > 0.99
    # the garment and its subdivision clear the body by more than the cloth's thickness
    fv, _ = S.loop_subdivide(v, f, 2)
    for pts in (v, fv):
        d, _ = obst.signed_distance(rest, pts.astype(np.float32))
        assert float(np.min(d)) > S.PARAMS.thickness
    # the waistband is a boundary loop at the waist, around the torso
    boundary = set(edges[counts == 1].ravel().tolist())
    assert set(g.waist.tolist()) <= boundary
    np.testing.assert_allclose(v[g.waist, 1], v[:, 1].max())


def test_fine_waist_is_the_subdivided_waistband():
    g = garments.skirt()
    for levels in (1, 2):
        fv, ff = S.loop_subdivide(g.vertices, g.faces, levels)
        w = garments.fine_waist(g.waist, ff)
        assert set(g.waist.tolist()) <= set(w.tolist())
        assert len(w) == len(g.waist) * 2**levels
        np.testing.assert_allclose(fv[w, 1], g.vertices[g.waist[0], 1], atol=1e-9)
    with pytest.raises(ValueError, match="not on the fine mesh's boundary"):
        garments.fine_waist(np.array([100]), ff)  # a coarse vertex inside the skirt


def test_garment_scenario_pins_ride_with_the_pelvis():
    sc = S.scenario("skirt", 3, n_frames=40, levels=1)
    assert sc.meta["kind"] == "skirt" and len(sc.meta["program"]) >= 1
    assert sc.meta["coarse_vertices"] == 128 and sc.meta["pinned_coarse"] == 16
    x0 = np.asarray(sc.x0_coarse)
    held = S.pin_track(sc, x0)
    np.testing.assert_allclose(held[0], x0, atol=1e-6)  # frame 0: the rest pose
    anim_pelvis = np.asarray(sc.track.capsule_a[:, 1])  # the torso capsule starts at the pelvis joint
    rest_pelvis = body.rest_pose()[0][body.J["pelvis"]]
    rot, trans = sc.attach
    np.testing.assert_allclose(np.einsum("tij,j->ti", rot, rest_pelvis) + trans, anim_pelvis, atol=1e-5)
    pair_dist = np.linalg.norm(held[:, :, None] - held[:, None], axis=-1)
    np.testing.assert_allclose(pair_dist, np.broadcast_to(pair_dist[0], pair_dist.shape), atol=1e-5)
    p = S.pins(sc)
    assert p["coarse_pin_positions"].shape == (40, 16, 3) and p["fine_pin_positions"].shape == (40, 32, 3)
    np.testing.assert_allclose(p["coarse_pin_positions"], held[:, p["coarse_pins"]], atol=1e-6)
    # the same request gives the same scenario; another index another motion
    again = S.scenario("skirt", 3, n_frames=40, levels=1)
    np.testing.assert_array_equal(again.track.capsule_a, sc.track.capsule_a)
    other = S.scenario("skirt", 4, n_frames=40, levels=1)
    assert not np.allclose(other.track.capsule_a, sc.track.capsule_a)


def test_skirt_pair_follows_the_body_without_penetrating(tmp_path):
    from jaxdeform.cloth import data as cdata

    sc = S.scenario("skirt", 0, n_frames=24, levels=1)
    sc = S.dataclasses.replace(sc, settle_frames=4)
    out = S.simulate_pair(sc, progress=False)
    assert out["coarse"].shape == (24, 128, 3) and out["fine"].shape == (24, 480, 3)
    for res in ("coarse", "fine"):
        idx = out[f"{res}_pins"]
        np.testing.assert_allclose(out[res][:, idx], out[f"{res}_pin_positions"], atol=1e-5)
        assert out["meta"][f"{res}_max_penetration"] <= 1e-3
        assert out["meta"][f"{res}_strain_max"] < 0.1
    # the hem moves with the body: the skirt's centroid follows the pelvis
    pelvis = np.asarray(sc.track.capsule_a[:, 1])
    offset = out["fine"].mean(axis=1) - pelvis
    assert np.abs(offset - offset[0]).max() < 0.15
    # stored and read back: the per-frame pin positions are part of the sequence
    cdata.write_sequence(tmp_path / "seq_000.npz", out)
    seq, _ = cdata.read_sequence(tmp_path / "seq_000.npz")
    assert seq.pins["fine_pin_positions"].shape == (24, len(out["fine_pins"]), 3)
    np.testing.assert_array_equal(seq.pins["coarse_pin_positions"], out["coarse_pin_positions"])
    bad = dict(out, fine_pin_positions=out["fine_pin_positions"][:5])
    cdata.write_sequence(tmp_path / "seq_001.npz", bad)
    with pytest.raises(Exception, match="fine pins do not match its fine mesh"):
        cdata.read_sequence(tmp_path / "seq_001.npz")


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--scenario", "skirt", "--motions", "moonwalk"], "unknown motion 'moonwalk'"),
        (["--scenario", "skirt", "--motions", "walk", "run:speed=9"], "run speed must lie in [0.0, 4.0], got 9.0."),
        (["--scenario", "pants", "--motions", "jump:height"], "a motion parameter is written NAME=VALUE"),
        (["--scenario", "skirt", "--motions", "kick:amp=big"], "kick amp must be a number"),
        (["--scenario", "skirt", "--motions", "sway:tempo=2"], "a sway motion has no parameter 'tempo'"),
        (["--scenario", "sheet", "--motions", "walk"], "motions apply to the garment scenarios (skirt, pants)"),
    ],
)
def test_simulate_refuses_malformed_motions(tmp_path, capsys, argv, message):
    from jaxdeform.cli import main

    out = tmp_path / "data"
    code = main(["cloth", "simulate", "--out", str(out), "--sequences", "2", "--quiet"] + argv)
    err = capsys.readouterr().err
    assert code == 2 and message in err and err.count("\n") == 1, err
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_motion_choices_fix_parameters_and_restrict_kinds():
    choices = garments.motion_choices("skirt", ["run:speed=3,amp=1.2", "walk"])
    assert choices == [("run", {"speed": 3.0, "amp": 1.2}), ("walk", {})]
    assert garments.motion_choices("skirt", None) is None
    program = body.random_program(np.random.default_rng(1), 30.0, choices)
    assert {m.kind for m in program} == {"run", "walk"}
    assert all(m.params["speed"] == 3.0 and m.params["amp"] == 1.2 for m in program if m.kind == "run")
    sc = S.scenario("skirt", 0, n_frames=20, levels=1, motions=choices)
    assert {m["kind"] for m in sc.meta["program"]} <= {"run", "walk"} and sc.meta["motions"][0][0] == "run"
