"""The paired SHEET, DISK, SKIRT and PANTS scenes of seed 002 (Sec. 4, "Datasets"): coarse and fine cloth simulated
separately.

Meshes (metres):
- SHEET: a 1 m x 1 m square in the plane z = 0, x in [-0.5, 0.5], y in [0.4, 1.4]; coarse = regular 9 x 9 grid
  (81 vertices, 128 triangles, edge 0.125 m), fine = 3 x Loop subdivision (``igl.loop``) = 65 x 65 = 4225 vertices
  (edge ~1.56 cm). Loop keeps the coarse vertices first (same indices) but moves the boundary corners inward by
  ~2 cm (the boundary rule), so the fine rest sheet has slightly rounded corners.
- DISK: a round tablecloth of radius 0.75 m; coarse = centre + 6 rings of 6, 12, 17, 22, 30, 60 vertices at
  radii k / 6 * 0.75 (148 vertices, 234 triangles, 60 on the boundary, min angle 32 deg), Delaunay-triangulated;
  fine = 3 x Loop = 7,729 vertices, 14,976 triangles -- exactly the paper's counts (for a disk, 3 Loop levels
  give 64 V - 63 - 28 B vertices, so 148 / 7,729 imply B = 60 boundary vertices).
- ``levels`` (default 3) sets the Loop levels from coarse to fine everywhere (1 for quick tests).

Scenes (every sequence is determined by (kind, index, seed) through ``np.random.default_rng``):
- SHEET: the top edge is clamped (a curtain rod: the coarse top row, the fine boundary arc between the same two
  corners; :func:`pins` gives both with their positions), the
  ground is at y = 0. An obstacle on a pendulum crashes into the sheet: a sphere of radius 0.14 / 0.20 / 0.26 m
  (index % 4 = 0, 1, 2) or a horizontal pole (capsule, radius 0.14 m, length 0.6 m plus caps; index % 4 = 3),
  every radius above the coarse edge length so that the coarse mesh cannot let it through. The pivot sits at
  x in [-0.25, 0.25], y = 2.4, the bob's lowest point at y in [0.65, 1.05]; the swing plane turns by
  [-35, 35] degrees about y from the sheet's normal; the swing (horizontal amplitude A in [0.45, 0.75] m)
  follows phi(t) = -phi0 cos(sqrt(g / l) t) from rest, and its far turning point lies ``reach`` in
  :data:`SHEET_REACH` = [0.05, 0.25] m past the sheet's rest plane (the pivot sits A - reach behind it), so
  the obstacle strikes the sheet at ~0.5-1 m/s, pushes it out, withdraws and strikes again about one period
  (~2.4 s) later. The swing turns back just past the plane because an obstacle swinging the full A past it
  sweeps under the sheet's hem, a bifurcation that the coarse and the fine sheet take differently, so the
  Loop-upsampled coarse sheet would no longer follow the fine one.
- DISK: the cloth lies centred on a table (capped cylinder, radius 0.45 m, top at y = 0.75 m, height 0.75 m,
  rims rounded to :data:`TABLE_RIM_RADIUS` = 5 cm; ground at y = 0) with a weight in the middle (the vertices
  within 6 cm of the centre are pinned: 1 coarse vertex, the corresponding patch of fine ones). Wind blows
  horizontally from a random direction; its mean speed is index-dependent across [1, 5] m/s (jittered), ramps up
  over the first second and gusts +-30 % (periods 1.5-4 s), its direction drifts by up to +-25 degrees over the
  sequence, and the turbulence RMS is 15-35 % of the speed.

- SKIRT, PANTS (:data:`GARMENT_KINDS`): garments (:mod:`jaxdeform.cloth.garments`) worn by the animated capsule body
  of :mod:`jaxdeform.cloth.body`, which plays a random program of motions (walk, run, jump, turn, kick, sway; the
  15 intro frames from the rest pose first; :data:`GARMENT_FRAMES` frames by default). The waistband is pinned and
  rides rigidly with the pelvis (``Scenario.attach``, :func:`pin_track`); the cloth settles on the body at rest
  before the recorded frames; no wind, no ground.

Both resolutions use the same :class:`ClothParams` physics and the same obstacle / wind / pin tracks; only the
iteration budget differs (:data:`COARSE_STEPS` = 10 x 2, :data:`FINE_STEPS` = 40 x 4 (substeps,
iterations) per frame), and so does the number of obstacle contact points inside each triangle (see
:data:`MIN_OBSTACLE_RADIUS`: SHEET coarse 12 per triangle, DISK coarse 25, the fine meshes none). With these
budgets the edge strain |l / L - 1| stays below ~6 % (mean ~0.1-0.2 %) at both resolutions (20 x 4 on the
fine SHEET lets it reach ~13 %, hence 40 x 4), and no
stored SHEET or DISK frame penetrates an obstacle, at the vertices or inside the triangles
(:func:`max_penetration` with faces). A fine frame costs tens of times a coarse one.
DISK's table has a rounded rim: a sharp one gives the contact-point rule no curvature radius to work with.
Initial state: the flat rest cloth (the fine one = Loop-subdivided coarse one), settled for ``settle_frames``
frames with the obstacles at their t = 0 position and no wind, then the recorded sequence starts from the
settled positions and velocities.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time

import igl
import jax
import numpy as np

from jaxdeform.errors import JaxDeformError

from . import garments as garm
from . import obstacles as obst
from . import simulate as sim
from .obstacles import Obstacles
from .simulate import ClothParams

#: the garments worn by the animated body (:mod:`jaxdeform.cloth.garments`, :mod:`jaxdeform.cloth.body`)
GARMENT_KINDS = tuple(garm.GARMENTS)
KINDS = ("sheet", "disk") + GARMENT_KINDS
#: Default recorded frames per sequence (4 s at 30 frames/s); garments: the 15 intro frames and 5 s of motion.
N_FRAMES = 120
GARMENT_FRAMES = 165


def default_frames(kind: str) -> int:
    """Recorded frames of a sequence of scenario ``kind`` when none are asked for."""
    return GARMENT_FRAMES if kind in GARMENT_KINDS else N_FRAMES


#: Settling frames before recording (obstacles at t = 0, no wind).
SETTLE_FRAMES = {"sheet": 10, "disk": 30, **{k: 30 for k in GARMENT_KINDS}}
#: (substeps, iterations) per frame for the coarse meshes (per kind) and the fine ones. With frictionless contact
#: points inside the triangles DISK's coarse cloth needed 4 iterations (with 2 a gust slapping it onto the rounded
#: rim left one frame of seq_018 2.7 mm inside the table); with friction there (``ClothParams.face_friction``) 2
#: iterations leave no coarse frame of the 20 scenarios inside it.
COARSE_STEPS = {"sheet": (10, 2), "disk": (10, 2), **{k: (10, 2) for k in GARMENT_KINDS}}
FINE_STEPS = (40, 4)
#: Physical parameters shared by both resolutions (defaults of ClothParams unless listed).
PARAMS = ClothParams()
#: Per-scene physics over :data:`PARAMS`, the same for both resolutions. SHEET: a stiffer, damped fabric (bending
#: 1e-4 N m, damping 2 /s). With the defaults (5e-6 N m, 0.2 /s) the fine sheet's wrinkles buckle differently
#: from a start perturbed by 0.1 mm: on test scenarios 2 and 7 the perturbed fine cloth lies 0.40x and 0.30x as
#: far from the stored one as the upsampled coarse cloth does (damping 2 alone: 0.26x / 0.23x; bending 1e-4
#: alone: 0.27x on scenario 2), with both 0.07x and 0.004x: the fine cloth is determined by its scenario, so
#: what it adds to the coarse one can be learned (:func:`simulate_pair` against :func:`simulate_fine` with
#: ``perturbation=1e-4``, 100 frames).
#: Garments: the same fabric without tethers. A tether holds each free vertex within its rest distance of the
#: nearest pinned vertex; the waistbands of the two resolutions (16 and 128 vertices around the skirt's waist) give
#: different nearest pins and so different limits, and with them the settled coarse and fine skirts of scenario 2
#: lay 0.050 m apart (Loop-upsampled coarse against fine) against 0.019 m without them; over its 165 frames 0.039 m
#: against 0.022 m, the 0.1 mm perturbed fine cloth 0.0002 / 0.0001 m from the stored one, largest edge strain 7.6 /
#: 8.0 % (``experiments.cloth.garment_params``).
KIND_PARAMS = {
    "sheet": dict(bend_stiffness=1.0e-4, damping=2.0),
    "disk": {},
    **{k: dict(bend_stiffness=1.0e-4, damping=2.0, tethers=False) for k in GARMENT_KINDS},
}

SHEET_TOP = 1.4
SHEET_SIZE = 1.0
SHEET_N = 9
DISK_RADIUS = 0.75
DISK_RINGS = (6, 12, 17, 22, 30, 60)
TABLE_RADIUS = 0.45
TABLE_TOP = 0.75
SPHERE_RADII = (0.14, 0.20, 0.26)
POLE_RADIUS = 0.14
POLE_HALF_LENGTH = 0.3
#: Smallest curvature radius of the obstacles (m): it sets the contact points per triangle of each mesh
#: (:func:`simulate.face_samples_for`). With vertex contacts alone a coarse triangle (legs 12.5 cm) sags up to
#: r - sqrt(r^2 - R^2) into a sphere of radius r between its corners (R its circumradius; SHEET's coarse
#: triangles would sink 1.0-3.0 cm, 8-24 % of the edge, into the obstacles with vertex contacts alone). The
#: rule gives the SHEET coarse mesh the order-4 grid (4 intervals per edge, 12 points per triangle; sag 1.7 mm at
#: r = 0.14 m, inside the 5 mm thickness) and its 3-level fine mesh none (sag 0.4 mm between vertices). The rule
#: needs smooth obstacles: DISK's table rims are rounded (:data:`TABLE_RIM_RADIUS`), which gives its coarse mesh
#: the order-6 grid (25 points per triangle; sag 2.4 mm) and its 3-level fine mesh none (sag 1.7 mm). Per kind.
TABLE_RIM_RADIUS = 0.05
#: the body's thinnest capsule (the forearms)
BODY_MIN_RADIUS = 0.04
MIN_OBSTACLE_RADIUS = {
    "sheet": min(SPHERE_RADII + (POLE_RADIUS,)),
    "disk": TABLE_RIM_RADIUS,
    **{k: BODY_MIN_RADIUS for k in GARMENT_KINDS},
}
#: Range of the distance (m) the obstacle's centre travels past the sheet's rest plane before it turns back.
SHEET_REACH = (0.05, 0.25)
PIN_RADIUS_DISK = 0.06


class ScenarioError(JaxDeformError):
    """A scenario request is invalid (unknown kind, negative index, too few frames)."""


@dataclasses.dataclass(frozen=True)
class Scenario:
    """Everything needed to simulate one paired sequence (host arrays)."""

    kind: str
    index: int
    seed: int
    n_frames: int
    settle_frames: int
    track: Obstacles  # (T, ...) per stored frame
    wind: np.ndarray  # (T, 3) mean wind per frame, m/s
    params: ClothParams  # physics (coarse substeps/iterations); the fine run replaces them by FINE_STEPS
    pinned_coarse: np.ndarray  # (Vc,) bool
    pinned_fine: np.ndarray  # (Vf,) bool
    x0_coarse: np.ndarray  # (Vc, 3) initial (pre-settling) positions
    meta: dict
    levels: int = 3  # Loop subdivision levels from the coarse to the fine mesh (3: the paper's resolutions)
    #: garments: the pins' rigid motion (rotation (T, 3, 3), translation (T, 3)) from their start positions;
    #: None: the pins stay where they were placed
    attach: tuple | None = None

    @property
    def key(self):
        return jax.random.PRNGKey(_seed_int(self.kind, self.index, self.seed))


def _seed_int(kind: str, index: int, seed: int) -> int:
    return int(np.random.default_rng([KINDS.index(kind), index, seed]).integers(0, 2**31 - 1))


# ----------------------------------------------------------------------------------------------------- meshes


def _grid(n: int, size: float, top: float):
    u = np.linspace(-size / 2, size / 2, n)
    y = np.linspace(top - size, top, n)
    X, Y = np.meshgrid(u, y, indexing="ij")
    verts = np.stack([X.ravel(), Y.ravel(), np.zeros(n * n)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return verts, faces


def _disk():
    from scipy.spatial import Delaunay

    pts = [np.zeros(2)]
    golden = math.pi * (3 - math.sqrt(5))
    for k, n in enumerate(DISK_RINGS, start=1):
        r = DISK_RADIUS * k / len(DISK_RINGS)
        th = 2 * math.pi * np.arange(n) / n + k * golden
        pts.append(np.stack([r * np.cos(th), r * np.sin(th)], 1))
    p2 = np.concatenate([np.atleast_2d(p) for p in pts])
    tri = Delaunay(p2).simplices
    verts = np.stack([p2[:, 0], np.zeros(len(p2)), p2[:, 1]], 1)
    # orient every triangle with its normal up (+y)
    a, b, c = verts[tri[:, 0]], verts[tri[:, 1]], verts[tri[:, 2]]
    flip = np.cross(b - a, c - a)[:, 1] < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    return verts, tri


def loop_subdivide(verts, faces, levels: int = 3):
    """Loop subdivision by ``igl.loop`` (original vertices first).

    **Arguments:**

    - ``verts``: ``(V, 3)``.
    - ``faces``: ``(F, 3)``.
    - ``levels``: the number of subdivisions.

    **Returns:**

    ``(positions (V', 3) float64, faces (F', 3) int64)``.
    """
    v, f = igl.loop(np.ascontiguousarray(verts, np.float64), np.ascontiguousarray(faces, np.int64), levels)
    return np.asarray(v), np.asarray(f)


@functools.cache
def _meshes(kind: str, levels: int = 3):
    if kind == "sheet":
        cv, cf = _grid(SHEET_N, SHEET_SIZE, SHEET_TOP)
    elif kind == "disk":
        cv, cf = _disk()
    elif kind in GARMENT_KINDS:
        g = garm.GARMENTS[kind]()
        cv, cf = g.vertices, g.faces
    else:
        raise ScenarioError(f"Unknown scenario kind {kind!r}; expected one of {KINDS}.")
    if levels < 1:
        raise ScenarioError(f"the fine mesh needs at least 1 Loop level, got {levels}.")
    fv, ff = loop_subdivide(cv, cf, levels)
    return cv, cf.astype(np.int64), fv, ff


def meshes(kind: str, levels: int = 3):
    """Rest meshes of a scenario kind (host numpy).

    **Arguments:**

    - ``kind``: ``"sheet"`` or ``"disk"``.
    - ``levels``: Loop subdivisions from coarse to fine (3: the paper's resolutions; fewer for quick tests).

    **Returns:**

    ``(coarse_v, coarse_f, fine_v, fine_f)``, float64 / int64.

    **Raises:**

    ``ScenarioError`` for an unknown kind or ``levels < 1``.
    """
    return tuple(np.array(a) for a in _meshes(kind, levels))


@functools.cache
def models(kind: str, levels: int = 3) -> tuple[sim.ClothModel, sim.ClothModel]:
    """The coarse and fine :class:`ClothModel` of a kind (built once per process).

    **Arguments:**

    - ``kind``: ``"sheet"`` or ``"disk"``.
    - ``levels``: Loop subdivisions from coarse to fine.

    **Returns:**

    ``(coarse model, fine model)``.
    """
    cv, cf, fv, ff = _meshes(kind, levels)
    return sim.build_model(cv, cf), sim.build_model(fv, ff)


def _pins(kind: str, levels: int = 3):
    cv, cf, fv, ff = _meshes(kind, levels)
    if kind == "sheet":
        # coarse: the top row; fine: the boundary arc between the same two corners (Loop keeps their indices
        # first but rounds the corners, so the fine rod follows the subdivided top edge)
        pc = cv[:, 1] > SHEET_TOP - 1e-6
        corners = np.flatnonzero(pc)[[0, -1]]
        loop = np.asarray(igl.boundary_loop(np.ascontiguousarray(ff, np.int64)))
        i, j = sorted(int(np.flatnonzero(loop == c)[0]) for c in corners)
        arcs = [loop[i : j + 1], np.concatenate([loop[j:], loop[: i + 1]])]
        arc = max(arcs, key=lambda a: fv[a, 1].mean())
        pf = np.zeros(len(fv), bool)
        pf[arc] = True
    elif kind == "disk":
        pc = np.linalg.norm(cv[:, [0, 2]], axis=1) < PIN_RADIUS_DISK
        pf = np.linalg.norm(fv[:, [0, 2]], axis=1) < PIN_RADIUS_DISK
    else:  # a garment: its waistband
        waist = garm.GARMENTS[kind]().waist
        pc = np.zeros(len(cv), bool)
        pc[waist] = True
        pf = np.zeros(len(fv), bool)
        pf[garm.fine_waist(waist, ff)] = True
    return pc, pf


# --------------------------------------------------------------------------------------------------- scenes


def _sheet_track(rng, index: int, T: int, dt: float):
    g = PARAMS.gravity
    kind = ("sphere", "sphere", "sphere", "pole")[index % 4]
    radius = SPHERE_RADII[index % 4] if kind == "sphere" else POLE_RADIUS
    pivot = np.array([rng.uniform(-0.25, 0.25), 2.4, 0.0])
    low = rng.uniform(0.65, 1.05)
    length = pivot[1] - low
    amp = rng.uniform(0.45, 0.75)
    phi0 = math.asin(min(amp / length, 0.95))
    yaw = math.radians(rng.uniform(-35.0, 35.0))
    swing = np.array([math.sin(yaw), 0.0, math.cos(yaw)])  # horizontal direction of the swing plane
    reach = rng.uniform(*SHEET_REACH)  # how far the bob's centre passes the sheet's rest plane
    pivot = pivot - (amp - reach) * swing
    side = np.cross(swing, [0.0, 1.0, 0.0])
    omega = math.sqrt(g / length)
    t = np.arange(T) * dt
    phi = -phi0 * np.cos(omega * t)
    bob = pivot[None] + length * (np.sin(phi)[:, None] * swing[None] - np.cos(phi)[:, None] * np.array([0, 1.0, 0]))
    frames = []
    for b in bob:
        if kind == "sphere":
            frames.append(obst.make(spheres=[(b, radius)], ground=0.0))
        else:
            frames.append(
                obst.make(capsules=[(b - POLE_HALF_LENGTH * side, b + POLE_HALF_LENGTH * side, radius)], ground=0.0)
            )
    meta = dict(
        obstacle=kind,
        radius=radius,
        pivot=pivot.tolist(),
        pendulum_length=length,
        amplitude_m=amp,
        amplitude_rad=phi0,
        yaw_deg=math.degrees(yaw),
        period_s=2 * math.pi / omega,
        max_speed_m_s=length * phi0 * omega,
        pole_length=2 * POLE_HALF_LENGTH if kind == "pole" else None,
    )
    return obst.stack(frames), np.zeros((T, 3)), meta


def _disk_track(rng, index: int, n_per: int, T: int, dt: float):
    table = obst.make(cylinders=[((0.0, TABLE_TOP, 0.0), TABLE_RADIUS, TABLE_TOP, TABLE_RIM_RADIUS)], ground=0.0)
    lo, hi = 1.0, 5.0
    frac = (index % n_per + rng.uniform(0.1, 0.9)) / n_per
    speed = lo + (hi - lo) * frac
    az = rng.uniform(0, 2 * math.pi)
    drift = math.radians(rng.uniform(-25, 25))
    gust_amp = rng.uniform(0.1, 0.3)
    gust_period = rng.uniform(1.5, 4.0)
    gust_phase = rng.uniform(0, 2 * math.pi)
    turb = rng.uniform(0.15, 0.35) * speed
    t = np.arange(T) * dt
    ramp = np.clip(t / 1.0, 0, 1)
    ramp = ramp * ramp * (3 - 2 * ramp)
    s = speed * ramp * (1 + gust_amp * np.sin(2 * math.pi * t / gust_period + gust_phase))
    ang = az + drift * t / max(t[-1], dt)
    wind = np.stack([s * np.cos(ang), np.zeros(T), s * np.sin(ang)], 1)
    meta = dict(
        obstacle="table",
        table_radius=TABLE_RADIUS,
        table_top=TABLE_TOP,
        table_rim_radius=TABLE_RIM_RADIUS,
        wind_speed_m_s=speed,
        wind_azimuth_deg=math.degrees(az),
        wind_drift_deg=math.degrees(drift),
        gust_amplitude=gust_amp,
        gust_period_s=gust_period,
        turbulence_m_s=turb,
        ramp_s=1.0,
    )
    return obst.static_track(table, T), wind, turb, meta


def _scene(kind: str, rng, index: int, n_frames: int, n_sequences: int, params: ClothParams, cv, motions):
    """The kind's tracks and start: ``(obstacle track, wind (T, 3), params, x0 (Vc, 3), attach, meta)``."""
    dt = PARAMS.frame_dt
    if kind == "sheet":
        track, wind, meta = _sheet_track(rng, index, n_frames, dt)
        return track, wind, params, cv.copy(), None, meta
    if kind in GARMENT_KINDS:
        track, rot, trans, meta = garm.motion_track(rng, n_frames, 1.0 / dt, motions)
        if motions:
            meta["motions"] = [[k, dict(p)] for k, p in motions]
        attach = (rot.astype(np.float32), trans.astype(np.float32))
        return track, np.zeros((n_frames, 3)), params, cv.copy(), attach, meta
    track, wind, turb, meta = _disk_track(rng, index, max(n_sequences, 1), n_frames, dt)
    x0 = cv + np.array([0.0, TABLE_TOP + PARAMS.thickness + 0.005, 0.0])
    return track, wind, params.replace(turbulence=float(turb)), x0, None, meta


def scenario(
    kind: str,
    index: int,
    seed: int = 0,
    n_frames: int = N_FRAMES,
    n_sequences: int = 10,
    levels: int = 3,
    motions=None,
) -> Scenario:
    """Sequence ``index`` of a scenario kind; deterministic from (kind, index, seed).

    **Arguments:**

    - ``kind``: ``"sheet"``, ``"disk"``, ``"skirt"`` or ``"pants"`` (:data:`KINDS`).
    - ``index``: the sequence's index (non-negative).
    - ``seed``: the seed of the random draws.
    - ``n_frames``: frames of the sequence (at least 2).
    - ``n_sequences``: spreads the disk's wind speeds over [1, 5] m/s across indices.
    - ``levels``: Loop levels of the fine mesh.
    - ``motions``: garments: the body's motions to draw from, ``(kind, fixed parameters)`` pairs
        (:func:`jaxdeform.cloth.body.parse_motion`; default None: all of them, nothing fixed).

    **Returns:**

    The :class:`Scenario`: meshes' start states, pins, obstacle and wind tracks, physics and its record.

    **Raises:**

    ``ScenarioError`` for an unknown kind, a negative index or fewer than 2 frames.
    """
    if kind not in KINDS:
        raise ScenarioError(f"Unknown scenario kind {kind!r}; expected one of {KINDS}.")
    if index < 0 or n_frames < 2:
        raise ScenarioError("A scenario needs a non-negative index and at least 2 frames.")
    rng = np.random.default_rng([KINDS.index(kind), index, seed])
    dt = PARAMS.frame_dt
    cv, cf, fv, ff = _meshes(kind, levels)
    pc, pf = _pins(kind, levels)
    params = PARAMS.replace(substeps=COARSE_STEPS[kind][0], iterations=COARSE_STEPS[kind][1], **KIND_PARAMS[kind])
    params = params.replace(face_samples=sim.face_samples_for(cv, cf, params.thickness, MIN_OBSTACLE_RADIUS[kind]))
    track, wind, params, x0, attach, meta = _scene(kind, rng, index, n_frames, n_sequences, params, cv, motions)
    meta = dict(
        kind=kind,
        index=index,
        seed=seed,
        n_frames=n_frames,
        frame_dt=dt,
        settle_frames=SETTLE_FRAMES[kind],
        coarse_vertices=len(cv),
        fine_vertices=len(fv),
        coarse_steps=list(COARSE_STEPS[kind]),
        fine_steps=list(FINE_STEPS),
        params=params.as_dict(),
        fine_face_samples=sim.face_samples_for(fv, ff, params.thickness, MIN_OBSTACLE_RADIUS[kind]),
        pinned_coarse=int(pc.sum()),
        pinned_fine=int(pf.sum()),
        levels=levels,
        **meta,
    )
    return Scenario(
        kind,
        index,
        seed,
        n_frames,
        SETTLE_FRAMES[kind],
        track,
        wind.astype(np.float32),
        params,
        pc,
        pf,
        x0.astype(np.float32),
        meta,
        levels,
        attach,
    )


# ------------------------------------------------------------------------------------------------ simulation


def _run_one(model, params, x0, sc: Scenario, pinned, progress: bool, desc: str):
    T0 = obst.obstacles_at(sc.track, 0)
    settle = sim.run(
        model,
        params.replace(turbulence=0.0),
        x0,
        None,
        obst.static_track(T0, sc.settle_frames),
        pinned,
        None,
        sc.key,
        wind_track=np.zeros((sc.settle_frames, 3)),
        progress=progress,
        desc=f"{desc} settle",
    )
    pins = pin_track(sc, x0)
    res = sim.run(
        model,
        params,
        settle.x,
        settle.v,
        sc.track,
        pinned,
        pins,
        sc.key,
        wind_track=sc.wind,
        progress=progress,
        desc=desc,
    )
    return res, settle.compile_seconds + res.compile_seconds


def pin_track(sc: Scenario, x0) -> np.ndarray:
    """Where the pinned vertices are held in each frame ``(T, V, 3)``: at their start positions ``x0`` ``(V, 3)``,
    or carried from there by the scenario's rigid motion (a garment's waistband rides with the pelvis)."""
    x0 = np.asarray(x0, np.float32)
    if sc.attach is None:
        return np.broadcast_to(x0, (sc.n_frames,) + x0.shape)
    rot, trans = sc.attach
    return (np.einsum("tij,vj->tvi", rot, x0) + trans[:, None]).astype(np.float32)


def fine_start(sc: Scenario) -> np.ndarray:
    """The fine cloth's initial (pre-settling) positions: the coarse start Loop-subdivided.

    **Arguments:**

    - ``sc``: the scenario.

    **Returns:**

    ``(Vf, 3)`` float32.
    """
    _, cf, _, _ = _meshes(sc.kind, sc.levels)
    return loop_subdivide(sc.x0_coarse, cf, sc.levels)[0].astype(np.float32)


def _run_fine(sc: Scenario, x0: np.ndarray, progress: bool):
    """Settle and simulate the fine mesh from ``x0`` with the fine iteration budget: (result, compile seconds)."""
    _, mf = models(sc.kind, sc.levels)
    pf = sc.params.replace(substeps=FINE_STEPS[0], iterations=FINE_STEPS[1], face_samples=sc.meta["fine_face_samples"])
    return _run_one(mf, pf, x0, sc, sc.pinned_fine, progress, f"{sc.kind} {sc.index} fine")


def pins(sc: Scenario) -> dict:
    """The pinned vertices of both meshes and where they are held.

    These are part of the scenario, like the obstacles: the synthesis anchors its reconstruction on them.

    **Arguments:**

    - ``sc``: the scenario.

    **Returns:**

    A dict: "coarse_pins" / "fine_pins" (int32 indices) and "coarse_pin_positions" / "fine_pin_positions" (float32
    ``(P, 3)`` for pins that never move; ``(T, P, 3)``, one row per frame, for pins that follow the body).
    """
    x0f = fine_start(sc)
    pc, pf = np.flatnonzero(sc.pinned_coarse), np.flatnonzero(sc.pinned_fine)
    if sc.attach is None:
        at_c, at_f = np.asarray(sc.x0_coarse)[pc], x0f[pf]
    else:
        at_c, at_f = pin_track(sc, np.asarray(sc.x0_coarse)[pc]), pin_track(sc, x0f[pf])
    return {
        "coarse_pins": pc.astype(np.int32),
        "coarse_pin_positions": np.asarray(at_c, np.float32),
        "fine_pins": pf.astype(np.int32),
        "fine_pin_positions": np.asarray(at_f, np.float32),
    }


def simulate_pair(sc: Scenario, *, progress: bool = True) -> dict:
    """Simulate the coarse and the fine cloth of a scenario separately (same tracks and physics).

    **Arguments:**

    - ``sc``: the scenario (:func:`scenario`).
    - ``progress``: show progress bars.

    **Returns:**

    A dict: "coarse" ``(T, Vc, 3)`` and "fine" ``(T, Vf, 3)`` float32 frames, "coarse_faces", "fine_faces",
    "coarse_rest", "fine_rest", "obstacles" (the track as a dict of arrays), "wind" ``(T, 3)``, "meta" (with the
    measured timings and edge strains) and "coarse_seconds_per_frame" / "fine_seconds_per_frame" (compilation
    excluded; settling excluded).
    """
    cv, cf, fv, ff = _meshes(sc.kind, sc.levels)
    mc, mf = models(sc.kind, sc.levels)
    t = time.perf_counter()
    rc, cc = _run_one(mc, sc.params, sc.x0_coarse, sc, sc.pinned_coarse, progress, f"{sc.kind} {sc.index} coarse")
    tc = time.perf_counter() - t
    t = time.perf_counter()
    rf, cfine = _run_fine(sc, fine_start(sc), progress)
    tf = time.perf_counter() - t
    sc_mean, sc_max = sim.edge_strain(mc, rc.frames)
    sf_mean, sf_max = sim.edge_strain(mf, rf.frames)
    meta = dict(sc.meta)
    meta.update(
        coarse_seconds_per_frame=rc.seconds_per_frame,
        fine_seconds_per_frame=rf.seconds_per_frame,
        coarse_compile_seconds=cc,
        fine_compile_seconds=cfine,
        coarse_wall_seconds=tc,
        fine_wall_seconds=tf,
        coarse_strain_mean=sc_mean,
        coarse_strain_max=sc_max,
        fine_strain_mean=sf_mean,
        fine_strain_max=sf_max,
        coarse_max_penetration=max_penetration(rc.frames, sc.track, cf),
        fine_max_penetration=max_penetration(rf.frames, sc.track, ff),
        penetration_samples=PENETRATION_SAMPLES,
    )
    return {
        **pins(sc),
        "coarse": rc.frames,
        "fine": rf.frames,
        "coarse_faces": cf.astype(np.int32),
        "fine_faces": ff.astype(np.int32),
        "coarse_rest": cv.astype(np.float32),
        "fine_rest": fv.astype(np.float32),
        "obstacles": obst.to_dict(sc.track),
        "wind": sc.wind,
        "meta": meta,
        "coarse_seconds_per_frame": rc.seconds_per_frame,
        "fine_seconds_per_frame": rf.seconds_per_frame,
    }


def simulate_fine(sc: Scenario, *, perturbation: float = 0.0, seed: int = 1) -> np.ndarray:
    """The fine cloth of a scenario alone, optionally from a perturbed start.

    Two runs that differ only by a tiny perturbation measure how far the fine simulation itself is determined
    by its scenario: their distance is a floor below which no predictor of the fine cloth from the scenario
    (let alone from the coarse cloth) can be expected to go (the ``floor`` stage of ``experiments/cloth``).

    **Arguments:**

    - ``sc``: the scenario.
    - ``perturbation``: the RMS per coordinate, in metres, of Gaussian noise added to the free vertices' start
        (non-negative; 0: none).
    - ``seed``: draws the noise.

    **Returns:**

    The frames ``(T, Vf, 3)`` float32.

    **Raises:**

    ``ScenarioError`` for a negative or non-finite perturbation.
    """
    if not (perturbation >= 0 and np.isfinite(perturbation)):
        raise ScenarioError(f"the perturbation must be a non-negative number of metres, got {perturbation}.")
    x0 = fine_start(sc)
    if perturbation > 0:
        noise = np.random.default_rng(seed).standard_normal(x0.shape) * perturbation
        x0 = (x0 + noise * ~np.asarray(sc.pinned_fine)[:, None]).astype(np.float32)
    res, _ = _run_fine(sc, x0, False)
    return np.asarray(res.frames, np.float32)


#: Order of the barycentric grid (intervals per edge) at which :func:`max_penetration` tests the triangles'
#: interiors: finer than the contact points of the simulation (:func:`simulate.face_samples_for`), so it also
#: tests between them.
PENETRATION_SAMPLES = 12


@jax.jit
def _penetration(frames, track, faces, bary):
    def one(x, obs):
        pts = (
            x
            if faces is None
            else jax.numpy.concatenate([x, jax.numpy.einsum("sk,fkd->fsd", bary, x[faces]).reshape(-1, 3)])
        )
        d, _ = obst.signed_distance(obs, pts)
        return jax.numpy.max(jax.numpy.maximum(-d, 0.0))

    return jax.numpy.max(jax.lax.map(lambda a: one(*a), (frames, track)))


def max_penetration(frames, obstacle_track: Obstacles, faces=None) -> float:
    """Max over frames of -min(sdf, 0) (metres), frame t tested against track frame t.

    **Arguments:**

    - ``frames``: positions ``(T, V, 3)``.
    - ``obstacle_track``: the obstacles of the T frames.
    - ``faces``: triangles ``(F, 3)``; given, the points of an order-:data:`PENETRATION_SAMPLES` grid inside every
        triangle are tested too (default None: the vertices only).

    **Returns:**

    The largest penetration depth as a float (0 when nothing penetrates).

    **Raises:**

    ``ScenarioError`` if ``frames`` and the track have different numbers of frames.
    """
    frames = np.asarray(frames, np.float32)
    track = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32), obstacle_track)
    if frames.shape[0] != obst.n_frames(track):
        raise ScenarioError(f"{frames.shape[0]} frames but the obstacle track has {obst.n_frames(track)}.")
    if faces is None:
        return float(_penetration(frames, track, None, None))
    bary = sim.face_barycentrics(PENETRATION_SAMPLES)
    return float(_penetration(frames, track, np.asarray(faces, np.int32), bary))
