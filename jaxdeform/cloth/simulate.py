"""Cloth simulation by XPBD (extended position-based dynamics) in JAX, for the paired data of seed 002.

Units: metres, seconds, kilograms; y is up, gravity (0, -g, 0) with g = 9.81 m/s^2; 30 frames/s by default.

One frame = ``substeps`` substeps of h = frame_dt / substeps (Macklin et al. 2019, "Small steps in physics
simulation": many substeps with few iterations). One substep:

1. external forces: v += h (g + f_air / m);  v *= exp(-damping h);  p = x + h v;  pinned p = pin target
2. ``iterations`` times: bending (Jacobi), stretch (Gauss-Seidel over an edge colouring), tethers, and a
   frictionless push out of the obstacles (so the solver sees the contacts)
3. self-collision: vertex-vertex separation to ``self_radius`` (see below)
4. obstacle collision with friction -- the last vertex projection, so stored frames have vertex penetration ~0;
   with ``face_samples`` > 1 a push of the triangles' interiors follows (and joins step 2, frictionless there), with
   friction like the vertices' (``face_friction``); its normal part only moves points outward along the obstacles'
   normals
5. v = (p - x) / h;  x = p

Masses: lumped, m_i = density * (sum of the areas of the triangles at i) / 3.

Stretch (XPBD, Macklin et al. 2016): per edge C = |x_i - x_j| - L with compliance alpha_e = L^2 / (Y A_e), A_e a
third of the area of the triangles at the edge, so that a uniform strain eps has the membrane energy
(Y/2) eps^2 per area at every resolution (Y = ``stretch_stiffness``, N/m). Update with alpha~ = alpha / h^2:
dlam = (-C - alpha~ lam) / (w_i + w_j + alpha~), x_i += w_i dlam n, x_j -= w_j dlam n. Edges of one colour share
no vertex, so each colour is one vectorised Gauss-Seidel sweep (greedy colouring on the host).

Bending: the isometric (quadratic) model of Bergou et al. 2006 / Wardetzky et al. 2007. For an interior edge
(x0, x1) with opposite vertices x2, x3, the linear vector constraint c = sum_i k_i x_i with
k2 = |e| / h2, k3 = |e| / h3, k1 = -(t2 / h2 + t3 / h3), k0 = -(k1 + k2 + k3) (h_j the height of x_j over the
edge line, t_j its coordinate along the edge, from the rest mesh) vanishes on the rest hinge and has
|c| = |e| theta for a small hinge angle theta. Energy (k_b / 2) (3 / (A0 + A1)) |c - c_rest|^2, i.e. the
discrete-shells hinge energy 3 k_b |e|^2 theta^2 / (2 (A0 + A1)) (k_b = ``bend_stiffness``, N m), compliance
alpha = (A0 + A1) / (3 k_b). The three components are independent linear constraints with gradient k_i I, solved
by Jacobi with mass splitting (denominator sum_i n_i w_i k_i^2 + alpha~, n_i = hinges at vertex i), which is
stable whatever k_b and exact when alpha~ dominates (the case for cloth).

Air (flat-plate model per triangle; relative air velocity u = w(x_c, t) - v_c, unit normal n, area A, c = u.n):
drag F_d = 1/2 rho_air C_d A |c| u (along the flow, projected area), lift F_l = 1/2 rho_air C_l A c (|u| n - c u
/ |u|) (perpendicular to the flow, |F_l| ~ |cos| sin of the angle of attack); spread 1/3 to each corner. The air
is at rest unless ``wind``: w = mean wind (per-frame track, linearly interpolated) + turbulence, a sum of
``TURBULENCE_MODES`` random Fourier modes sum_k a_k sin(q_k . x - omega_k t + phi_k) with q_k ~ N(0, 1/l^2),
omega_k ~ N(0, 1/tau^2), phi_k ~ U(0, 2 pi), a_k ~ N(0, 2/K) (so each component has RMS ~ 1), scaled by
``turbulence`` (m/s), drawn from the PRNG key (l = ``turbulence_length``, tau = ``turbulence_time``). Moving
cloth in still air feels the same drag, which is the main damping of a falling sheet.

Obstacles (``obstacles.py``): a vertex with d(x) < thickness is pushed out along the shape's normal to
d = thickness; friction in position form (Coulomb): the tangential motion relative to the obstacle's surface
during the substep, dx_t, is removed if |dx_t| <= mu * depth, else shortened by mu * depth. Obstacles move
linearly between stored frames (the track is interpolated per substep). Vertex contacts alone let an obstacle
sink into a large triangle between its corners (by r - sqrt(r^2 - R^2) for a sphere of radius r and a triangle
of circumradius R); ``face_samples`` = n > 1 adds contact points on the order-n barycentric grid of every
triangle (n intervals per edge), each a zero-compliance point constraint whose correction goes to the corners by
their barycentric weights (:func:`_push_out_faces`). Inside the solver iterations these pushes are
frictionless, like the vertices'; the final push of the substep (:func:`_collide_faces`, ``face_friction``, on by
default) applies the same Coulomb law to each sample point q = sum b_k x_k: its tangential motion relative to the
surface is removed or shortened by mu times its normal correction of the substep, the correction c spread over the
corners as x_k += w_k b_k c / sum_j w_j b_j^2 and averaged per vertex. Without it a triangle held up by its
interior points alone slides off a rim freely while a vertex resting there sticks, so two resolutions of one cloth
part ways on a table (the DISK scenes).

Tethers (long-range attachments, Kim et al. 2012; ``tethers``, on by default): every free vertex stays within
its rest distance of its nearest pinned vertex (unilateral, projected after each stretch sweep). They remove the
iteration-limited sag of pinned cloth (mean strain of the hanging fine sheet 0.9 % -> 0.13 %) at the cost of
one gather per iteration; the rest meshes here are flat and convex, so rest distance = geodesic distance.

Self-collision (vertex-vertex, Mueller's "ten minutes physics" scheme): two vertices whose REST distance exceeds
2 r (so not mesh neighbours; the rest meshes here are flat, where that is the geodesic distance) are kept
at least r = ``self_radius`` * (mean rest edge length) apart. With r >= 0.71 L no vertex can pass through the
interior of a right-isoceles grid triangle of leg L without coming within r of one of its corners
(circumradius L / sqrt 2), so layers cannot cross. Candidates: once per frame a sorted hash grid (cell 2 r,
27 cells, at most ``SELF_CELL_CAP`` vertices per cell, fixed sizes, jittable) keeps the ``SELF_NEIGHBOURS``
nearest non-excluded vertices within 2 r of each vertex; every substep pushes each vertex away from the listed
ones closer than r (share w_i / (w_i + w_j) of the overlap, averaged over the active pairs, Jacobi).

Defaults (:class:`ClothParams`): density 0.2 kg/m^2 and bending stiffness 5e-6 N m are of the order of the
measured knits of Wang et al. 2011 (the Gray Interlock of the paper); membrane stiffness 5e3 N/m
(practically inextensible: the attained strain is limited by the iteration count, not by Y); friction 0.4,
thickness 5 mm, damping 0.2 /s, air density 1.2 kg/m^3, C_d = 1.0, C_l = 0.5, 10 substeps x 2 iterations.
Friction bound: mu times the normal correction of the substep (solver pushes plus the final push).
The scenarios raise substeps/iterations for the fine meshes (see ``scenarios.py``); every physical parameter
is the same for both resolutions.

Compilation: ``ClothParams`` is a pytree whose numbers are traced leaves and whose ints/flags (substeps,
iterations, self_collision) are static, so changing a wind speed or a stiffness never recompiles; one
executable exists per (mesh sizes, obstacle counts, chunk length, static fields), cached in this module.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxdeform.errors import ConnectivityError, DegenerateMeshError, JaxDeformError
from jaxdeform.mesh.topology import half_edge_groups

from . import obstacles as obst
from .obstacles import Obstacles

#: Random Fourier modes of the turbulence field.
TURBULENCE_MODES = 16
#: Candidate partners kept per vertex for self-collision (nearest first).
SELF_NEIGHBOURS = 8
#: Vertices read per hash-grid cell when gathering self-collision candidates.
SELF_CELL_CAP = 10
#: Frames per jitted ``lax.scan`` chunk (the progress bar advances per chunk).
CHUNK = 10


class SimulationError(JaxDeformError):
    """A simulation input is inconsistent (shapes, counts or values)."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ClothParams:
    """Physical and numerical parameters (SI units). Numbers are traced leaves; ints and flags are static."""

    density: float = 0.2  # kg/m^2
    stretch_stiffness: float = 5.0e3  # N/m, membrane Young's modulus (compliance per edge L^2 / (Y A_e))
    bend_stiffness: float = 5.0e-6  # N m
    damping: float = 0.2  # 1/s, v *= exp(-damping h)
    friction: float = 0.4  # Coulomb coefficient against obstacles
    thickness: float = 0.005  # m, collision margin to obstacles
    self_radius: float = 0.75  # self-collision distance as a fraction of the mean rest edge length
    frame_dt: float = 1.0 / 30.0  # s
    gravity: float = 9.81  # m/s^2
    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m/s, mean wind when no per-frame track is given
    turbulence: float = 0.0  # m/s, RMS per component of the turbulent wind
    turbulence_length: float = 0.5  # m
    turbulence_time: float = 1.0  # s
    air_density: float = 1.2  # kg/m^3
    drag: float = 1.0  # C_d
    lift: float = 0.5  # C_l
    substeps: int = dataclasses.field(default=10, metadata=dict(static=True))
    iterations: int = dataclasses.field(default=2, metadata=dict(static=True))
    self_collision: bool = dataclasses.field(default=True, metadata=dict(static=True))
    tethers: bool = dataclasses.field(default=True, metadata=dict(static=True))
    face_samples: int = dataclasses.field(default=0, metadata=dict(static=True))  # 0 or 1: vertex contacts only
    face_friction: bool = dataclasses.field(default=True, metadata=dict(static=True))  # Coulomb at face samples

    def replace(self, **kw) -> ClothParams:
        return dataclasses.replace(self, **kw)

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["wind"] = list(d["wind"])
        return d


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ClothModel:
    """Host-built constant data of one mesh (a pytree of arrays; sizes are static through the shapes)."""

    rest: Float[Array, "v 3"]
    faces: Int[Array, "f 3"]
    area_v: Float[Array, " v"]  # lumped area per vertex (m^2); mass = density * area_v
    edges: Int[Array, "e 2"]
    rest_len: Float[Array, " e"]
    color_edges: Int[Array, "k m 2"]  # edges by colour, padded
    color_len: Float[Array, "k m"]
    color_comp: Float[Array, "k m"]  # L^2 / A_e: alpha_e = color_comp / Y
    color_mask: Bool[Array, "k m"]
    hinges: Int[Array, "h 4"]  # (x0, x1) the edge, x2, x3 the opposite vertices
    hinge_k: Float[Array, "h 4"]
    hinge_comp: Float[Array, " h"]  # (A0 + A1) / 3: alpha = hinge_comp / k_b
    hinge_rest: Float[Array, "h 3"]  # c at rest (0 for flat hinges)
    hinge_count: Float[Array, " v"]  # hinges touching each vertex
    mean_edge: Float[Array, ""]

    @property
    def n_vertices(self) -> int:
        return self.rest.shape[0]


class SimResult(NamedTuple):
    frames: np.ndarray  # (T, V, 3) float32
    x: np.ndarray  # last positions (V, 3)
    v: np.ndarray  # last velocities (V, 3)
    compile_seconds: float  # 0 when the executable was cached
    seconds_per_frame: float  # wall time of the frames, compilation excluded


# ----------------------------------------------------------------------------------------------- model (host)


def _edge_colouring(edges: np.ndarray, n_vertices: int) -> np.ndarray:
    """Greedy colouring so that edges of one colour share no vertex (host, once per mesh)."""
    used = [0] * n_vertices
    colour = np.empty(len(edges), np.int64)
    for e, (i, j) in enumerate(edges.tolist()):
        m = used[i] | used[j]
        c = (~m & (m + 1)).bit_length() - 1
        colour[e] = c
        used[i] |= 1 << c
        used[j] |= 1 << c
    return colour


def _rest_mesh(rest_vertices, faces) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Checked rest mesh with its areas: ``(X (V, 3) float64, F (F, 3) int64, tri_area (F,), area_v (V,))``.

    ``tri_area`` is each triangle's area (all > 1e-14) and ``area_v`` the lumped area per vertex (a third of the
    area of every triangle at it). Raises, in this order, SimulationError for wrong shapes, ConnectivityError
    for a face index out of range, DegenerateMeshError for a triangle of (near) zero area.
    """
    X = np.asarray(rest_vertices, np.float64)
    F = np.asarray(faces, np.int64)
    if X.ndim != 2 or X.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
        raise SimulationError("The rest mesh must be vertices (V, 3) and triangles (F, 3).")
    if F.size and (F.min() < 0 or F.max() >= len(X)):
        raise ConnectivityError("The cloth faces index vertices that do not exist.")
    V = len(X)
    a, b, c = X[F[:, 0]], X[F[:, 1]], X[F[:, 2]]
    tri_area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if np.any(tri_area <= 1e-14):
        raise DegenerateMeshError("The cloth rest mesh has a triangle of zero area.")
    area_v = np.zeros(V)
    np.add.at(area_v, F.ravel(), np.repeat(tri_area / 3.0, 3))
    return X, F, tri_area, area_v


class _EdgeTable(NamedTuple):
    """Unique edges of a mesh and the sorted half-edges they come from (:func:`_edge_table`)."""

    edges: np.ndarray  # (E, 2) sorted vertex pairs, lexicographic order
    rest_len: np.ndarray  # (E,)
    edge_area: np.ndarray  # (E,) a third of the area of the (one or two) triangles at each edge
    he: np.ndarray  # (3F, 2) half-edges sorted by edge; the half-edges of edge e start at starts[e]
    opp: np.ndarray  # (3F,) the vertex opposite each half-edge in its triangle
    fid: np.ndarray  # (3F,) the triangle of each half-edge
    starts: np.ndarray  # (E,) index of each edge's first half-edge
    two: np.ndarray  # (E,) bool: interior edge (two triangles)


def _edge_table(X: np.ndarray, F: np.ndarray, tri_area: np.ndarray) -> _EdgeTable:
    """Half-edges grouped into unique edges with their (one or two) faces and opposite vertices.

    Takes the checked rest mesh ``X``, ``F`` and its triangle areas. Raises ConnectivityError if an edge has
    more than two triangles (not a manifold).
    """
    key, he, opp, fid, starts, counts = half_edge_groups(F)
    if counts.max(initial=1) > 2:
        raise ConnectivityError("The cloth mesh is not a manifold (an edge has more than two triangles).")
    edges = key[starts]
    rest_len = np.linalg.norm(X[edges[:, 0]] - X[edges[:, 1]], axis=1)
    edge_area = tri_area[fid[starts]] / 3.0
    two = counts == 2
    edge_area[two] += tri_area[fid[starts[two] + 1]] / 3.0
    return _EdgeTable(edges, rest_len, edge_area, he, opp, fid, starts, two)


def _hinges(X: np.ndarray, et: _EdgeTable, tri_area: np.ndarray):
    """Bending hinges of the interior edges, oriented as the first face's half-edge (module docstring).

    Returns ``(hinges (H, 4) [x0, x1, x2, x3], hinge_k (H, 4), hinge_rest (H, 3), hinge_comp (H,),
    hinge_count (V,) float64)``: the constraint coefficients k_i, the constraint value c at rest, (A0 + A1) / 3,
    and the number of hinges touching each vertex.
    """
    s2 = et.starts[et.two]
    x0, x1 = et.he[s2, 0], et.he[s2, 1]
    x2, x3 = et.opp[s2], et.opp[s2 + 1]
    hinges = np.stack([x0, x1, x2, x3], 1)
    e = X[x1] - X[x0]
    el = np.linalg.norm(e, axis=1)
    eh = e / el[:, None]

    def wing(xj):
        r = X[xj] - X[x0]
        t = np.sum(r * eh, 1)
        h = np.linalg.norm(r - t[:, None] * eh, axis=1)
        return t, h

    t2, h2 = wing(x2)
    t3, h3 = wing(x3)
    k2, k3 = el / h2, el / h3
    k1 = -(t2 / h2 + t3 / h3)
    k0 = -(k1 + k2 + k3)
    hinge_k = np.stack([k0, k1, k2, k3], 1)
    hinge_rest = np.einsum("hk,hkd->hd", hinge_k, X[hinges])
    hinge_comp = (tri_area[et.fid[s2]] + tri_area[et.fid[s2 + 1]]) / 3.0
    hinge_count = np.bincount(hinges.ravel(), minlength=len(X)).astype(np.float64)
    return hinges, hinge_k, hinge_rest, hinge_comp, hinge_count


def _colour_tables(et: _EdgeTable, n_vertices: int):
    """The edges grouped by colour (:func:`_edge_colouring`), padded to the largest colour.

    Returns ``(edges (K, M, 2) int64, rest lengths (K, M), compliance factors L^2 / A_e (K, M), mask (K, M))``;
    padding slots hold zeros and mask False. A mesh without edges gives one colour of one masked slot.
    """
    edges = et.edges
    colour = _edge_colouring(edges, n_vertices)
    n_col = int(colour.max()) + 1 if len(edges) else 1
    m = int(np.bincount(colour, minlength=n_col).max()) if len(edges) else 1
    ce = np.zeros((n_col, m, 2), np.int64)
    cl = np.zeros((n_col, m))
    cc = np.zeros((n_col, m))
    cm = np.zeros((n_col, m), bool)
    for k in range(n_col):
        sel = np.flatnonzero(colour == k)
        ce[k, : len(sel)] = edges[sel]
        cl[k, : len(sel)] = et.rest_len[sel]
        cc[k, : len(sel)] = et.rest_len[sel] ** 2 / et.edge_area[sel]
        cm[k, : len(sel)] = True
    return ce, cl, cc, cm


def build_model(rest_vertices, faces) -> ClothModel:
    """Edges, colours, hinges, lumped areas and rest quantities of a triangle mesh (host numpy, once).

    **Arguments:**

    - ``rest_vertices``: the rest positions ``(V, 3)``.
    - ``faces``: the triangles ``(F, 3)``.

    **Returns:**

    The :class:`ClothModel`; its float arrays are float32, its indices int32.

    **Raises:**

    ``SimulationError``, ``ConnectivityError`` or ``DegenerateMeshError`` for a malformed, non-manifold or degenerate
    rest mesh (:func:`_rest_mesh`, :func:`_edge_table`).
    """
    X, F, tri_area, area_v = _rest_mesh(rest_vertices, faces)
    et = _edge_table(X, F, tri_area)
    hinges, hinge_k, hinge_rest, hinge_comp, hinge_count = _hinges(X, et, tri_area)
    ce, cl, cc, cm = _colour_tables(et, len(X))
    edges, rest_len = et.edges, et.rest_len

    f32 = np.float32
    return ClothModel(
        rest=jnp.asarray(X, f32),
        faces=jnp.asarray(F, jnp.int32),
        area_v=jnp.asarray(area_v, f32),
        edges=jnp.asarray(edges, jnp.int32),
        rest_len=jnp.asarray(rest_len, f32),
        color_edges=jnp.asarray(ce, jnp.int32),
        color_len=jnp.asarray(cl, f32),
        color_comp=jnp.asarray(cc, f32),
        color_mask=jnp.asarray(cm),
        hinges=jnp.asarray(hinges, jnp.int32),
        hinge_k=jnp.asarray(hinge_k, f32),
        hinge_comp=jnp.asarray(hinge_comp, f32),
        hinge_rest=jnp.asarray(hinge_rest, f32),
        hinge_count=jnp.asarray(hinge_count, f32),
        mean_edge=jnp.asarray(rest_len.mean(), f32),
    )


ClothModel.build = staticmethod(build_model)


# ------------------------------------------------------------------------------------------------ air / wind


def turbulence_modes(key, dtype=jnp.float32) -> dict:
    """Unit-scale random Fourier modes of the turbulence (q in 1/length units, omega in 1/time units).

    **Arguments:**

    - ``key``: the PRNG key.
    - ``dtype``: the arrays' dtype.

    **Returns:**

    A dict of the K = TURBULENCE_MODES modes: wave vectors ``q`` ``(K, 3)``, frequencies ``omega`` ``(K,)``,
    ``phase`` ``(K,)`` in [0, 2 pi) and amplitudes ``amp`` ``(K, 3)``.
    """
    kq, kw, kp, ka = jax.random.split(key, 4)
    K = TURBULENCE_MODES
    return dict(
        q=jax.random.normal(kq, (K, 3), dtype),
        omega=jax.random.normal(kw, (K,), dtype),
        phase=jax.random.uniform(kp, (K,), dtype, 0.0, 2 * math.pi),
        amp=jax.random.normal(ka, (K, 3), dtype) * jnp.sqrt(2.0 / K).astype(dtype),
    )


def wind_velocity(
    params: ClothParams, modes: dict, mean: Float[Array, " 3"], x: Float[Array, "p 3"], t
) -> Float[Array, "p 3"]:
    """Air velocity at points x and time t: mean + turbulence * sum_k a_k sin(q_k.x / l - omega_k t / tau + phi_k).

    **Arguments:**

    - ``params``: the physical parameters (turbulence strength and scales).
    - ``modes``: :func:`turbulence_modes`' result.
    - ``mean``: the mean wind ``(3,)``.
    - ``x``: points ``(P, 3)``.
    - ``t``: the time.

    **Returns:**

    The velocities ``(P, 3)``.
    """
    arg = x @ (modes["q"].T / params.turbulence_length) - modes["omega"] * (t / params.turbulence_time) + modes["phase"]
    return mean + params.turbulence * (jnp.sin(arg) @ modes["amp"])


def air_force(model: ClothModel, params: ClothParams, modes: dict, mean, x, v, t) -> Float[Array, "v 3"]:
    """Per-vertex aerodynamic force (N) of the flat-plate drag + lift model (module docstring).

    **Arguments:**

    - ``model``: the cloth model.
    - ``params``: the physical parameters.
    - ``modes``: :func:`turbulence_modes`' result.
    - ``mean``: the mean wind ``(3,)``.
    - ``x``, ``v``: positions and velocities ``(V, 3)``.
    - ``t``: the time.

    **Returns:**

    The forces ``(V, 3)``.
    """
    f = model.faces
    a, b, c = x[f[:, 0]], x[f[:, 1]], x[f[:, 2]]
    cr = jnp.cross(b - a, c - a)
    dbl = jnp.sqrt(jnp.sum(cr * cr, -1))
    n = cr / jnp.maximum(dbl, 1e-12)[:, None]
    area = 0.5 * dbl
    vc = (v[f[:, 0]] + v[f[:, 1]] + v[f[:, 2]]) / 3.0
    u = wind_velocity(params, modes, mean, (a + b + c) / 3.0, t) - vc
    cn = jnp.sum(u * n, -1)
    um = jnp.sqrt(jnp.sum(u * u, -1) + 1e-20)
    coef = 0.5 * params.air_density * area
    force = coef[:, None] * (
        params.drag * jnp.abs(cn)[:, None] * u + params.lift * cn[:, None] * (um[:, None] * n - (cn / um)[:, None] * u)
    )
    per = jnp.repeat(force / 3.0, 3, axis=0)
    return jax.ops.segment_sum(per, f.reshape(-1), num_segments=x.shape[0])


# ------------------------------------------------------------------------------------------------ projections


def _stretch_sweep(model: ClothModel, params: ClothParams, w, h2, p, lam):
    """One Gauss-Seidel sweep over the edge colours (XPBD distance constraints). lam: (k, m) multipliers."""

    def colour(p, xs):
        e, L, comp, mask, lam_c = xs
        i, j = e[:, 0], e[:, 1]
        d = p[i] - p[j]
        dist = jnp.sqrt(jnp.sum(d * d, -1))
        n = d / jnp.maximum(dist, 1e-12)[:, None]
        alpha = comp / (params.stretch_stiffness * h2)
        wi, wj = w[i], w[j]
        denom = wi + wj + alpha
        dl = jnp.where(mask & (denom > 0), (-(dist - L) - alpha * lam_c) / jnp.where(denom > 0, denom, 1.0), 0.0)
        p = p.at[i].add((wi * dl)[:, None] * n).at[j].add(-(wj * dl)[:, None] * n)
        return p, lam_c + dl

    p, lam = jax.lax.scan(colour, p, (model.color_edges, model.color_len, model.color_comp, model.color_mask, lam))
    return p, lam


def _bend_sweep(model: ClothModel, params: ClothParams, w, h2, p, lam):
    """One Jacobi sweep with mass splitting over the hinges (linear isometric-bending constraints). lam: (h, 3)."""
    hv = model.hinges
    k = model.hinge_k
    c = jnp.einsum("hk,hkd->hd", k, p[hv]) - model.hinge_rest
    alpha = model.hinge_comp / (params.bend_stiffness * h2)
    denom = jnp.sum(w[hv] * k * k * model.hinge_count[hv], -1) + alpha
    dl = (-c - alpha[:, None] * lam) / denom[:, None]
    dx = (w[hv] * k)[..., None] * dl[:, None, :]
    p = p + jax.ops.segment_sum(dx.reshape(-1, 3), hv.reshape(-1), num_segments=p.shape[0])
    return p, lam + dl


def _hash_cells(cells, size: int):
    c = cells.astype(jnp.uint32)
    h = (c[..., 0] * jnp.uint32(73856093)) ^ (c[..., 1] * jnp.uint32(19349663)) ^ (c[..., 2] * jnp.uint32(83492791))
    return (h & jnp.uint32(size - 1)).astype(jnp.int32)


_OFFSETS = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), -1).reshape(27, 3)


def self_candidates(model: ClothModel, x: Float[Array, "v 3"], radius) -> tuple[Int[Array, "v k"], Bool[Array, "v k"]]:
    """Self-collision candidates from a hash grid.

    **Arguments:**

    - ``model``: the cloth model.
    - ``x``: positions ``(V, 3)``.
    - ``radius``: r.

    **Returns:**

    ``(neighbours (V, k), valid (V, k))``: up to SELF_NEIGHBOURS nearest vertices within 2 r of each vertex whose
    rest distance exceeds 2 r, and which entries are real.
    """
    x = jnp.asarray(x, jnp.float32)
    V = x.shape[0]
    size = 1 << max(4, int(math.ceil(math.log2(2 * V))))
    cell = 2.0 * radius
    ci = jnp.floor(x / cell).astype(jnp.int32)
    hv = _hash_cells(ci, size)
    order = jnp.argsort(hv)
    hs = hv[order]
    hn = _hash_cells(ci[:, None, :] + jnp.asarray(_OFFSETS, jnp.int32)[None], size)  # (V, 27)
    first = jnp.full((size,), V, jnp.int32).at[hs].min(jnp.arange(V, dtype=jnp.int32))  # bucket -> first slot
    start = first[hn]  # (V, 27)
    slot = start[..., None] + jnp.arange(SELF_CELL_CAP)  # (V, 27, cap)
    slot_c = jnp.minimum(slot, V - 1)
    valid = (slot < V) & (hs.at[slot_c].get(mode="promise_in_bounds") == hn[..., None])
    cand = order.at[slot_c].get(mode="promise_in_bounds").reshape(V, -1)
    valid = valid.reshape(V, -1)
    # per-coordinate 1-D gathers: XLA:CPU gathers (V, n, 3) rows an order of magnitude slower
    d2 = dr2 = 0.0
    for k in range(3):
        d2 = d2 + (x[:, k, None] - x[:, k].at[cand].get(mode="promise_in_bounds")) ** 2
        dr2 = dr2 + (model.rest[:, k, None] - model.rest[:, k].at[cand].get(mode="promise_in_bounds")) ** 2
    valid = valid & (d2 < cell * cell) & (dr2 > cell * cell)
    d = d2
    score = jnp.where(valid, -d, -jnp.inf)
    top, idx = jax.lax.top_k(score, SELF_NEIGHBOURS)
    return jnp.take_along_axis(cand, idx, 1), jnp.isfinite(top)


def _self_project(w, radius, p, nbr, mask):
    d = p[:, None, :] - p[nbr]
    dist = jnp.sqrt(jnp.sum(d * d, -1))
    active = mask & (dist < radius)
    wi, wj = w[:, None], w[nbr]
    share = jnp.where(wi + wj > 0, wi / jnp.where(wi + wj > 0, wi + wj, 1.0), 0.0)
    push = jnp.where(active, share * (radius - dist) / jnp.maximum(dist, 1e-9), 0.0)
    n_act = jnp.maximum(jnp.sum(active, -1), 1)
    return p + jnp.sum(push[..., None] * d, 1) / n_act[:, None]


def _push_out(params: ClothParams, w, obs: Obstacles, p):
    """Project vertices out of the obstacles to d = thickness (no friction); also returns the push length."""
    d, n = obst.signed_distance(obs, p)
    depth = jnp.where(w > 0, jnp.maximum(params.thickness - d, 0.0), 0.0)
    return p + depth[:, None] * n, depth


def face_barycentrics(n: int) -> np.ndarray:
    """Barycentric coordinates of the order-``n`` grid on a triangle without its corners (the vertices are tested
    already).

    **Arguments:**

    - ``n``: intervals per edge (>= 0).

    **Returns:**

    ``(S, 3)`` float32, S = (n + 1)(n + 2) / 2 - 3 points (none for n <= 1).

    **Raises:**

    ``SimulationError`` for ``n < 0``.
    """
    if n < 0:
        raise SimulationError(f"face_samples must be >= 0, got {n}.")
    pts = [(i, j, n - i - j) for i in range(n + 1) for j in range(n + 1 - i) if max(i, j, n - i - j) < n]
    return np.asarray(pts, np.float32).reshape(-1, 3) / max(n, 1)


def face_samples_for(rest_vertices, faces, thickness: float, min_radius: float) -> int:
    """The ``face_samples`` a mesh needs so that no obstacle of curvature radius >= ``min_radius`` sinks into a
    triangle by more than half the ``thickness`` between contact points.

    A sphere of radius r sinks ~ R^2 / (2 r) into a triangle whose corners are on it, R the radius of the
    triangle's smallest enclosing circle (its circumradius, or half its longest edge if it is obtuse). The
    order-n grid splits a triangle into copies scaled by 1 / n, so (R / n)^2 / (2 r) <= thickness / 2 needs
    n = ceil(R_max / sqrt(thickness r)) over the rest triangles.

    **Arguments:**

    - ``rest_vertices``, ``faces``: the rest mesh.
    - ``thickness``: the cloth's thickness.
    - ``min_radius``: the smallest obstacle curvature radius.

    **Returns:**

    n; 0 (vertex contacts only) when n <= 1.
    """
    X = np.asarray(rest_vertices, np.float64)
    F = np.asarray(faces, np.int64)
    a, b, c = (np.linalg.norm(X[F[:, (k + 1) % 3]] - X[F[:, (k + 2) % 3]], axis=1) for k in range(3))
    s = np.sort(np.stack([a, b, c], 1), 1)
    area = 0.25 * np.sqrt(np.maximum((a + b + c) * (-a + b + c) * (a - b + c) * (a + b - c), 1e-300))
    obtuse = s[:, 2] ** 2 >= s[:, 0] ** 2 + s[:, 1] ** 2
    radius = np.where(obtuse, 0.5 * s[:, 2], a * b * c / (4.0 * area))
    n = int(math.ceil(radius.max() / math.sqrt(thickness * min_radius) - 1e-9))
    return n if n > 1 else 0


def _coulomb(dx, n, bound, hit):
    """Position-based Coulomb friction: the part of the tangential motion ``dx`` (relative to the surface, normal
    ``n``) to remove at contacts ``hit``: all of it when its length is at most ``bound`` (static), else ``bound``
    of it (kinetic); zero elsewhere."""
    dxt = dx - jnp.sum(dx * n, -1, keepdims=True) * n
    lt = jnp.sqrt(jnp.sum(dxt * dxt, -1))
    scale = jnp.where(lt <= bound, 1.0, bound / jnp.maximum(lt, 1e-12))
    return jnp.where(hit, scale, 0.0)[..., None] * dxt


def _face_points(model: ClothModel, bary, p):
    """The sample points (F, S, 3) of every triangle at barycentric coordinates ``bary`` (S, 3)."""
    return jnp.einsum("sk,fkd->fsd", bary, p[model.faces])


def _spread(model: ClothModel, w, bary, c, active, V: int):
    """Corner corrections of point constraints on the face samples: sample (f, s) moving by ``c`` (F, S, 3) moves
    corner k by w_k b_k c / sum_j w_j b_j^2; per vertex the corrections of the ``active`` samples are averaged."""
    F = model.faces
    wF = w[F]  # (F, 3)
    denom = jnp.einsum("fk,sk->fs", wF, bary * bary)  # sum_j w_j b_j^2
    inv = jnp.where(active & (denom > 0), 1.0 / jnp.where(denom > 0, denom, 1.0), 0.0)
    # sum over a triangle's samples first (a small contraction), then one scatter of F x 3 corner sums
    acc = wF[..., None] * jnp.einsum("sk,fs,fsd->fkd", bary, inv, c)  # (F, 3, 3)
    cnt = jnp.einsum("sk,fs->fk", (bary > 0).astype(c.dtype), (inv > 0).astype(c.dtype)) * (wF > 0)
    acc = jax.ops.segment_sum(acc.reshape(-1, 3), F.reshape(-1), V)
    cnt = jax.ops.segment_sum(cnt.reshape(-1), F.reshape(-1), V)
    return acc / jnp.maximum(cnt, 1.0)[:, None]


def _push_out_faces(model: ClothModel, params: ClothParams, w, obs: Obstacles, p):
    """Push the triangles' interiors out of the obstacles to d = thickness (no friction).

    Each sample point q = sum_k b_k x_k of :func:`face_barycentrics` (``params.face_samples``) with depth
    delta = thickness - d(q) > 0 is one point constraint, projected with zero compliance (:func:`_spread`, n the
    closest shape's normal at q). Returns the positions, each vertex's push length and each sample's depth
    (F, S)."""
    bary = jnp.asarray(face_barycentrics(params.face_samples), p.dtype)
    pts = _face_points(model, bary, p)
    d, n = obst.signed_distance(obs, pts.reshape(-1, 3))
    depth = jnp.maximum(params.thickness - d, 0.0).reshape(pts.shape[:2])
    dp = _spread(model, w, bary, depth[..., None] * n.reshape(pts.shape), depth > 0, p.shape[0])
    return p + dp, jnp.sqrt(jnp.sum(dp * dp, -1)), depth


def _collide_faces(
    model: ClothModel, params: ClothParams, w, obs_now: Obstacles, obs_prev: Obstacles, x_old, p, prior_depth
):
    """The last push of the triangles' interiors, with Coulomb friction at the sample points. A sample in contact
    loses its tangential motion relative to the surface since ``x_old`` when that is at most mu times its normal
    correction in this substep (``prior_depth``, from the solver iterations, plus this push); otherwise that
    much of it. Returns the positions."""
    bary = jnp.asarray(face_barycentrics(params.face_samples), p.dtype)
    q = _face_points(model, bary, p)
    shape = q.shape
    d, n, disp, _ = obst.query(obs_now, obs_prev, q.reshape(-1, 3))
    d, n, disp = d.reshape(shape[:2]), n.reshape(shape), disp.reshape(shape)
    depth = jnp.maximum(params.thickness - d, 0.0)
    c = depth[..., None] * n
    hit = (depth + prior_depth > 0) & (d < params.thickness + 1e-6)
    stop = _coulomb(q + c - _face_points(model, bary, x_old) - disp, n, params.friction * (depth + prior_depth), hit)
    return p + _spread(model, w, bary, c - stop, hit | (depth > 0), p.shape[0])


def _collide(params: ClothParams, w, obs_now: Obstacles, obs_prev: Obstacles, x_old, p, prior_push):
    """Push vertices out of the obstacles to d = thickness; Coulomb friction against the surface's motion with
    the normal correction of this substep (``prior_push`` from the solver iterations plus this push) as bound."""
    d, n, disp, _ = obst.query(obs_now, obs_prev, p)
    depth = jnp.maximum(params.thickness - d, 0.0)
    hit = (w > 0) & (depth + prior_push > 0) & (d < params.thickness + 1e-6)
    p1 = p + jnp.where(w > 0, depth, 0.0)[:, None] * n
    return p1 - _coulomb(p1 - x_old - disp, n, params.friction * (depth + prior_push), hit)


# ------------------------------------------------------------------------------------------------- stepping


def _tether_project(anchor, length, active, p):
    """Long-range attachments: a free vertex stays within its rest distance of its nearest pinned vertex."""
    d = p - p[anchor]
    dist = jnp.sqrt(jnp.sum(d * d, -1))
    over = jnp.where(active & (dist > length), dist - length, 0.0)
    return p - (over / jnp.maximum(dist, 1e-12))[:, None] * d


def _frame(model: ClothModel, params: ClothParams, modes: dict, inv_mass, pinned, tether, state, xs):
    """One frame: ``substeps`` XPBD substeps between the frame's previous and current obstacle / pin / wind."""
    x, v = state
    obs0, obs1, pin0, pin1, wind0, wind1, t0 = xs
    n_sub = params.substeps
    h = params.frame_dt / n_sub
    h2 = h * h
    g = jnp.asarray([0.0, -1.0, 0.0], x.dtype) * params.gravity
    radius = params.self_radius * model.mean_edge
    if params.self_collision:
        nbr, nmask = self_candidates(model, x, radius)
    n_col, m = model.color_len.shape
    faces = params.face_samples > 1
    fshape = (model.faces.shape[0], face_barycentrics(params.face_samples).shape[0]) if faces else (0,)

    def substep(k, carry):
        x, v = carry
        s0 = k / n_sub
        s1 = (k + 1) / n_sub
        t = t0 + s0 * params.frame_dt
        f_air = air_force(model, params, modes, wind0 + s0 * (wind1 - wind0), x, v, t)
        v = (v + h * (g + f_air * inv_mass[:, None])) * jnp.exp(-params.damping * h)
        p = x + h * v
        p = jnp.where(pinned[:, None], pin0 + s1 * (pin1 - pin0), p)

        obs_now = obst.lerp(obs0, obs1, s1)

        def iterate(_, c):
            p, ls, lb, push, fpush = c
            p, lb = _bend_sweep(model, params, inv_mass, h2, p, lb)
            p, ls = _stretch_sweep(model, params, inv_mass, h2, p, ls)
            if params.tethers:
                p = _tether_project(*tether, p)
            p, dpush = _push_out(params, inv_mass, obs_now, p)  # contacts seen by the solver
            if faces:
                p, dface, fdepth = _push_out_faces(model, params, inv_mass, obs_now, p)
                dpush, fpush = dpush + dface, fpush + fdepth
            return p, ls, lb, push + dpush, fpush

        carry0 = (
            p,
            jnp.zeros((n_col, m), x.dtype),
            jnp.zeros(model.hinge_k.shape[:1] + (3,), x.dtype),
            jnp.zeros(x.shape[:1], x.dtype),
            jnp.zeros(fshape, x.dtype),
        )
        p, _, _, push, fpush = jax.lax.fori_loop(0, params.iterations, iterate, carry0)
        if params.self_collision:
            p = _self_project(inv_mass, radius, p, nbr, nmask)
        obs_prev = obst.lerp(obs0, obs1, s0)
        p = _collide(params, inv_mass, obs_now, obs_prev, x, p, push)
        if faces and params.face_friction:
            p = _collide_faces(model, params, inv_mass, obs_now, obs_prev, x, p, fpush)
        elif faces:
            p, _, _ = _push_out_faces(model, params, inv_mass, obs_now, p)
        return p, (p - x) / h

    x, v = jax.lax.fori_loop(0, n_sub, substep, (x, v))
    return (x, v), (x, v)


_TRACES = 0


def trace_count() -> int:
    """How many times the frame-chunk function has been traced in this process (for retracing tests).

    **Returns:**

    The count.
    """
    return _TRACES


def _chunk(model, params, modes, inv_mass, pinned, tether, x, v, xs):
    global _TRACES
    _TRACES += 1
    (x, v), frames = jax.lax.scan(lambda s, e: _frame(model, params, modes, inv_mass, pinned, tether, s, e), (x, v), xs)
    return x, v, frames


_JIT_CHUNK = jax.jit(_chunk)
_COMPILED: dict = {}


def _signature(args):
    leaves, tree = jax.tree_util.tree_flatten(args)
    return tree, tuple((np.shape(a), str(getattr(a, "dtype", None) or np.asarray(a).dtype)) for a in leaves)


def clear_compiled() -> None:
    """Drop the compiled frame-chunk executables (each holds mapped machine code; see tests/conftest.py).

    **Returns:**

    Nothing.
    """
    _COMPILED.clear()


def _executable(args):
    sig = _signature(args)
    exe = _COMPILED.get(sig)
    if exe is None:
        t = time.perf_counter()
        exe = _JIT_CHUNK.lower(*args).compile()
        _COMPILED[sig] = exe
        return exe, time.perf_counter() - t
    return exe, 0.0


def _params_leaves(params: ClothParams) -> ClothParams:
    return jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32), params)


def tethers(model: ClothModel, pinned) -> tuple[Int[Array, " v"], Float[Array, " v"], Bool[Array, " v"]]:
    """Nearest pinned vertex of every free vertex and its rest distance (host).

    The rest meshes are flat and convex, where that distance is the geodesic one.

    **Arguments:**

    - ``model``: the cloth model.
    - ``pinned``: ``(V,)`` bool mask.

    **Returns:**

    ``(anchor (V,) int32, length (V,) float32, active (V,) bool)``; all inactive when nothing is pinned.
    """
    pinned = np.asarray(pinned, bool)
    rest = np.asarray(model.rest)
    V = len(rest)
    if not pinned.any():
        return jnp.zeros(V, jnp.int32), jnp.zeros(V, jnp.float32), jnp.zeros(V, bool)
    from scipy.spatial import cKDTree

    pid = np.flatnonzero(pinned)
    dist, k = cKDTree(rest[pid]).query(rest)
    return jnp.asarray(pid[k], jnp.int32), jnp.asarray(dist, jnp.float32), jnp.asarray(~pinned)


def inverse_mass(model: ClothModel, params: ClothParams, pinned) -> Float[Array, " v"]:
    """Per-vertex inverse mass: 1 / (density * lumped area), 0 at pinned vertices.

    **Arguments:**

    - ``model``: the cloth model.
    - ``params``: the physical parameters.
    - ``pinned``: ``(V,)`` bool mask.

    **Returns:**

    ``(V,)`` float32.
    """
    return jnp.where(jnp.asarray(pinned), 0.0, 1.0 / (params.density * model.area_v)).astype(jnp.float32)


def step(
    model: ClothModel,
    params: ClothParams,
    x,
    v,
    obstacles_prev: Obstacles,
    obstacles_now: Obstacles,
    key=None,
    *,
    pinned=None,
    pin_prev=None,
    pin_now=None,
    wind_prev=None,
    wind_now=None,
    time_s: float = 0.0,
):
    """One frame (``params.substeps`` substeps) from the obstacles ``obstacles_prev`` to ``obstacles_now``.

    Jitted through the same chunk function as :func:`simulate` (a chunk of one frame).

    **Arguments:**

    - ``model``: the cloth model (:func:`build_model`).
    - ``params``: the physical and solver parameters.
    - ``x``, ``v``: positions and velocities ``(V, 3)``.
    - ``obstacles_prev``, ``obstacles_now``: the obstacles at the start and the end of the frame.
    - ``key``: draws the turbulence modes (the same key gives the same air field).
    - ``pinned``: ``(V,)`` bool mask of the pinned vertices (default None: none).
    - ``pin_prev``, ``pin_now``: the pinned vertices' targets ``(V, 3)`` at the start and end of the frame (defaults:
        ``x``, then ``pin_prev``).
    - ``wind_prev``, ``wind_now``: the mean wind ``(3,)`` at the start and end of the frame (defaults: ``params.wind``,
        then ``wind_prev``).
    - ``time_s``: the simulation time at the start of the frame, in seconds.

    **Returns:**

    The new ``(x, v)``, each ``(V, 3)``.
    """
    V = np.shape(x)[0]
    pinned = np.zeros(V, bool) if pinned is None else np.asarray(pinned, bool)
    x = jnp.asarray(x, jnp.float32)
    pin_prev = x if pin_prev is None else pin_prev
    pin_now = pin_prev if pin_now is None else pin_now
    wm = jnp.asarray(params.wind, jnp.float32)
    wind_prev = wm if wind_prev is None else wind_prev
    wind_now = wind_prev if wind_now is None else wind_now
    xs = (obstacles_prev, obstacles_now, pin_prev, pin_now, wind_prev, wind_now, time_s)
    xs = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float32)[None], xs)
    modes = turbulence_modes(jax.random.PRNGKey(0) if key is None else key)
    x1, v1, _ = _JIT_CHUNK(
        model,
        _params_leaves(params),
        modes,
        inverse_mass(model, params, pinned),
        jnp.asarray(pinned),
        tethers(model, pinned),
        x,
        jnp.asarray(v, jnp.float32),
        xs,
    )
    return x1, v1


def _checked_inputs(model, params, x0, v0, obstacle_track, pinned, pin_track, wind_track):
    """Validate and normalise the inputs of :func:`run`, in the order ``run`` has always checked them.

    Returns ``(x0, v0, track, T, pinned, pins, wind)``: float32 ``x0``/``v0`` (V, 3), the float32 obstacle
    track and its frame count T >= 1, the (V,) bool pin mask, pin targets (T, V, 3) and wind (T, 3).
    Raises :class:`SimulationError` (same messages as before) on the first bad input.
    """
    x0 = np.asarray(x0, np.float32)
    V = model.n_vertices
    if x0.shape != (V, 3):
        raise SimulationError(f"x0 has shape {x0.shape} but the cloth model has {V} vertices.")
    v0 = np.zeros_like(x0) if v0 is None else np.asarray(v0, np.float32)
    if v0.shape != x0.shape:
        raise SimulationError("v0 must have the shape of x0.")
    track = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32), obstacle_track)
    T = obst.n_frames(track)
    if T < 1:
        raise SimulationError("The obstacle track has no frames.")
    pinned = np.zeros(V, bool) if pinned is None else np.asarray(pinned, bool)
    if pinned.shape != (V,):
        raise SimulationError("pinned must be a boolean mask of one entry per vertex.")
    pins = np.broadcast_to(x0, (T, V, 3)) if pin_track is None else np.asarray(pin_track, np.float32)
    if pins.shape != (T, V, 3):
        raise SimulationError(f"pin_track must have shape {(T, V, 3)}, got {pins.shape}.")
    wind = (
        np.broadcast_to(np.asarray(params.wind, np.float32), (T, 3))
        if wind_track is None
        else np.asarray(wind_track, np.float32)
    )
    if wind.shape != (T, 3):
        raise SimulationError(f"wind_track must have shape {(T, 3)}, got {wind.shape}.")
    if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(v0))):
        raise SimulationError("The initial state holds non-finite numbers.")
    return x0, v0, track, T, pinned, pins, wind


def _frame_pairs(params, track, pins, wind, T, start_time, chunk):
    """Per-frame (previous, current) inputs of the scan, padded to whole chunks by repeating the last frame.

    Takes the checked track/pins/wind of T frames. Returns ``(xs_all, n_pad)`` where ``xs_all`` is the
    host-side tuple ``(prev track, cur track, prev pins, cur pins, prev wind, cur wind, times)`` of
    length ``T + n_pad`` (a multiple of ``chunk``); frame 0's previous is itself.
    """
    n_pad = (-T) % chunk
    idx = np.concatenate([np.arange(T), np.full(n_pad, T - 1)])
    prev = np.maximum(idx - 1, 0)
    prev[T:] = T - 1
    times = (start_time + idx * params.frame_dt).astype(np.float32)
    xs_all = (
        jax.tree_util.tree_map(lambda a: a[prev], track),
        jax.tree_util.tree_map(lambda a: a[idx], track),
        pins[prev],
        pins[idx],
        wind[prev],
        wind[idx],
        times,
    )
    return xs_all, n_pad


def _run_chunks(consts, x, v, xs_all, T, n_pad, chunk, progress, desc):
    """Step the simulation chunk by chunk from state ``(x, v)`` with a tqdm bar of T frames.

    ``consts`` is ``(model, params leaves, modes, inverse mass, pin mask, tethers)``. Returns
    ``(frames, v_last, compile_s, run_s)``: the (T, V, 3) positions (padding dropped), the velocity of
    frame T - 1, total compile seconds and total run seconds (compilation apart). No finiteness check.
    """
    from tqdm.auto import tqdm

    out = []
    compile_s = 0.0
    run_s = 0.0
    with tqdm(total=T, desc=desc, unit="frame", disable=not progress, leave=False) as bar:
        for c0 in range(0, T + n_pad, chunk):
            xs = jax.tree_util.tree_map(lambda a: jnp.asarray(a[c0 : c0 + chunk]), xs_all)
            args = (*consts, x, v, xs)
            exe, cs = _executable(args)
            compile_s += cs
            t = time.perf_counter()
            x, v, (fx, fv) = exe(*args)
            fx = np.asarray(fx)
            run_s += time.perf_counter() - t
            out.append(fx)
            if c0 <= T - 1 < c0 + chunk:
                v_last = np.asarray(fv[T - 1 - c0])
            bar.update(min(chunk, T - c0))
    return np.concatenate(out)[:T], v_last, compile_s, run_s


def run(
    model: ClothModel,
    params: ClothParams,
    x0,
    v0,
    obstacle_track: Obstacles,
    pinned=None,
    pin_track=None,
    key=None,
    *,
    wind_track=None,
    start_time: float = 0.0,
    progress: bool = True,
    desc: str = "simulate",
    chunk: int = CHUNK,
) -> SimResult:
    """Simulate T = len(track) frames.

    Frame t is the state after stepping the obstacles from track[t - 1] to track[t] (track[-1] := track[0]), so
    every stored frame went through a collision projection. Deterministic from the key.

    **Arguments:**

    - ``model``: the cloth model (:func:`build_model`).
    - ``params``: the physical and solver parameters.
    - ``x0``, ``v0``: initial positions and velocities ``(V, 3)``.
    - ``obstacle_track``: the obstacles of every frame (T frames).
    - ``pinned``: ``(V,)`` bool mask of the pinned vertices (default None: none).
    - ``pin_track``: ``(T, V, 3)`` targets of the pinned vertices (default: their ``x0``).
    - ``key``: the PRNG key of the turbulence (default None: ``PRNGKey(0)``).
    - ``wind_track``: ``(T, 3)`` mean wind per frame (default: ``params.wind``).
    - ``start_time``: the simulation time of the first frame.
    - ``progress``, ``desc``: a progress bar and its label.
    - ``chunk``: frames per compiled chunk.

    **Returns:**

    A :class:`SimResult`: the frames ``(T, V, 3)`` float32, the last state, the compile time and the seconds per
    frame (compilation apart).

    **Raises:**

    ``SimulationError`` for inputs of the wrong shape (``x0``, ``v0``, ``pinned``, ``pin_track``,
    ``wind_track``), an empty obstacle track, or a simulation that diverges (non-finite positions).
    """
    x0, v0, track, T, pinned, pins, wind = _checked_inputs(
        model, params, x0, v0, obstacle_track, pinned, pin_track, wind_track
    )
    xs_all, n_pad = _frame_pairs(params, track, pins, wind, T, start_time, chunk)
    key = jax.random.PRNGKey(0) if key is None else key
    modes = turbulence_modes(key)
    p = _params_leaves(params)
    w = inverse_mass(model, params, pinned)
    pin_j = jnp.asarray(pinned)
    teth = tethers(model, pinned)
    x, v = jnp.asarray(x0), jnp.asarray(v0)
    frames, v_last, compile_s, run_s = _run_chunks(
        (model, p, modes, w, pin_j, teth), x, v, xs_all, T, n_pad, chunk, progress, desc
    )
    if not np.all(np.isfinite(frames)):
        raise SimulationError("The simulation diverged (non-finite positions); lower the time step or stiffness.")
    return SimResult(
        frames.astype(np.float32),
        frames[-1].astype(np.float32),
        v_last.astype(np.float32),
        compile_s,
        run_s / (T + n_pad),
    )


def simulate(
    model: ClothModel,
    params: ClothParams,
    x0,
    v0,
    obstacle_track: Obstacles,
    pinned=None,
    pin_track=None,
    key=None,
    *,
    wind_track=None,
    progress: bool = True,
) -> np.ndarray:
    """Frames of a simulation (see :func:`run`); one compile per (mesh, static params).

    **Arguments:**

    As :func:`run`'s.

    **Returns:**

    The frames ``(T, V, 3)`` float32.

    **Raises:**

    As :func:`run`.
    """
    return run(
        model, params, x0, v0, obstacle_track, pinned, pin_track, key, wind_track=wind_track, progress=progress
    ).frames


def edge_strain(model: ClothModel, frames) -> tuple[float, float]:
    """Mean and max relative edge stretch |l / L - 1| over frames and edges.

    **Arguments:**

    - ``model``: the cloth model.
    - ``frames``: positions ``(T, V, 3)``.

    **Returns:**

    ``(mean, max)`` as floats.
    """
    f = jnp.asarray(frames)
    e = model.edges
    ln = jnp.linalg.norm(f[:, e[:, 0]] - f[:, e[:, 1]], axis=-1)
    s = jnp.abs(ln / model.rest_len - 1.0)
    return float(s.mean()), float(s.max())
