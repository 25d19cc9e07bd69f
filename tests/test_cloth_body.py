"""jaxdeform.cloth.body: the capsule body's forward kinematics, motions, blends, track and attachments."""

import numpy as np
import pytest

from jaxdeform.cloth import body
from jaxdeform.cloth import obstacles as obst


def _animation(seed: int, n_frames: int = 240, rest_frames: int = 10) -> body.Animation:
    program = body.random_program(np.random.default_rng(seed), n_frames / 30.0)
    return body.animate(program, n_frames, rest_frames=rest_frames)


def test_rotations_are_proper_and_composed_x_of_y_of_z():
    rng = np.random.default_rng(0)
    angles = rng.uniform(-3, 3, (50, 3))
    r = body.rotations(angles)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    q = np.pi / 2
    np.testing.assert_allclose(body.rotations([q, 0, 0]) @ [0, 1, 0], [0, 0, 1], atol=1e-12)  # y -> z about x
    np.testing.assert_allclose(body.rotations([0, q, 0]) @ [0, 0, 1], [1, 0, 0], atol=1e-12)  # z -> x about y
    np.testing.assert_allclose(body.rotations([0, 0, q]) @ [1, 0, 0], [0, 1, 0], atol=1e-12)  # x -> y about z
    # z first, then y, then x
    np.testing.assert_allclose(body.rotations([q, 0, q]) @ [1, 0, 0], [0, 0, 1], atol=1e-12)


def test_rest_pose_is_the_offsets_summed_along_the_chain():
    pos, frames = body.rest_pose()
    for j in range(body.N_JOINTS):
        expected, k = np.zeros(3), j
        while k >= 0:
            expected += body.OFFSETS[k]
            k = body.PARENTS[k]
        np.testing.assert_allclose(pos[j], expected, atol=1e-12)
    np.testing.assert_allclose(frames, np.broadcast_to(np.eye(3), frames.shape))
    assert all(body.PARENTS[j] < j for j in range(1, body.N_JOINTS))  # parents come first


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bones_keep_their_lengths_and_capsules_follow_the_joints(seed):
    anim = _animation(seed)
    bones = anim.positions[:, 1:] - anim.positions[:, body.PARENTS[1:]]
    np.testing.assert_allclose(
        np.linalg.norm(bones, axis=-1),
        np.broadcast_to(np.linalg.norm(body.OFFSETS[1:], axis=-1), bones.shape[:2]),
        atol=1e-9,
    )
    f = anim.frames
    np.testing.assert_allclose(f @ np.swapaxes(f, -1, -2), np.broadcast_to(np.eye(3), f.shape), atol=1e-9)
    tr = body.track(anim)
    assert obst.n_frames(tr) == len(anim.positions) and tr.capsule_a.shape[1:] == (body.N_CAPSULES, 3)
    for c, (_, ja, jb, r) in enumerate(body.CAPSULES):
        np.testing.assert_allclose(tr.capsule_a[:, c], anim.positions[:, ja], atol=1e-6)
        np.testing.assert_allclose(tr.capsule_b[:, c], anim.positions[:, jb], atol=1e-6)
        assert np.all(tr.capsule_r[:, c] == np.float32(r))
    # a point on the torso's axis is inside the body at every frame, a point 2 m above the head is not
    mid = 0.5 * (anim.positions[:, body.J["pelvis"]] + anim.positions[:, body.J["chest"]])
    above = anim.positions[:, body.J["head"]] + [0.0, 2.0, 0.0]
    for t in range(0, len(mid), 30):
        d, _ = obst.signed_distance(obst.obstacles_at(tr, t), np.stack([mid[t], above[t]]).astype(np.float32))
        assert float(d[0]) < -0.1 and float(d[1]) > 1.5


def test_animation_starts_at_rest_then_moves_smoothly():
    rest_frames = 20
    anim = _animation(3, rest_frames=rest_frames)
    rest_pos, _ = body.rest_pose()
    # before the intro (and the smoothing's reach of 3 sigma = 6 frames) the body stands in its rest pose
    np.testing.assert_allclose(
        anim.positions[: rest_frames - 6], np.broadcast_to(rest_pos, (rest_frames - 6,) + rest_pos.shape), atol=1e-12
    )
    assert np.abs(anim.positions[rest_frames + body.INTRO_FRAMES + 30] - rest_pos).max() > 0.05
    # smooth: no joint angle changes by more than 0.3 rad between frames (a fast crouch: 0.2), through every blend
    for seed in range(5):
        a = _animation(seed).angles
        assert np.abs(np.diff(a[:, 1:], axis=0)).max() < 0.3, seed
    # a hard switch (no blend, no smoothing) between two unlike motions jumps
    program = [body.Motion("kick", 1.0), body.Motion("jump", 1.0)]
    hard = body.animate(program, 100, blend=0.0, smooth=0.0).angles
    soft = body.animate(program, 100).angles
    assert np.abs(np.diff(hard, axis=0)).max() > 2 * np.abs(np.diff(soft, axis=0)).max()


def test_walk_advances_at_its_speed_and_turn_turns_at_its_rate():
    fps, seconds = 30.0, 4.0
    n = body.INTRO_FRAMES + int(seconds * fps)
    walk = body.animate([body.Motion("walk", seconds, {"speed": 1.2})], n, fps, smooth=0.0)
    travelled = walk.root[-1] - walk.root[body.INTRO_FRAMES]
    assert travelled[2] == pytest.approx(1.2 * (n - 1 - body.INTRO_FRAMES) / fps, rel=1e-6)  # along +z, facing it
    assert abs(travelled[0]) < 1e-9
    turn = body.animate([body.Motion("turn", seconds, {"rate": -0.8})], n, fps, smooth=0.0)
    z_axis = turn.frames[:, 0, :, 2]
    heading = np.unwrap(np.arctan2(z_axis[:, 0], z_axis[:, 2]))
    assert heading[-1] - heading[body.INTRO_FRAMES] == pytest.approx(-0.8 * (n - 1 - body.INTRO_FRAMES) / fps, rel=1e-6)
    # a jump leaves the ground: the ankles rise above their rest height during the flight
    jump = body.animate([body.Motion("jump", seconds, {"height": 0.25})], n, fps)
    rest_ankle = body.rest_pose()[0][body.J["ankle_l"], 1]
    assert jump.positions[:, body.J["ankle_l"], 1].max() > rest_ankle + 0.1


def test_attached_points_ride_rigidly_with_their_joint():
    anim = _animation(4)
    rest_pos, _ = body.rest_pose()
    ring = rest_pos[0] + np.stack(
        [0.16 * np.cos(np.linspace(0, 6, 12)), np.full(12, 0.05), 0.16 * np.sin(np.linspace(0, 6, 12))], -1
    )
    carried = body.attached(anim, body.J["pelvis"], ring)
    assert carried.shape == (len(anim.positions), 12, 3)
    np.testing.assert_allclose(carried[0], ring, atol=1e-12)  # frame 0 is the rest pose
    d0 = np.linalg.norm(ring[:, None] - ring[None], axis=-1)
    d = np.linalg.norm(carried[:, :, None] - carried[:, None], axis=-1)
    np.testing.assert_allclose(d, np.broadcast_to(d0, d.shape), atol=1e-9)
    # and with the pelvis: the offset from the joint, seen in the joint's frame, never changes
    local = np.einsum("tji,tpj->tpi", anim.frames[:, 0], carried - anim.positions[:, :1])
    np.testing.assert_allclose(local, np.broadcast_to(ring - rest_pos[0], local.shape), atol=1e-9)


def test_random_programs_are_reproducible_and_within_range():
    a = body.random_program(np.random.default_rng(7), 20.0)
    b = body.random_program(np.random.default_rng(7), 20.0)
    assert a == b and sum(m.seconds for m in a) >= 20.0
    kinds = set()
    for seed in range(10):
        for m in body.random_program(np.random.default_rng(seed), 20.0):
            kinds.add(m.kind)
            assert m.resolved().keys() == body.MOTIONS[m.kind].keys()
    assert kinds == set(body.MOTIONS)
    only = body.random_program(np.random.default_rng(0), 10.0, kinds=("walk",))
    assert {m.kind for m in only} == {"walk"}


@pytest.mark.parametrize(
    "motion, message",
    [
        (body.Motion("moonwalk", 2.0), "unknown motion 'moonwalk'"),
        (body.Motion("walk", 0.0), "lasts 0.2 to 60 seconds"),
        (body.Motion("walk", float("nan")), "lasts 0.2 to 60 seconds"),
        (body.Motion("walk", 2.0, {"height": 0.2}), "has no parameter 'height'"),
        (body.Motion("walk", 2.0, {"speed": 9.0}), "walk speed must lie in [0.0, 1.6]"),
        (body.Motion("jump", 2.0, {"height": float("inf")}), "jump height must lie in"),
        (body.Motion("kick", 2.0, {"amp": "big"}), "kick amp must be a number"),
    ],
)
def test_malformed_motions_are_refused_in_one_sentence(motion, message):
    with pytest.raises(body.BodyError, match=None) as err:
        body.animate([motion], 50)
    text = str(err.value)
    assert message in text and text.endswith(".") and "\n" not in text


def test_malformed_animations_are_refused():
    with pytest.raises(body.BodyError, match="at least one motion"):
        body.animate([], 50)
    with pytest.raises(body.BodyError, match="at least 2 frames"):
        body.animate([body.Motion("walk", 2.0)], 1)
    with pytest.raises(body.BodyError, match="non-negative"):
        body.animate([body.Motion("walk", 2.0)], 50, blend=-1.0)


def test_capsule_meshes_are_closed_outward_and_on_the_capsule():
    a, b, r = np.array([0.1, 0.2, 0.3]), np.array([0.5, -0.2, 0.1]), 0.07
    v, f = body.capsule_mesh(a, b, r, n_around=16, n_lat=6)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert np.all(counts == 2)  # closed
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)  # consistently wound
    tri = v[f]
    volume = np.sum(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))) / 6.0
    exact = np.pi * r**2 * np.linalg.norm(b - a) + 4.0 / 3.0 * np.pi * r**3
    assert 0.9 * exact < volume < exact  # outward (positive) and inscribed
    caps = obst.make(capsules=[(a, b, r)], dtype=np.float64)
    d, _ = obst.signed_distance(caps, v)
    np.testing.assert_allclose(np.asarray(d), 0.0, atol=1e-9)  # every vertex on the surface
    anim = _animation(0, n_frames=40)
    tr = body.track(anim)
    sv, sf = body.capsules_mesh(tr.capsule_a[20], tr.capsule_b[20], tr.capsule_r[20])
    assert sf.max() == len(sv) - 1 and len(sv) == body.N_CAPSULES * (2 * 4 * 12 + 2)
