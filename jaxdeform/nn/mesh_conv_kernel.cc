// Mesh convolution of seed 000, eq. (1), and its adjoint, as XLA FFI custom calls on CPU.
// Loaded by jaxdeform/nn/native.py; the pure-JAX definition in jaxdeform/nn/graph_conv.py is the reference.
//
// Layout: x (G, P, V, Ci) with G weight groups (blocks of a level) of P planes (shapes) each; the one-rings
// nbr (V, K) int32 with the valid slots of row i first (count[i] of them) and inv[i] = 1 / max(count[i], 1);
// weights Wp, Wn (G, Ci, Co), bias b (G, Co). jax.vmap ("broadcast_all") gives every argument the same leading
// batch dimensions, so the weight groups are a prefix of x's planes; a single weight group (G_w = 1) is shared
// by every group of the output.
//
//   forward   y[g,p,i] = x[g,p,i] Wp[g] + (inv[i] sum_k x[g,p,n_ik]) Wn[g] + b[g]
//   backward  gx[g,p,i] = gy[g,p,i] Wp[g]^T + (sum_k inv[n_ik] gy[g,p,n_ik]) Wn[g]^T   (symmetric rings)
//             gWp[g] = sum_{p,i} x^T gy,  gWn[g] = sum_{p,i} r^T gy (r: the forward ring mean), gb[g] = sum gy
//
// Why: XLA on CPU fuses the producer of a gather's operand into the gather (so tanh chains and the forward ring
// sums are recomputed once per ring slot in the backward pass), and runs the 9x9 channel mixes as batched
// matrix products with N = 9 at a fraction of memory speed. Here each row of 9 channels is read once.
#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <thread>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

constexpr int kLanes = 16;  // at most 16 channels in and out

struct Geometry {
  int64_t G = 1, P = 1, V = 0, K = 0, Ci = 0, Co = 0, Gw = 1;
};

// The most threads one call uses: JAXDEFORM_NATIVE_THREADS if set, else the hardware's, at most 16.
int64_t MaxThreads() {
  static const int64_t n = [] {
    const char* env = std::getenv("JAXDEFORM_NATIVE_THREADS");
    const int64_t want = (env != nullptr && std::atoi(env) > 0)
                             ? std::atoi(env)
                             : static_cast<int64_t>(std::max(1u, std::thread::hardware_concurrency()));
    return std::min<int64_t>(want, 16);
  }();
  return n;
}

// Runs fn(thread_index, plane_begin, plane_end) over `planes` split into contiguous ranges; thread_index is
// below MaxThreads().
template <typename Fn>
void ParallelPlanes(int64_t planes, int64_t work_per_plane, Fn fn) {
  int64_t threads = std::min<int64_t>({MaxThreads(), planes,
                                       std::max<int64_t>(1, planes * work_per_plane / (1 << 16))});
  if (threads <= 1) {
    fn(0, 0, planes);
    return;
  }
  std::vector<std::thread> pool;
  const int64_t chunk = (planes + threads - 1) / threads;
  for (int64_t t = 1; t < threads; ++t) {
    const int64_t b = t * chunk, e = std::min(planes, b + chunk);
    if (b < e) pool.emplace_back(fn, t, b, e);
  }
  fn(0, 0, std::min(planes, chunk));
  for (auto& th : pool) th.join();
}

// Any channel counts up to kLanes, read from the geometry. The 9-channel case of seed 000 runs Forward9 /
// Backward9 below instead.
template <typename T>
void ForwardPlanes(const Geometry& s, const T* __restrict__ x, const int32_t* __restrict__ nbr,
                   const int32_t* __restrict__ count, const T* __restrict__ inv, const T* __restrict__ wp,
                   const T* __restrict__ wn, const T* __restrict__ b, T* __restrict__ y, int64_t p0, int64_t p1) {
  const int64_t Ci = s.Ci, Co = s.Co, V = s.V, K = s.K;
  for (int64_t q = p0; q < p1; ++q) {  // q = g * P + p
    const int64_t g = (s.Gw == 1) ? 0 : q / s.P;
    const T* __restrict__ Wp = wp + g * Ci * Co;
    const T* __restrict__ Wn = wn + g * Ci * Co;
    const T* __restrict__ B = b + g * Co;
    const T* __restrict__ plane = x + q * V * Ci;
    T* __restrict__ out = y + q * V * Co;
    for (int64_t i = 0; i < V; ++i) {
      T r[kLanes] = {};
      const int32_t* ring = nbr + i * K;
      const int32_t n = count[i];
      for (int32_t k = 0; k < n; ++k) {
        const T* __restrict__ src = plane + static_cast<int64_t>(ring[k]) * Ci;
        for (int64_t c = 0; c < Ci; ++c) r[c] += src[c];
      }
      const T w = inv[i];
      const T* __restrict__ xi = plane + i * Ci;
      T o[kLanes];
      for (int64_t d = 0; d < Co; ++d) o[d] = B[d];
      for (int64_t c = 0; c < Ci; ++c) {
        const T a = xi[c], rn = r[c] * w;
        for (int64_t d = 0; d < Co; ++d) o[d] += a * Wp[c * Co + d] + rn * Wn[c * Co + d];
      }
      for (int64_t d = 0; d < Co; ++d) out[i * Co + d] = o[d];
    }
  }
}

template <typename T>
void BackwardPlanes(const Geometry& s, const T* __restrict__ x, const T* __restrict__ gy,
                    const int32_t* __restrict__ nbr, const int32_t* __restrict__ count, const T* __restrict__ inv,
                    const T* __restrict__ wp, const T* __restrict__ wn, T* __restrict__ gx, T* __restrict__ acc,
                    int64_t p0, int64_t p1) {
  // acc: this thread's (G, 2 * Ci * Co + Co) partial sums of gWp, gWn, gb; each plane first sums into
  // local arrays (kept in registers / L1), added to acc once per plane
  const int64_t Ci = s.Ci, Co = s.Co, V = s.V, K = s.K;
  const int64_t stride = 2 * Ci * Co + Co;
  for (int64_t q = p0; q < p1; ++q) {
    const int64_t g = q / s.P;
    const int64_t gw = (s.Gw == 1) ? 0 : g;
    T Wp[kLanes * kLanes], Wn[kLanes * kLanes];
    for (int64_t e = 0; e < Ci * Co; ++e) {
      Wp[e] = wp[gw * Ci * Co + e];
      Wn[e] = wn[gw * Ci * Co + e];
    }
    T lp[kLanes * kLanes] = {}, ln[kLanes * kLanes] = {}, lb[kLanes] = {};
    const T* __restrict__ xp = x + q * V * Ci;
    const T* __restrict__ gp = gy + q * V * Co;
    T* __restrict__ gxp = gx + q * V * Ci;
    for (int64_t i = 0; i < V; ++i) {
      T sg[kLanes] = {};  // sum_k inv[j] gy[j]
      T r[kLanes] = {};   // sum_k x[j]
      const int32_t* ring = nbr + i * K;
      const int32_t n = count[i];
      for (int32_t k = 0; k < n; ++k) {
        const int64_t j = ring[k];
        const T wj = inv[j];
        const T* __restrict__ gsrc = gp + j * Co;
        for (int64_t d = 0; d < Co; ++d) sg[d] += wj * gsrc[d];
        const T* __restrict__ xsrc = xp + j * Ci;
        for (int64_t c = 0; c < Ci; ++c) r[c] += xsrc[c];
      }
      const T wi = inv[i];
      T gi[kLanes], xi[kLanes];
      for (int64_t d = 0; d < Co; ++d) gi[d] = gp[i * Co + d];
      for (int64_t c = 0; c < Ci; ++c) xi[c] = xp[i * Ci + c];
      for (int64_t c = 0; c < Ci; ++c) {
        T v = 0;
        for (int64_t d = 0; d < Co; ++d) v += gi[d] * Wp[c * Co + d] + sg[d] * Wn[c * Co + d];
        gxp[i * Ci + c] = v;
        const T a = xi[c], rn = r[c] * wi;
        for (int64_t d = 0; d < Co; ++d) {
          lp[c * Co + d] += a * gi[d];
          ln[c * Co + d] += rn * gi[d];
        }
      }
      for (int64_t d = 0; d < Co; ++d) lb[d] += gi[d];
    }
    T* __restrict__ out = acc + g * stride;
    for (int64_t e = 0; e < Ci * Co; ++e) {
      out[e] += lp[e];
      out[Ci * Co + e] += ln[e];
    }
    for (int64_t d = 0; d < Co; ++d) out[2 * Ci * Co + d] += lb[d];
  }
}

// The seed-000 case, 9 channels in and out, written on rows of 9 held as one 8-wide vector plus a scalar
// (GCC/Clang vector extensions: two AVX registers for a float row at most), so that the one-ring sums, the
// channel mixes and the weight-gradient sums stay in registers. The generic loops above keep the ring sum
// and the 2 x 81 weight-gradient accumulators in memory arrays. On the horse training split (8431 vertices,
// 50 planes) the adjoint runs 1.5-2x faster this way; the forward, bound by the one-ring gathers, about the
// same.
template <typename T>
struct Row9 {
  typedef T V8 __attribute__((vector_size(8 * sizeof(T))));
  V8 v;
  T s;
  static Row9 Zero() { Row9 r; r.v = V8{}; r.s = T(0); return r; }
  static Row9 Load(const T* p) { Row9 r; std::memcpy(&r.v, p, sizeof(V8)); r.s = p[8]; return r; }
  void Store(T* p) const { std::memcpy(p, &v, sizeof(V8)); p[8] = s; }
  T operator[](int c) const { return c < 8 ? v[c] : s; }
  Row9& operator+=(const Row9& o) { v += o.v; s += o.s; return *this; }
  void Fma(T a, const Row9& w) { v += a * w.v; s += a * w.s; }  // this += a * w
  void Scale(T a) { v *= a; s *= a; }
};

// rows[c] = row c of a 9x9 row-major matrix m (transpose = false) or column c (transpose = true)
template <typename T>
void LoadRows(const T* m, bool transpose, Row9<T>* rows) {
  for (int c = 0; c < 9; ++c) {
    T tmp[9];
    for (int d = 0; d < 9; ++d) tmp[d] = transpose ? m[d * 9 + c] : m[c * 9 + d];
    rows[c] = Row9<T>::Load(tmp);
  }
}

// init + sum_c a[c] A[c] + b[c] B[c], with four independent accumulators: one chain of 18 dependent FMAs
// would bound the vertex loop by their latency. a and b are rows in memory: their entries are broadcast
// from there (extracting lanes of a register costs more).
template <typename T>
Row9<T> Mix9(const Row9<T>& init, const T* a, const Row9<T>* A, const T* b, const Row9<T>* B) {
  Row9<T> o[4] = {init, Row9<T>::Zero(), Row9<T>::Zero(), Row9<T>::Zero()};
  for (int c = 0; c < 9; ++c) {
    o[c & 1].Fma(a[c], A[c]);
    o[2 + (c & 1)].Fma(b[c], B[c]);
  }
  o[0] += o[1];
  o[2] += o[3];
  o[0] += o[2];
  return o[0];
}

template <typename T>
void Forward9(const Geometry& s, const T* __restrict__ x, const int32_t* __restrict__ nbr,
              const int32_t* __restrict__ count, const T* __restrict__ inv, const T* __restrict__ wp,
              const T* __restrict__ wn, const T* __restrict__ b, T* __restrict__ y, int64_t p0, int64_t p1) {
  using R = Row9<T>;
  const int64_t V = s.V, K = s.K;
  R Wp[9], Wn[9], B;
  int64_t loaded = -1;
  for (int64_t q = p0; q < p1; ++q) {  // q = g * P + p
    const int64_t g = (s.Gw == 1) ? 0 : q / s.P;
    if (g != loaded) {
      LoadRows(wp + g * 81, false, Wp);
      LoadRows(wn + g * 81, false, Wn);
      B = R::Load(b + g * 9);
      loaded = g;
    }
    const T* __restrict__ plane = x + q * V * 9;
    T* __restrict__ out = y + q * V * 9;
    for (int64_t i = 0; i < V; ++i) {
      const int32_t* ring = nbr + i * K;
      const int32_t n = count[i];
      R r = R::Zero();
      for (int32_t k = 0; k < n; ++k) r += R::Load(plane + static_cast<int64_t>(ring[k]) * 9);
      r.Scale(inv[i]);
      T rm[9];
      r.Store(rm);
      Mix9(B, plane + i * 9, Wp, rm, Wn).Store(out + i * 9);
    }
  }
}

// Backward: per vertex the ring sums (of x, for gW_neighbor; of inv * gy, for gx) and gx = gy Wp^T + sg Wn^T;
// the weight gradients [x | r/D]^T gy are summed over tiles of kTile vertices, one output row (input
// channel) at a time, so that the accumulator row stays in registers over the tile.
constexpr int kTile = 32;

template <typename T>
void Backward9(const Geometry& s, const T* __restrict__ x, const T* __restrict__ gy,
               const int32_t* __restrict__ nbr, const int32_t* __restrict__ count, const T* __restrict__ inv,
               const T* __restrict__ wp, const T* __restrict__ wn, T* __restrict__ gx, T* __restrict__ acc,
               int64_t p0, int64_t p1) {
  using R = Row9<T>;
  const int64_t V = s.V, K = s.K;
  const int64_t stride = 2 * 81 + 9;
  R WpT[9], WnT[9];  // WpT[d] = column d of Wp: gx_i = sum_d gy_i[d] WpT[d] + sg_i[d] WnT[d]
  int64_t loaded = -1;
  alignas(64) T At[kTile][18];  // x_i | r_i / D_i
  R Gt[kTile];
  for (int64_t q = p0; q < p1; ++q) {
    const int64_t g = q / s.P;
    const int64_t gw = (s.Gw == 1) ? 0 : g;
    if (gw != loaded) {
      LoadRows(wp + gw * 81, true, WpT);
      LoadRows(wn + gw * 81, true, WnT);
      loaded = gw;
    }
    R lw[18];
    for (auto& r : lw) r = R::Zero();
    R lb = R::Zero();
    const T* __restrict__ xp = x + q * V * 9;
    const T* __restrict__ gp = gy + q * V * 9;
    T* __restrict__ gxp = gx + q * V * 9;
    for (int64_t i0 = 0; i0 < V; i0 += kTile) {
      const int64_t nt = std::min<int64_t>(kTile, V - i0);
      for (int64_t t = 0; t < nt; ++t) {
        const int64_t i = i0 + t;
        const int32_t* ring = nbr + i * K;
        const int32_t n = count[i];
        R sg = R::Zero(), r = R::Zero();
        for (int32_t k = 0; k < n; ++k) {
          const int64_t j = ring[k];
          sg.Fma(inv[j], R::Load(gp + j * 9));
          r += R::Load(xp + j * 9);
        }
        r.Scale(inv[i]);
        const R gi = R::Load(gp + i * 9);
        T sgm[9];
        sg.Store(sgm);
        Mix9(R::Zero(), gp + i * 9, WpT, sgm, WnT).Store(gxp + i * 9);
        std::memcpy(At[t], xp + i * 9, 9 * sizeof(T));
        r.Store(At[t] + 9);
        Gt[t] = gi;
        lb += gi;
      }
      for (int e = 0; e < 18; ++e) {
        R row[2] = {lw[e], R::Zero()};
        int64_t t = 0;
        for (; t + 1 < nt; t += 2) {
          row[0].Fma(At[t][e], Gt[t]);
          row[1].Fma(At[t + 1][e], Gt[t + 1]);
        }
        if (t < nt) row[0].Fma(At[t][e], Gt[t]);
        row[0] += row[1];
        lw[e] = row[0];
      }
    }
    T* __restrict__ out = acc + g * stride;
    for (int e = 0; e < 18; ++e)
      for (int d = 0; d < 9; ++d) out[e * 9 + d] += lw[e][d];
    for (int d = 0; d < 9; ++d) out[2 * 81 + d] += lb[d];
  }
}

ffi::Error CheckRings(const Geometry& s, ffi::AnyBuffer nbr, ffi::AnyBuffer count, ffi::AnyBuffer inv) {
  if (nbr.element_type() != ffi::DataType::S32 || count.element_type() != ffi::DataType::S32)
    return ffi::Error::InvalidArgument("mesh_conv: neighbors and counts must be int32");
  // jax.vmap ("broadcast_all") may hand in identical broadcast copies of the tables: the first one is used
  const int64_t n = static_cast<int64_t>(nbr.element_count()), c = static_cast<int64_t>(count.element_count()),
                v = static_cast<int64_t>(inv.element_count());
  if (s.V * s.K == 0 || n % (s.V * s.K) != 0 || c % s.V != 0 || v % s.V != 0 || c == 0 || v == 0)
    return ffi::Error::InvalidArgument("mesh_conv: one-ring tables do not match the vertex count");
  return ffi::Error::Success();
}

ffi::Error MakeGeometry(ffi::AnyBuffer x, ffi::AnyBuffer nbr, ffi::AnyBuffer wp, int64_t out_groups, Geometry* s) {
  auto xd = x.dimensions();
  auto nd = nbr.dimensions();
  auto wd = wp.dimensions();
  if (xd.size() < 2 || nd.size() < 2 || wd.size() < 2)
    return ffi::Error::InvalidArgument("mesh_conv: x, neighbors and weights need rank >= 2");
  s->V = xd[xd.size() - 2];
  s->Ci = xd[xd.size() - 1];
  s->K = nd[nd.size() - 1];
  s->Co = wd[wd.size() - 1];
  if (wd[wd.size() - 2] != s->Ci) return ffi::Error::InvalidArgument("mesh_conv: weights do not match x's channels");
  if (s->Ci > kLanes || s->Co > kLanes) return ffi::Error::InvalidArgument("mesh_conv: at most 16 channels");
  if (nd[nd.size() - 2] != s->V) return ffi::Error::InvalidArgument("mesh_conv: neighbors do not match x's vertices");
  s->Gw = static_cast<int64_t>(wp.element_count()) / (s->Ci * s->Co);
  s->G = std::max(s->Gw, out_groups);
  const int64_t planes = (s->V * s->Ci == 0) ? 0 : static_cast<int64_t>(x.element_count()) / (s->V * s->Ci);
  if (s->G < 1 || planes % s->G != 0 || (s->Gw != 1 && s->Gw != s->G))
    return ffi::Error::InvalidArgument("mesh_conv: batch dimensions of x and the weights do not line up");
  s->P = planes / s->G;
  return ffi::Error::Success();
}

template <typename T>
ffi::Error Forward(ffi::AnyBuffer x, ffi::AnyBuffer nbr, ffi::AnyBuffer count, ffi::AnyBuffer inv,
                   ffi::AnyBuffer wp, ffi::AnyBuffer wn, ffi::AnyBuffer b, ffi::Result<ffi::AnyBuffer> y) {
  Geometry s;
  if (auto e = MakeGeometry(x, nbr, wp, 1, &s); e.failure()) return e;
  if (auto e = CheckRings(s, nbr, count, inv); e.failure()) return e;
  const T* xp = static_cast<const T*>(x.untyped_data());
  const int32_t* np_ = static_cast<const int32_t*>(nbr.untyped_data());
  const int32_t* cp = static_cast<const int32_t*>(count.untyped_data());
  const T* ip = static_cast<const T*>(inv.untyped_data());
  const T* wpp = static_cast<const T*>(wp.untyped_data());
  const T* wnp = static_cast<const T*>(wn.untyped_data());
  const T* bp = static_cast<const T*>(b.untyped_data());
  T* yp = static_cast<T*>(y->untyped_data());
  const bool nine = s.Ci == 9 && s.Co == 9;
  ParallelPlanes(s.G * s.P, s.V * (s.K + 2 * s.Co) * s.Ci, [&](int64_t, int64_t p0, int64_t p1) {
    if (nine) Forward9<T>(s, xp, np_, cp, ip, wpp, wnp, bp, yp, p0, p1);
    else ForwardPlanes<T>(s, xp, np_, cp, ip, wpp, wnp, bp, yp, p0, p1);
  });
  return ffi::Error::Success();
}

template <typename T>
ffi::Error Backward(ffi::AnyBuffer x, ffi::AnyBuffer gy, ffi::AnyBuffer nbr, ffi::AnyBuffer count,
                    ffi::AnyBuffer inv, ffi::AnyBuffer wp, ffi::AnyBuffer wn, ffi::Result<ffi::AnyBuffer> gx,
                    ffi::Result<ffi::AnyBuffer> gwp, ffi::Result<ffi::AnyBuffer> gwn,
                    ffi::Result<ffi::AnyBuffer> gb) {
  Geometry s;
  const int64_t ci = x.dimensions().back(), co = wp.dimensions().back();
  const int64_t out_groups = (ci * co == 0) ? 1 : static_cast<int64_t>(gwp->element_count()) / (ci * co);
  if (auto e = MakeGeometry(x, nbr, wp, out_groups, &s); e.failure()) return e;
  if (auto e = CheckRings(s, nbr, count, inv); e.failure()) return e;
  if (static_cast<int64_t>(gb->element_count()) != s.G * s.Co)
    return ffi::Error::InvalidArgument("mesh_conv: bias gradient has the wrong size");
  const int64_t stride = 2 * s.Ci * s.Co + s.Co;
  std::vector<T> acc(static_cast<size_t>(MaxThreads() * s.G * stride), T(0));
  const T* xp = static_cast<const T*>(x.untyped_data());
  const T* gp = static_cast<const T*>(gy.untyped_data());
  const int32_t* np_ = static_cast<const int32_t*>(nbr.untyped_data());
  const int32_t* cp = static_cast<const int32_t*>(count.untyped_data());
  const T* ip = static_cast<const T*>(inv.untyped_data());
  const T* wpp = static_cast<const T*>(wp.untyped_data());
  const T* wnp = static_cast<const T*>(wn.untyped_data());
  T* gxp = static_cast<T*>(gx->untyped_data());
  const bool nine = s.Ci == 9 && s.Co == 9;
  ParallelPlanes(s.G * s.P, s.V * (2 * s.K + 4 * s.Co) * s.Ci, [&](int64_t t, int64_t p0, int64_t p1) {
    T* a = acc.data() + t * s.G * stride;
    if (nine) Backward9<T>(s, xp, gp, np_, cp, ip, wpp, wnp, gxp, a, p0, p1);
    else BackwardPlanes<T>(s, xp, gp, np_, cp, ip, wpp, wnp, gxp, a, p0, p1);
  });
  T* out_p = static_cast<T*>(gwp->untyped_data());
  T* out_n = static_cast<T*>(gwn->untyped_data());
  T* out_b = static_cast<T*>(gb->untyped_data());
  const int64_t cc = s.Ci * s.Co;
  std::fill(out_p, out_p + s.G * cc, T(0));
  std::fill(out_n, out_n + s.G * cc, T(0));
  std::fill(out_b, out_b + s.G * s.Co, T(0));
  const int64_t threads = static_cast<int64_t>(acc.size()) / (s.G * stride);
  for (int64_t t = 0; t < threads; ++t) {
    const T* a = acc.data() + t * s.G * stride;
    for (int64_t g = 0; g < s.G; ++g) {
      const T* ag = a + g * stride;
      for (int64_t e = 0; e < cc; ++e) out_p[g * cc + e] += ag[e];
      for (int64_t e = 0; e < cc; ++e) out_n[g * cc + e] += ag[cc + e];
      for (int64_t e = 0; e < s.Co; ++e) out_b[g * s.Co + e] += ag[2 * cc + e];
    }
  }
  return ffi::Error::Success();
}

bool SameFloat(std::initializer_list<ffi::DataType> types, ffi::DataType* t) {
  *t = *types.begin();
  for (auto u : types)
    if (u != *t) return false;
  return *t == ffi::DataType::F32 || *t == ffi::DataType::F64;
}

ffi::Error ForwardDispatch(ffi::AnyBuffer x, ffi::AnyBuffer nbr, ffi::AnyBuffer count, ffi::AnyBuffer inv,
                           ffi::AnyBuffer wp, ffi::AnyBuffer wn, ffi::AnyBuffer b, ffi::Result<ffi::AnyBuffer> y) {
  ffi::DataType t;
  if (!SameFloat({x.element_type(), inv.element_type(), wp.element_type(), wn.element_type(), b.element_type(),
                  y->element_type()}, &t))
    return ffi::Error::InvalidArgument("mesh_conv: float arrays must all be float32 or all float64");
  if (t == ffi::DataType::F32) return Forward<float>(x, nbr, count, inv, wp, wn, b, y);
  return Forward<double>(x, nbr, count, inv, wp, wn, b, y);
}

ffi::Error BackwardDispatch(ffi::AnyBuffer x, ffi::AnyBuffer gy, ffi::AnyBuffer nbr, ffi::AnyBuffer count,
                            ffi::AnyBuffer inv, ffi::AnyBuffer wp, ffi::AnyBuffer wn,
                            ffi::Result<ffi::AnyBuffer> gx, ffi::Result<ffi::AnyBuffer> gwp,
                            ffi::Result<ffi::AnyBuffer> gwn, ffi::Result<ffi::AnyBuffer> gb) {
  ffi::DataType t;
  if (!SameFloat({x.element_type(), gy.element_type(), inv.element_type(), wp.element_type(), wn.element_type(),
                  gx->element_type(), gwp->element_type(), gwn->element_type(), gb->element_type()}, &t))
    return ffi::Error::InvalidArgument("mesh_conv: float arrays must all be float32 or all float64");
  if (t == ffi::DataType::F32) return Backward<float>(x, gy, nbr, count, inv, wp, wn, gx, gwp, gwn, gb);
  return Backward<double>(x, gy, nbr, count, inv, wp, wn, gx, gwp, gwn, gb);
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxdeformMeshConvFwd, ForwardDispatch,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // x
                                  .Arg<ffi::AnyBuffer>()  // neighbors
                                  .Arg<ffi::AnyBuffer>()  // counts
                                  .Arg<ffi::AnyBuffer>()  // inverse degrees
                                  .Arg<ffi::AnyBuffer>()  // W_point
                                  .Arg<ffi::AnyBuffer>()  // W_neighbor
                                  .Arg<ffi::AnyBuffer>()  // b
                                  .Ret<ffi::AnyBuffer>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxdeformMeshConvBwd, BackwardDispatch,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // x
                                  .Arg<ffi::AnyBuffer>()  // cotangent of y
                                  .Arg<ffi::AnyBuffer>()  // neighbors
                                  .Arg<ffi::AnyBuffer>()  // counts
                                  .Arg<ffi::AnyBuffer>()  // inverse degrees
                                  .Arg<ffi::AnyBuffer>()  // W_point
                                  .Arg<ffi::AnyBuffer>()  // W_neighbor
                                  .Ret<ffi::AnyBuffer>()  // gx
                                  .Ret<ffi::AnyBuffer>()  // gW_point
                                  .Ret<ffi::AnyBuffer>()  // gW_neighbor
                                  .Ret<ffi::AnyBuffer>());  // gb
