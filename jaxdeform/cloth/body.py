"""An animated body of capsules for the garment scenes (seed 002): a forward-kinematics skeleton, procedural
motions and their blends.

Coordinates are metres, y up; the body stands on y = 0 facing +z in its rest pose, a T pose (arms along +x and -x,
the body's left on +x). The skeleton has :data:`N_JOINTS` joints (:data:`JOINTS`, each after its parent); a pose
is one rotation per joint, given as angles (rx, ry, rz) in radians about the parent frame's x, y and z axes and
composed R = Rx Ry Rz (a bone turns about z, then y, then x), plus the root's position and heading (a turn about y). Forward kinematics puts joint j at
p_j = p_parent + R_parent o_j (o_j its rest offset) and gives it the frame R_j = R_parent Rx Ry Rz.

The body is :data:`N_CAPSULES` capsules between joints (:data:`CAPSULES`: pelvis, torso, head, thighs, shins,
upper arms, forearms), the shapes :mod:`jaxdeform.cloth.obstacles` collides cloth with. A *motion* is a function of
time and a few parameters (:data:`MOTIONS`: walk, run, jump, turn, kick, sway; :class:`Motion`); a *program* is
a list of them, played one after another with smooth blends (:func:`animate`): the pose is held at rest, moves
from rest into the first motion over :data:`INTRO_FRAMES` frames (the paper interpolates 15 frames from the T pose
into each motion), and the joint angles are then smoothed by a Gaussian in time. The root advances by integrating
each motion's forward speed along the current heading, so blends never make it jump.

Everything here is host numpy, vectorised over frames; :func:`random_program` draws a program from a generator.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from . import obstacles as obst
from .obstacles import Obstacles

#: Joint names, each after its parent (:data:`PARENTS`).
JOINTS = (
    "pelvis",
    "chest",
    "head",
    "hip_l",
    "knee_l",
    "ankle_l",
    "hip_r",
    "knee_r",
    "ankle_r",
    "shoulder_l",
    "elbow_l",
    "wrist_l",
    "shoulder_r",
    "elbow_r",
    "wrist_r",
)
N_JOINTS = len(JOINTS)
J = {name: k for k, name in enumerate(JOINTS)}
PARENTS = np.array([-1, 0, 1, 0, 3, 4, 0, 6, 7, 1, 9, 10, 1, 12, 13])
#: Rest offsets from the parent joint (the pelvis: its height above the ground).
OFFSETS = np.array(
    [
        [0.0, 0.95, 0.0],
        [0.0, 0.42, 0.0],
        [0.0, 0.26, 0.0],
        [0.10, -0.06, 0.0],
        [0.0, -0.42, 0.0],
        [0.0, -0.41, 0.0],
        [-0.10, -0.06, 0.0],
        [0.0, -0.42, 0.0],
        [0.0, -0.41, 0.0],
        [0.19, -0.02, 0.0],
        [0.28, 0.0, 0.0],
        [0.25, 0.0, 0.0],
        [-0.19, -0.02, 0.0],
        [-0.28, 0.0, 0.0],
        [-0.25, 0.0, 0.0],
    ]
)
#: Capsules (name, joint a, joint b, radius in metres); the head runs from the neck (chest) to the head joint.
CAPSULES = (
    ("pelvis", J["hip_l"], J["hip_r"], 0.12),
    ("torso", J["pelvis"], J["chest"], 0.14),
    ("head", J["chest"], J["head"], 0.09),
    ("thigh_l", J["hip_l"], J["knee_l"], 0.07),
    ("shin_l", J["knee_l"], J["ankle_l"], 0.05),
    ("thigh_r", J["hip_r"], J["knee_r"], 0.07),
    ("shin_r", J["knee_r"], J["ankle_r"], 0.05),
    ("upper_arm_l", J["shoulder_l"], J["elbow_l"], 0.05),
    ("forearm_l", J["elbow_l"], J["wrist_l"], 0.04),
    ("upper_arm_r", J["shoulder_r"], J["elbow_r"], 0.05),
    ("forearm_r", J["elbow_r"], J["wrist_r"], 0.04),
)
N_CAPSULES = len(CAPSULES)
#: Frames from the rest pose into the first motion (the paper's 15).
INTRO_FRAMES = 15

#: The motions and, per parameter, (least, default, largest): ``freq`` cycles per second, ``amp`` the swing's
#: scale (1 = the motion's typical size), ``speed`` forward metres per second, ``rate`` turning radians per
#: second (sign: direction), ``side`` +1 left / -1 right (kick), ``height`` jump height in metres.
MOTIONS = {
    "walk": {"freq": (0.6, 0.9, 1.2), "amp": (0.3, 1.0, 1.4), "speed": (0.0, 1.0, 1.6)},
    "run": {"freq": (1.0, 1.4, 1.8), "amp": (0.3, 1.0, 1.3), "speed": (0.0, 2.5, 4.0)},
    "jump": {"freq": (0.5, 0.8, 1.2), "height": (0.0, 0.15, 0.3)},
    "turn": {"freq": (0.6, 0.9, 1.2), "rate": (-1.5, 1.0, 1.5)},
    "kick": {"freq": (0.3, 0.6, 1.0), "amp": (0.3, 1.0, 1.3), "side": (-1.0, 1.0, 1.0)},
    "sway": {"freq": (0.3, 0.6, 1.0), "amp": (0.3, 1.0, 1.5)},
}


class BodyError(ValueError):
    """A motion or program is malformed (unknown motion or parameter, value out of range, bad duration)."""


@dataclasses.dataclass(frozen=True)
class Motion:
    """One motion of a program: its kind (a key of :data:`MOTIONS`), its duration in seconds, and its parameters
    (missing ones take the defaults of :data:`MOTIONS`)."""

    kind: str
    seconds: float
    params: dict = dataclasses.field(default_factory=dict)

    def resolved(self) -> dict:
        """The checked parameters with the defaults filled in; :class:`BodyError` (one sentence) otherwise."""
        if self.kind not in MOTIONS:
            raise BodyError(f"unknown motion '{self.kind}'; expected one of {', '.join(MOTIONS)}.")
        if not (np.isfinite(self.seconds) and 0.2 <= self.seconds <= 60.0):
            raise BodyError(f"a {self.kind} motion lasts 0.2 to 60 seconds, got {self.seconds}.")
        spec = MOTIONS[self.kind]
        unknown = sorted(set(self.params) - set(spec))
        if unknown:
            raise BodyError(f"a {self.kind} motion has no parameter '{unknown[0]}'; it takes {', '.join(spec)}.")
        out = {}
        for name, (lo, default, hi) in spec.items():
            value = self.params.get(name, default)
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise BodyError(f"{self.kind} {name} must be a number, got {value!r}.") from None
            if not (np.isfinite(value) and lo <= value <= hi):
                raise BodyError(f"{self.kind} {name} must lie in [{lo}, {hi}], got {value}.")
            out[name] = value
        return out


class Animation(NamedTuple):
    """A body animation of T frames: joint positions ``(T, J, 3)``, joint frames ``(T, J, 3, 3)`` (columns: the
    joint's axes in the world), and the local angles ``(T, J, 3)`` and root path ``(T, 3)`` it was made from."""

    positions: np.ndarray
    frames: np.ndarray
    angles: np.ndarray
    root: np.ndarray


def rotations(angles) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of angles ``(..., 3)``: Rx(rx) Ry(ry) Rz(rz)."""
    a = np.asarray(angles, np.float64)
    cx, cy, cz = np.cos(a[..., 0]), np.cos(a[..., 1]), np.cos(a[..., 2])
    sx, sy, sz = np.sin(a[..., 0]), np.sin(a[..., 1]), np.sin(a[..., 2])
    one, zero = np.ones_like(cx), np.zeros_like(cx)
    rx = np.stack([one, zero, zero, zero, cx, -sx, zero, sx, cx], -1).reshape(a.shape[:-1] + (3, 3))
    ry = np.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], -1).reshape(a.shape[:-1] + (3, 3))
    rz = np.stack([cz, -sz, zero, sz, cz, zero, zero, zero, one], -1).reshape(a.shape[:-1] + (3, 3))
    return rx @ ry @ rz


def forward_kinematics(angles, root) -> tuple[np.ndarray, np.ndarray]:
    """Joint positions and frames of poses.

    **Arguments:**

    - ``angles``: ``(T, J, 3)`` local angles (module docstring); the pelvis's include the heading (its ry).
    - ``root``: ``(T, 3)`` the pelvis's world position.

    **Returns:**

    ``(positions (T, J, 3), frames (T, J, 3, 3))``.
    """
    local = rotations(angles)
    T = local.shape[0]
    pos = np.zeros((T, N_JOINTS, 3))
    frames = np.zeros((T, N_JOINTS, 3, 3))
    pos[:, 0] = root
    frames[:, 0] = local[:, 0]
    for j in range(1, N_JOINTS):  # over the 15 joints, vectorised over frames
        p = PARENTS[j]
        pos[:, j] = pos[:, p] + frames[:, p] @ OFFSETS[j]
        frames[:, j] = frames[:, p] @ local[:, j]
    return pos, frames


def rest_pose() -> tuple[np.ndarray, np.ndarray]:
    """The rest (T) pose's joint positions ``(J, 3)`` and frames ``(J, 3, 3)``."""
    pos, frames = forward_kinematics(np.zeros((1, N_JOINTS, 3)), OFFSETS[:1])
    return pos[0], frames[0]


def _pose(kind: str, p: dict, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One motion at times ``t`` (seconds from its start): the local angles ``(T, J, 3)`` (the heading excluded) and
    the drive ``(T, 3)``: forward speed (m/s), turning rate (rad/s) and the pelvis's height change (m)."""
    w = 2.0 * np.pi * p.get("freq", 1.0) * t
    a = np.zeros(t.shape + (N_JOINTS, 3))
    speed = np.zeros_like(t)
    rate = np.zeros_like(t)
    lift = np.zeros_like(t)
    arms_down = 1.2  # rad: arms from the T pose to the sides (about z, shoulders)
    a[:, J["shoulder_l"], 2] = -arms_down
    a[:, J["shoulder_r"], 2] = arms_down
    if kind in ("walk", "run", "turn"):
        s = {"walk": 0.45, "run": 0.75, "turn": 0.25}[kind] * p.get("amp", 1.0)
        knee = {"walk": 0.6, "run": 1.3, "turn": 0.5}[kind] * p.get("amp", 1.0)
        for side, phase in (("l", 0.0), ("r", np.pi)):
            hip = s * np.sin(w + phase)
            a[:, J["hip_" + side], 0] = -hip  # forward swing: -rx lifts the leg towards +z
            a[:, J["knee_" + side], 0] = knee * np.clip(np.sin(w + phase + 1.2), 0.0, None) + 0.05
            a[:, J["shoulder_" + side], 0] = 0.8 * hip  # arms swing against the legs
            a[:, J["elbow_" + side], 1] = (1.3 if kind == "run" else 0.3) * (-1 if side == "l" else 1)  # bent forward
        a[:, J["chest"], 0] = {"walk": 0.05, "run": 0.2, "turn": 0.0}[kind]
        a[:, J["chest"], 1] = 0.1 * s * np.sin(w)
        lift = (0.015 if kind == "walk" else 0.04) * p.get("amp", 1.0) * np.cos(2 * w)
        speed = np.full_like(t, p.get("speed", 0.0))
        rate = np.full_like(t, p.get("rate", 0.0))
    elif kind == "jump":
        phase = np.mod(p["freq"] * t, 1.0)  # crouch in [0, 0.3), flight [0.3, 0.7), landing [0.7, 1)
        crouch = np.where(phase < 0.3, np.sin(np.pi * phase / 0.3), 0.0) + np.where(
            phase >= 0.7, np.sin(np.pi * (phase - 0.7) / 0.3), 0.0
        )
        flight = np.where((phase >= 0.3) & (phase < 0.7), np.sin(np.pi * (phase - 0.3) / 0.4), 0.0)
        for side in ("l", "r"):
            a[:, J["hip_" + side], 0] = -0.8 * crouch
            a[:, J["knee_" + side], 0] = 1.4 * crouch
            a[:, J["ankle_" + side], 0] = -0.5 * crouch
            a[:, J["shoulder_" + side], 0] = -1.2 * flight + 0.5 * crouch
        a[:, J["chest"], 0] = 0.3 * crouch
        lift = p["height"] * flight - 0.18 * crouch
    elif kind == "kick":
        side = "l" if p["side"] > 0 else "r"
        other = "r" if side == "l" else "l"
        kick = np.sin(np.pi * np.mod(p["freq"] * t, 1.0)) ** 2
        a[:, J["hip_" + side], 0] = -1.3 * p["amp"] * kick
        a[:, J["knee_" + side], 0] = 0.9 * p["amp"] * np.sin(2 * np.pi * np.mod(p["freq"] * t, 1.0)) ** 2
        a[:, J["knee_" + other], 0] = 0.15 * kick
        a[:, J["chest"], 0] = -0.15 * kick
        a[:, J["shoulder_" + side], 0] = 0.6 * kick
        a[:, J["shoulder_" + other], 0] = -0.6 * kick
        a[:, J["shoulder_l"], 2] += 0.5 * kick
        a[:, J["shoulder_r"], 2] -= 0.5 * kick
    elif kind == "sway":
        s = p["amp"]
        a[:, 0, 2] = 0.12 * s * np.sin(w)  # the pelvis rolls
        a[:, J["chest"], 2] = -0.2 * s * np.sin(w)  # the chest leans the other way
        a[:, J["chest"], 1] = 0.25 * s * np.sin(0.5 * w)
        a[:, J["hip_l"], 2] = -0.12 * s * np.sin(w)
        a[:, J["hip_r"], 2] = -0.12 * s * np.sin(w)
        a[:, J["knee_l"], 0] = 0.25 * s * np.clip(np.sin(w), 0.0, None)
        a[:, J["knee_r"], 0] = 0.25 * s * np.clip(-np.sin(w), 0.0, None)
        a[:, J["shoulder_l"], 2] += 0.9 * s * (0.5 + 0.5 * np.sin(w))
        a[:, J["shoulder_r"], 2] -= 0.9 * s * (0.5 - 0.5 * np.sin(w))
        a[:, J["elbow_l"], 1] = -0.3 * s * (1.0 + np.sin(w + 0.5))
        a[:, J["elbow_r"], 1] = 0.3 * s * (1.0 + np.sin(w - 0.5))
    return a, np.stack([speed, rate, lift], -1)


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _gaussian_smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    """``x`` (T, ...) convolved in time with a normalised Gaussian of ``sigma`` frames, cut at 3 sigma (edges held)."""
    if sigma <= 0:
        return x
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(x, sigma, axis=0, mode="nearest", radius=int(np.ceil(3 * sigma)))


def animate(
    program, n_frames: int, fps: float = 30.0, *, rest_frames: int = 0, blend: float = 0.5, smooth: float = 2.0
) -> Animation:
    """A body animation from a program of motions.

    **Arguments:**

    - ``program``: :class:`Motion` values, played in order (the last one continues if the frames outlast them).
    - ``n_frames``: frames to produce, the rest and intro frames included.
    - ``fps``: frames per second.
    - ``rest_frames``: frames held in the rest pose first (the garment settles on them).
    - ``blend``: seconds of the smooth crossfade between consecutive motions.
    - ``smooth``: the Gaussian's width in frames (0: none).

    **Returns:**

    The :class:`Animation`; frame 0 is the rest pose, frames ``rest_frames + INTRO_FRAMES`` on play the program.

    **Raises:**

    :class:`BodyError` (one sentence) for an empty or malformed program or bad frame counts.
    """
    program = list(program)
    if not program:
        raise BodyError("a body program needs at least one motion.")
    params = [m.resolved() for m in program]
    if n_frames < 2 or rest_frames < 0 or not (np.isfinite(fps) and fps > 0):
        raise BodyError(f"an animation needs at least 2 frames and a positive frame rate, got {n_frames} at {fps}.")
    if not (np.isfinite(blend) and blend >= 0 and np.isfinite(smooth) and smooth >= 0):
        raise BodyError("the blend and smoothing widths must be non-negative numbers.")
    blend = min(blend, min(m.seconds for m in program))  # a crossfade no longer than the shortest motion
    start = rest_frames + INTRO_FRAMES
    t = np.maximum(np.arange(n_frames) - start, 0) / fps  # program time; the intro holds the program's first pose
    ends = np.cumsum([m.seconds for m in program])
    begins = np.concatenate([[0.0], ends[:-1]])
    angles = np.zeros((n_frames, N_JOINTS, 3))
    drive = np.zeros((n_frames, 3))
    weight_sum = np.zeros(n_frames)
    for k, (m, p) in enumerate(zip(program, params)):  # over the program's few motions
        a, d = _pose(m.kind, p, t - begins[k])
        fade_in = 1.0 if k == 0 else _smoothstep((t - begins[k]) / max(blend, 1e-9) + 0.5)
        fade_out = 1.0 if k == len(program) - 1 else 1.0 - _smoothstep((t - ends[k]) / max(blend, 1e-9) + 0.5)
        w = np.broadcast_to(fade_in * fade_out, t.shape)
        angles += w[:, None, None] * a
        drive += w[:, None] * d
        weight_sum += w
    angles /= weight_sum[:, None, None]
    drive /= weight_sum[:, None]
    intro = _smoothstep((np.arange(n_frames) - rest_frames) / INTRO_FRAMES)
    angles *= intro[:, None, None]
    drive *= intro[:, None]
    angles = _gaussian_smooth(angles, smooth)
    drive = _gaussian_smooth(drive, smooth)
    playing = np.arange(n_frames) >= start
    heading = np.cumsum(np.where(playing, drive[:, 1], 0.0)) / fps
    forward = np.stack([np.sin(heading), np.zeros_like(heading), np.cos(heading)], -1)
    step = np.where(playing, drive[:, 0], 0.0)[:, None] * forward / fps
    root = OFFSETS[0] + np.cumsum(step, 0)
    root[:, 1] += drive[:, 2]
    full = angles.copy()
    full[:, 0, 1] += heading
    positions, frames = forward_kinematics(full, root)
    return Animation(positions, frames, full, root)


def track(anim: Animation, dtype=np.float32) -> Obstacles:
    """The body's capsules as an obstacle track (one entry per frame, no ground plane)."""
    a = np.stack([anim.positions[:, ja] for _, ja, _, _ in CAPSULES], 1)
    b = np.stack([anim.positions[:, jb] for _, _, jb, _ in CAPSULES], 1)
    r = np.broadcast_to(np.array([c[3] for c in CAPSULES]), a.shape[:2])
    T = a.shape[0]
    base = obst.static_track(obst.empty(dtype=dtype), T)
    return base._replace(
        capsule_a=a.astype(dtype), capsule_b=b.astype(dtype), capsule_r=np.ascontiguousarray(r, dtype=dtype)
    )


def attached(anim: Animation, joint: int, points) -> np.ndarray:
    """Points ``(P, 3)`` given in the rest pose carried rigidly by ``joint``'s frame: ``(T, P, 3)``."""
    rest_pos, rest_frames = rest_pose()
    local = (np.asarray(points, np.float64) - rest_pos[joint]) @ rest_frames[joint]
    return anim.positions[:, joint, None, :] + np.einsum("tij,pj->tpi", anim.frames[:, joint], local)


def parse_motion(text: str) -> tuple[str, dict]:
    """A motion choice written ``KIND`` or ``KIND:NAME=VALUE,...`` (e.g. ``run:speed=3,amp=1.2``): the kind and the
    parameters it fixes, checked against :data:`MOTIONS`; :class:`BodyError` (one sentence) otherwise."""
    kind, _, rest = str(text).strip().partition(":")
    params = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        name, eq, value = item.partition("=")
        if not eq or not name.strip():
            raise BodyError(f"a motion parameter is written NAME=VALUE, got '{item}' in '{text}'.")
        params[name.strip()] = value.strip()
    resolved = Motion(kind, 1.0, params).resolved()  # unknown kind or parameter, a value out of range: one sentence
    return kind, {k: resolved[k] for k in params}


def random_program(rng: np.random.Generator, seconds: float, kinds=tuple(MOTIONS), min_s=2.0, max_s=4.0) -> list:
    """Motions of random kinds, durations and parameters (uniform within :data:`MOTIONS`' ranges) filling
    ``seconds``. ``kinds``: the choices, each a kind or a ``(kind, fixed parameters)`` pair (:func:`parse_motion`)
    whose fixed parameters are kept."""
    choices = [(k, {}) if isinstance(k, str) else (k[0], dict(k[1])) for k in kinds]
    out, total = [], 0.0
    while total < seconds:
        kind, fixed = choices[int(rng.integers(len(choices)))]
        dur = float(rng.uniform(min_s, max_s))
        params = {}
        for name, (lo, _, hi) in MOTIONS[kind].items():
            params[name] = float(rng.choice([-1.0, 1.0])) if name == "side" else float(rng.uniform(lo, hi))
        params.update(fixed)
        out.append(Motion(kind, dur, params))
        total += dur
    return out


def capsule_mesh(a, b, radius: float, n_around: int = 12, n_lat: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A triangle mesh of the capsule of segment ``a``-``b`` and ``radius``, for figures: two hemispheres of
    ``n_lat`` rings of ``n_around`` vertices and a pole each, joined by the cylinder; faces oriented outward.

    **Returns:** ``(vertices (2 n_lat n_around + 2, 3), faces (F, 3))``."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    axis = b - a
    length = float(np.linalg.norm(axis))
    w = axis / length if length > 1e-12 else np.array([0.0, 1.0, 0.0])
    u = np.cross(w, [1.0, 0.0, 0.0] if abs(w[0]) < 0.9 else [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    th = 2.0 * np.pi * np.arange(n_around) / n_around
    around = np.cos(th)[:, None] * u + np.sin(th)[:, None] * v  # (n_around, 3)
    lower = np.linspace(-np.pi / 2, 0.0, n_lat + 1)[1:]
    upper = np.linspace(0.0, np.pi / 2, n_lat + 1)[:-1]
    rings = [a + radius * (np.cos(p) * around + np.sin(p) * w) for p in lower]
    rings += [b + radius * (np.cos(p) * around + np.sin(p) * w) for p in upper]
    verts = np.concatenate(rings + [(a - radius * w)[None], (b + radius * w)[None]])
    n_rings = len(rings)
    idx = np.arange(n_rings * n_around).reshape(n_rings, n_around)
    k = np.arange(n_around)
    k1 = (k + 1) % n_around
    faces = []
    for r in range(n_rings - 1):  # over the capsule's few rings
        lo, hi = idx[r], idx[r + 1]
        faces += [np.stack([lo[k], lo[k1], hi[k1]], 1), np.stack([lo[k], hi[k1], hi[k]], 1)]
    south, north = n_rings * n_around, n_rings * n_around + 1
    faces += [np.stack([np.full(n_around, south), idx[0][k1], idx[0][k]], 1)]
    faces += [np.stack([np.full(n_around, north), idx[-1][k], idx[-1][k1]], 1)]
    return verts, np.concatenate(faces).astype(np.int64)


def capsules_mesh(capsule_a, capsule_b, capsule_r) -> tuple[np.ndarray, np.ndarray]:
    """One mesh of every capsule of one instant (``(C, 3)``, ``(C, 3)``, ``(C,)``), for figures."""
    verts, faces, n = [], [], 0
    for a, b, r in zip(np.asarray(capsule_a), np.asarray(capsule_b), np.asarray(capsule_r)):
        cv, cf = capsule_mesh(a, b, float(r))
        verts.append(cv)
        faces.append(cf + n)
        n += len(cv)
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.concatenate(verts), np.concatenate(faces)
