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
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <atomic>
#include <condition_variable>
#include <cstring>
#include <functional>
#include <initializer_list>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <thread>
#include <type_traits>
#include <vector>

#if defined(__AVX2__)
#include <immintrin.h>
#endif

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

// XLA's intra-op thread pool of the call being served (set by the handlers, see PoolScope), or null.
thread_local ffi::ThreadPool* tls_pool = nullptr;

struct PoolScope {
  ffi::ThreadPool* prev;
  explicit PoolScope(ffi::ThreadPool* pool) : prev(tls_pool) { tls_pool = pool; }
  ~PoolScope() { tls_pool = prev; }
};

// How a range of work is cut: `chunks` pieces of `len` items (the last one shorter). The cut depends on the
// sizes only, never on the thread count, and the kernels keep one partial sum per chunk, added in chunk order:
// results are the same bit for bit whatever the number of threads.
struct Plan {
  int64_t chunks = 1, len = 0;
};

constexpr int64_t kMaxChunks = 16;

// n items of `work` each, cut into pieces of a multiple of `unit` items, at least 2^16 work per piece
Plan MakePlan(int64_t n, int64_t unit, int64_t work) {
  const int64_t units = std::max<int64_t>(1, (n + unit - 1) / unit);
  const int64_t want = std::min<int64_t>({kMaxChunks, units, std::max<int64_t>(1, n * work / (1 << 16))});
  Plan p;
  p.len = (units + want - 1) / want * unit;
  p.chunks = std::max<int64_t>(1, (n + p.len - 1) / p.len);
  return p;
}

// The chunks of one parallel call; shared with the helper tasks, which may start after the call has returned
// (they then find no chunk left and touch nothing else). A chunk that throws (an allocation) is counted as done
// and flagged, so that the call still waits for every other chunk before it reports the failure.
struct ChunkQueue {
  std::atomic<int64_t> next{0}, done{0};
  std::atomic<bool> failed{false};
  int64_t total = 0;
  const std::function<void(int64_t)>* run = nullptr;  // valid while done < total
  std::mutex m;
  std::condition_variable cv;

  void Work() {
    for (;;) {
      const int64_t c = next.fetch_add(1);
      if (c >= total) return;
      try {
        (*run)(c);
      } catch (...) {
        failed.store(true);
      }
      if (done.fetch_add(1) + 1 == total) {
        std::lock_guard<std::mutex> lock(m);
        cv.notify_all();
      }
    }
  }
};

// Runs fn(chunk, begin, end) for every chunk of `plan` over [0, n). Threads claim chunks one at a time: the
// calling thread, and helpers on XLA's own intra-op thread pool (as many as the pool has threads, less one, and
// at most MaxThreads() - 1), or on std::thread where the call has no pool. A helper the pool cannot start at once
// (its threads busy with other operations of the program) leaves its chunks to the others, so a call never waits
// for a core that XLA is using. Throws std::runtime_error, after every chunk has ended, if one of them threw.
template <typename Fn>
void RunPlan(const Plan& plan, int64_t n, Fn fn) {
  if (plan.chunks <= 1) {
    fn(int64_t{0}, int64_t{0}, n);
    return;
  }
  const std::function<void(int64_t)> run = [&](int64_t c) {
    fn(c, c * plan.len, std::min(n, (c + 1) * plan.len));
  };
  auto q = std::make_shared<ChunkQueue>();
  q->total = plan.chunks;
  q->run = &run;
  ffi::ThreadPool* pool = tls_pool;
  const int64_t pool_threads = pool != nullptr ? pool->num_threads() : 0;
  if (pool_threads <= 0) pool = nullptr;  // no pool (or its size unknown): threads of our own
  const int64_t threads = std::min<int64_t>({plan.chunks, MaxThreads(), pool != nullptr ? pool_threads : MaxThreads()});
  std::vector<std::thread> own;
  for (int64_t t = 1; t < threads; ++t) {
    if (pool != nullptr) pool->Schedule([q] { q->Work(); });
    else own.emplace_back([q] { q->Work(); });
  }
  q->Work();
  {
    std::unique_lock<std::mutex> lock(q->m);
    q->cv.wait(lock, [&] { return q->done.load() == q->total; });
  }
  for (auto& th : own) th.join();
  if (q->failed.load()) throw std::runtime_error("a chunk of a native mesh kernel failed (out of memory?)");
}

// The cut of `planes` into chunks of whole planes (RunPlan(plan, planes, fn) runs fn(chunk, p0, p1) over them)
Plan PlanPlanes(int64_t planes, int64_t work_per_plane) { return MakePlan(planes, 1, work_per_plane); }

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
  // acc: this chunk's (G, 2 * Ci * Co + Co) partial sums of gWp, gWn, gb; each plane first sums into
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

// Ring sums over the n ring slots `ring` of one vertex in kRun planes at base + q * pstride: r[q] = sum_k a[n_k]
// (the ring mean before its 1 / D_i), or with kAdjoint sum_k inv[n_k] a[n_k] (the adjoint of the ring mean, rings
// being symmetric). The ring's indices are read once for all kRun planes, whose sums are independent chains.
template <typename T, bool kAdjoint, int kRun>
void RingSums(const T* base, int64_t pstride, const int32_t* ring, int32_t n, const T* inv, Row9<T>* r) {
  for (int q = 0; q < kRun; ++q) r[q] = Row9<T>::Zero();
  for (int32_t k = 0; k < n; ++k) {
    const int64_t j = ring[k];
    const T* src = base + j * 9;
    if constexpr (kAdjoint) {
      const T w = inv[j];
      for (int q = 0; q < kRun; ++q) r[q].Fma(w, Row9<T>::Load(src + q * pstride));
    } else {
      for (int q = 0; q < kRun; ++q) r[q] += Row9<T>::Load(src + q * pstride);
    }
  }
}

// (inv[i] sum_k a[n_ik]) over the ring of vertex i of one plane of rows
template <typename T>
Row9<T> RingMean(const T* plane, const int32_t* nbr, const int32_t* count, const T* inv, int64_t K, int64_t i) {
  Row9<T> r;
  RingSums<T, false, 1>(plane, 0, nbr + i * K, count[i], inv, &r);
  r.Scale(inv[i]);
  return r;
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
      T rm[9];
      RingMean(plane, nbr, count, inv, K, i).Store(rm);
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
  RunPlan(PlanPlanes(s.G * s.P, s.V * (s.K + 2 * s.Co) * s.Ci), s.G * s.P, [&](int64_t, int64_t p0, int64_t p1) {
    if (nine) Forward9<T>(s, xp, np_, cp, ip, wpp, wnp, bp, yp, p0, p1);
    else ForwardPlanes<T>(s, xp, np_, cp, ip, wpp, wnp, bp, yp, p0, p1);
  });
  return ffi::Error::Success();
}

// Sums the per-chunk weight-gradient partials acc (chunks x groups x [gWp (cc) | gWn (cc) | gb (co)], with
// cc = Ci Co) into the outputs, in chunk order
template <typename T>
void ReduceWeightGrads(const std::vector<T>& acc, int64_t groups, int64_t cc, int64_t co, T* gwp, T* gwn, T* gb) {
  std::fill(gwp, gwp + groups * cc, T(0));
  std::fill(gwn, gwn + groups * cc, T(0));
  std::fill(gb, gb + groups * co, T(0));
  const int64_t stride = 2 * cc + co;
  const int64_t chunks = static_cast<int64_t>(acc.size()) / (groups * stride);
  for (int64_t t = 0; t < chunks; ++t)
    for (int64_t g = 0; g < groups; ++g) {
      const T* a = acc.data() + (t * groups + g) * stride;
      for (int64_t e = 0; e < cc; ++e) gwp[g * cc + e] += a[e];
      for (int64_t e = 0; e < cc; ++e) gwn[g * cc + e] += a[cc + e];
      for (int64_t e = 0; e < co; ++e) gb[g * co + e] += a[2 * cc + e];
    }
}

// Sums per-chunk partials (chunks x n, as many chunks as part holds) into out (n), in chunk order
template <typename T>
void SumChunkParts(const std::vector<T>& part, int64_t n, T* out) {
  std::fill(out, out + n, T(0));
  for (size_t t = 0; t < part.size() / static_cast<size_t>(std::max<int64_t>(n, 1)); ++t)
    for (int64_t e = 0; e < n; ++e) out[e] += part[t * n + e];
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
  const Plan plan = PlanPlanes(s.G * s.P, s.V * (2 * s.K + 4 * s.Co) * s.Ci);
  std::vector<T> acc(static_cast<size_t>(plan.chunks * s.G * stride), T(0));
  const T* xp = static_cast<const T*>(x.untyped_data());
  const T* gp = static_cast<const T*>(gy.untyped_data());
  const int32_t* np_ = static_cast<const int32_t*>(nbr.untyped_data());
  const int32_t* cp = static_cast<const int32_t*>(count.untyped_data());
  const T* ip = static_cast<const T*>(inv.untyped_data());
  const T* wpp = static_cast<const T*>(wp.untyped_data());
  const T* wnp = static_cast<const T*>(wn.untyped_data());
  T* gxp = static_cast<T*>(gx->untyped_data());
  const bool nine = s.Ci == 9 && s.Co == 9;
  RunPlan(plan, s.G * s.P, [&](int64_t t, int64_t p0, int64_t p1) {
    T* a = acc.data() + t * s.G * stride;
    if (nine) Backward9<T>(s, xp, gp, np_, cp, ip, wpp, wnp, gxp, a, p0, p1);
    else BackwardPlanes<T>(s, xp, gp, np_, cp, ip, wpp, wnp, gxp, a, p0, p1);
  });
  ReduceWeightGrads(acc, s.G, s.Ci * s.Co, s.Co, static_cast<T*>(gwp->untyped_data()),
                    static_cast<T*>(gwn->untyped_data()), static_cast<T*>(gb->untyped_data()));
  return ffi::Error::Success();
}

// Calls fn(T{}) with T the float type of t (float32 or float64, as SameFloat established); an exception of the
// kernel (memory) becomes an error of the call instead of ending the process.
template <typename Fn>
ffi::Error ByFloat(ffi::DataType t, Fn fn) {
  try {
    if (t == ffi::DataType::F32)
      fn(float{});
    else
      fn(double{});
  } catch (const std::exception& e) {
    return ffi::Error::Internal(std::string("native mesh kernel: ") + e.what());
  }
  return ffi::Error::Success();
}

bool SameFloat(const std::vector<ffi::DataType>& types, ffi::DataType* t) {
  *t = *types.begin();
  for (auto u : types)
    if (u != *t) return false;
  return *t == ffi::DataType::F32 || *t == ffi::DataType::F64;
}

ffi::Error ForwardDispatch(ffi::ThreadPool pool, ffi::AnyBuffer x, ffi::AnyBuffer nbr, ffi::AnyBuffer count, ffi::AnyBuffer inv,
                           ffi::AnyBuffer wp, ffi::AnyBuffer wn, ffi::AnyBuffer b, ffi::Result<ffi::AnyBuffer> y) {
  PoolScope scope(&pool);
  ffi::DataType t;
  if (!SameFloat({x.element_type(), inv.element_type(), wp.element_type(), wn.element_type(), b.element_type(),
                  y->element_type()}, &t))
    return ffi::Error::InvalidArgument("mesh_conv: float arrays must all be float32 or all float64");
  ffi::Error result = ffi::Error::Success();
  if (auto e = ByFloat(t, [&](auto zero) { result = Forward<decltype(zero)>(x, nbr, count, inv, wp, wn, b, y); });
      e.failure())
    return e;
  return result;
}

ffi::Error BackwardDispatch(ffi::ThreadPool pool, ffi::AnyBuffer x, ffi::AnyBuffer gy, ffi::AnyBuffer nbr, ffi::AnyBuffer count,
                            ffi::AnyBuffer inv, ffi::AnyBuffer wp, ffi::AnyBuffer wn,
                            ffi::Result<ffi::AnyBuffer> gx, ffi::Result<ffi::AnyBuffer> gwp,
                            ffi::Result<ffi::AnyBuffer> gwn, ffi::Result<ffi::AnyBuffer> gb) {
  PoolScope scope(&pool);
  ffi::DataType t;
  if (!SameFloat({x.element_type(), gy.element_type(), inv.element_type(), wp.element_type(), wn.element_type(),
                  gx->element_type(), gwp->element_type(), gwn->element_type(), gb->element_type()}, &t))
    return ffi::Error::InvalidArgument("mesh_conv: float arrays must all be float32 or all float64");
  ffi::Error result = ffi::Error::Success();
  if (auto e = ByFloat(t, [&](auto zero) {
        result = Backward<decltype(zero)>(x, gy, nbr, count, inv, wp, wn, gx, gwp, gwn, gb);
      });
      e.failure())
    return e;
  return result;
}

// ---------------------------------------------------------------------------------------------------------
// The two halves of seed 000's autoencoder block (jaxdeform/nn/graph_conv.py), each fused into one call:
//
//   encoder  z[g,p]  = C[g] flatten(tanh(conv_enc(x[g,p])))             (no activation on z)
//   decoder  xh[g,p] = tanh(conv_dec(tanh(reshape(z[g,p] C[g]))))
//
// x, xh (..., P, V, 9); z (..., P, Kz); C (..., Kz, 9V); conv weights (..., 9, 9) and biases (..., 9). The
// leading (batch) dimensions of the inputs broadcast against those of the outputs (AeGeometry). The gradients
// come back per group of their output buffer (summed where it has one group). Each forward also returns its
// hidden layer (encoder tanh(conv(x)), decoder tanh(z C)) for its adjoint.
// Why: with one call per convolution, XLA still ran the tanh layers, the fully connected products with C and
// their adjoints as separate passes over (G, P, V, 9) arrays (15 MB each on the horse split). Fused, each
// block's layers run over tiles of 64 vertices that stay in cache. The convolutions' arithmetic runs on groups
// of kL vertices held channel by channel (Soa9: one kL-lane vector per channel; kL = 16 floats where the CPU
// has AVX-512, else 8), so a 9x9 channel mix is 81 full-width multiply-adds per group, where the row layout of
// the convolution kernels above spends 18 vector and 18 scalar ones per vertex; the one-ring gathers stay on
// rows. On a 2-core Intel Xeon with AVX-512, 16 lanes instead of 8 took the horse training step from 70.7 to
// 60.4 ms (medians of 8 alternated runs of 150 steps each). The products with C mix no channels, so they run on
// the rows as stored (Flat: kL consecutive entries at a time), with no transposes: 56.8 -> 51.6 ms on the same
// machine (14 alternated runs of 100 steps each). tanh: float32, Eigen's 13/6 rational interpolant (a few ulp);
// float64, std::tanh. Work is split over vertex ranges, so the rows of dC a chunk writes are its own; the
// reductions over vertices (z, dz, weight gradients) are summed per chunk (Plan), then in chunk order.

constexpr int64_t kVertexTile = 64;  // a multiple of 16

// Vertices per group (lanes of one vector): 16 floats where the CPU has AVX-512 (one 512-bit register per
// channel), else 8 (an AVX register of floats); 8 doubles.
template <typename T>
constexpr int64_t kL =
#if defined(__AVX512F__) && defined(__AVX512DQ__)  // DQ: _mm512_insertf32x8 / extractf32x8 below
    std::is_same_v<T, float> ? 16 : 8;
#else
    8;
#endif
template <typename T>
struct Soa9 {  // kL vertices x 9 channels, channel-major
  static constexpr int L = static_cast<int>(kL<T>);
  typedef T V __attribute__((vector_size(L * sizeof(T))));
  V c[9];
  static Soa9 Zero() {
    Soa9 r;
    for (auto& v : r.c) v = V{};
    return r;
  }
  // n <= L rows of 9 channels at src (contiguous); the missing rows read as zero
  static Soa9 FromRows(const T* src, int n) {
#if defined(__AVX2__)
    if constexpr (std::is_same_v<T, float>) {
      if (n == L) return FromRowsFull(src);
    }
#endif
    alignas(64) T buf[9][L];
    if (n == L) {
      for (int t = 0; t < L; ++t)
        for (int ch = 0; ch < 9; ++ch) buf[ch][t] = src[t * 9 + ch];
    } else {
      for (int t = 0; t < L; ++t)
        for (int ch = 0; ch < 9; ++ch) buf[ch][t] = t < n ? src[t * 9 + ch] : T(0);
    }
    Soa9 r;
    for (int ch = 0; ch < 9; ++ch) std::memcpy(&r.c[ch], buf[ch], sizeof(V));
    return r;
  }
  void ToRows(T* dst, int n) const {
#if defined(__AVX2__)
    if constexpr (std::is_same_v<T, float>) {
      if (n == L) return ToRowsFull(dst);
    }
#endif
    alignas(64) T buf[9][L];
    for (int ch = 0; ch < 9; ++ch) std::memcpy(buf[ch], &c[ch], sizeof(V));
    for (int t = 0; t < n; ++t)
      for (int ch = 0; ch < 9; ++ch) dst[t * 9 + ch] = buf[ch][t];
  }

#if defined(__AVX2__)
  // float, whole groups: channels 0-7 of each 8 rows by an 8x8 register transpose of the rows' first 8 entries
  // (unaligned loads at a stride of 9), channel 8 by one gather. The generic loops above go through a stack
  // buffer with 9 x L scalar stores, and vector loads that the store buffer cannot forward: on the horse training
  // split the two directions took 78 ns per group of 8 rows on a 2-core EPYC, these 19 ns (then with the
  // transposes of C and dC that the products with C now avoid, see Flat).
  static void Transpose8(__m256* r) {
    const __m256 t0 = _mm256_unpacklo_ps(r[0], r[1]), t1 = _mm256_unpackhi_ps(r[0], r[1]);
    const __m256 t2 = _mm256_unpacklo_ps(r[2], r[3]), t3 = _mm256_unpackhi_ps(r[2], r[3]);
    const __m256 t4 = _mm256_unpacklo_ps(r[4], r[5]), t5 = _mm256_unpackhi_ps(r[4], r[5]);
    const __m256 t6 = _mm256_unpacklo_ps(r[6], r[7]), t7 = _mm256_unpackhi_ps(r[6], r[7]);
    const __m256 u0 = _mm256_shuffle_ps(t0, t2, 0x44), u1 = _mm256_shuffle_ps(t0, t2, 0xEE);
    const __m256 u2 = _mm256_shuffle_ps(t1, t3, 0x44), u3 = _mm256_shuffle_ps(t1, t3, 0xEE);
    const __m256 u4 = _mm256_shuffle_ps(t4, t6, 0x44), u5 = _mm256_shuffle_ps(t4, t6, 0xEE);
    const __m256 u6 = _mm256_shuffle_ps(t5, t7, 0x44), u7 = _mm256_shuffle_ps(t5, t7, 0xEE);
    r[0] = _mm256_permute2f128_ps(u0, u4, 0x20);
    r[1] = _mm256_permute2f128_ps(u1, u5, 0x20);
    r[2] = _mm256_permute2f128_ps(u2, u6, 0x20);
    r[3] = _mm256_permute2f128_ps(u3, u7, 0x20);
    r[4] = _mm256_permute2f128_ps(u0, u4, 0x31);
    r[5] = _mm256_permute2f128_ps(u1, u5, 0x31);
    r[6] = _mm256_permute2f128_ps(u2, u6, 0x31);
    r[7] = _mm256_permute2f128_ps(u3, u7, 0x31);
  }
  // channels 0-7 of 8 rows at src, channel-major
  static void Load8(const T* src, __m256* a) {
    for (int t = 0; t < 8; ++t) a[t] = _mm256_loadu_ps(src + 9 * t);
    Transpose8(a);
  }
  // channels 0-7 (a, channel-major; transposed in place) and channel 8 (last) of 8 rows to dst
  static void Store8(__m256* a, const T* last, T* dst) {
    Transpose8(a);
    for (int t = 0; t < 8; ++t) {  // row t's 8-wide store ends where row t + 1 begins: rows in order
      _mm256_storeu_ps(dst + 9 * t, a[t]);
      dst[9 * t + 8] = last[t];
    }
  }
  static Soa9 FromRowsFull(const T* src) {
    Soa9 r;
    if constexpr (L == 8) {
      __m256 a[8];
      Load8(src, a);
      for (int ch = 0; ch < 8; ++ch) r.c[ch] = reinterpret_cast<const V&>(a[ch]);
      const __m256 last = _mm256_i32gather_ps(src + 8, _mm256_setr_epi32(0, 9, 18, 27, 36, 45, 54, 63), 4);
      r.c[8] = reinterpret_cast<const V&>(last);
    } else {
#if defined(__AVX512F__) && defined(__AVX512DQ__)
      __m256 lo[8], hi[8];
      Load8(src, lo);
      Load8(src + 72, hi);
      for (int ch = 0; ch < 8; ++ch) {
        const __m512 v = _mm512_insertf32x8(_mm512_castps256_ps512(lo[ch]), hi[ch], 1);
        r.c[ch] = reinterpret_cast<const V&>(v);
      }
      const __m512i idx = _mm512_setr_epi32(0, 9, 18, 27, 36, 45, 54, 63, 72, 81, 90, 99, 108, 117, 126, 135);
      const __m512 last = _mm512_i32gather_ps(idx, src + 8, 4);
      r.c[8] = reinterpret_cast<const V&>(last);
#endif
    }
    return r;
  }
  void ToRowsFull(T* dst) const {
    alignas(64) T last[L];
    std::memcpy(last, &c[8], sizeof(V));
    if constexpr (L == 8) {
      __m256 a[8];
      for (int ch = 0; ch < 8; ++ch) a[ch] = reinterpret_cast<const __m256&>(c[ch]);
      Store8(a, last, dst);
    } else {
#if defined(__AVX512F__) && defined(__AVX512DQ__)
      __m256 lo[8], hi[8];
      for (int ch = 0; ch < 8; ++ch) {
        const __m512 v = reinterpret_cast<const __m512&>(c[ch]);
        lo[ch] = _mm512_castps512_ps256(v);
        hi[ch] = _mm512_extractf32x8_ps(v, 1);
      }
      Store8(lo, last, dst);
      Store8(hi, last + 8, dst + 72);
#endif
    }
  }
#endif
};

template <typename T>
typename Soa9<T>::V TanhV(typename Soa9<T>::V x) {
  typedef typename Soa9<T>::V V;
  if constexpr (std::is_same_v<T, float>) {
    const V hi = V{} + 7.90531110763549805f;  // tanh rounds to +-1 in float32 beyond
    x = x < hi ? x : hi;
    x = x > -hi ? x : -hi;
    const V x2 = x * x;
    V p = x2 * -2.76076847742355e-16f + 2.00018790482477e-13f;
    p = x2 * p + -8.60467152213735e-11f;
    p = x2 * p + 5.12229709037114e-08f;
    p = x2 * p + 1.48572235717979e-05f;
    p = x2 * p + 6.37261928875436e-04f;
    p = x2 * p + 4.89352455891786e-03f;
    V q = x2 * 1.19825839466702e-06f + 1.18534705686654e-04f;
    q = x2 * q + 2.26843463243900e-03f;
    q = x2 * q + 4.89352518554385e-03f;
    return x * p / q;
  } else {
    for (int t = 0; t < Soa9<T>::L; ++t) x[t] = std::tanh(x[t]);
    return x;
  }
}

template <typename T>
void TanhSoa(Soa9<T>& a) {
  for (auto& v : a.c) v = TanhV<T>(v);
}

template <typename T>
T HSum(typename Soa9<T>::V v) {
  T s = 0;
  for (int t = 0; t < Soa9<T>::L; ++t) s += v[t];
  return s;
}

// o[e] += sum_f a[f] w[f * 9 + e]
template <typename T>
void MixAdd(Soa9<T>& o, const Soa9<T>& a, const T* __restrict__ w) {
  for (int e = 0; e < 9; ++e) {
    typename Soa9<T>::V acc = o.c[e];
    for (int f = 0; f < 9; ++f) acc += a.c[f] * w[f * 9 + e];
    o.c[e] = acc;
  }
}

// The conv weights of one group: W_point, W_neighbor as given (forward) or transposed (adjoint), and the bias.
template <typename T>
struct ConvW {
  T p[81], n[81], b[9];
  void Load(const T* wp, const T* wn, const T* bias, int64_t g, bool transpose) {
    for (int c = 0; c < 9; ++c)
      for (int d = 0; d < 9; ++d) {
        p[c * 9 + d] = transpose ? wp[g * 81 + d * 9 + c] : wp[g * 81 + c * 9 + d];
        n[c * 9 + d] = transpose ? wn[g * 81 + d * 9 + c] : wn[g * 81 + c * 9 + d];
      }
    for (int d = 0; d < 9; ++d) b[d] = bias != nullptr ? bias[g * 9 + d] : T(0);
  }
  Soa9<T> Bias() const {
    Soa9<T> r;
    for (int d = 0; d < 9; ++d) r.c[d] = typename Soa9<T>::V{} + b[d];
    return r;
  }
};

// G: the groups of the outputs' batch shape. For each output group g, the group each input reads: numpy
// broadcasting of the leading (batch) dimensions, so under nested jax.vmap an input that one of the maps does
// not batch (a shared C, the primal arguments of a vmapped adjoint) is read in place, never copied.
struct AeGeometry {
  int64_t G = 1, P = 1, V = 0, K = 0, Kz = 0;
  std::vector<int64_t> in, aux, cot, c, w;  // x or z | h or S | dz or the decoder's dpre | C | W_point, W_neighbor, b
  std::vector<int64_t> tgt;                  // the decoder's target (DecoderForward with the error)
  std::vector<int64_t> am;                   // per-vertex weights of the masked input (..., V), see Masked
};

// A masked input: the block of output group g reads rows am[g, i] x[i] (x broadcast over the blocks, one row
// weight per vertex and block) instead of a materialized array of them: seed 000's children, diag(AM_k) X_res.
template <typename T>
struct Masked {
  const T* am = nullptr;  // (..., V) by AeGeometry::am, or null: the input is read as it is
  const T* Of(const AeGeometry& s, int64_t g) const { return am == nullptr ? nullptr : am + s.am[g] * s.V; }
};

// Vertex ranges of whole tiles (RunPlan(plan, V, fn) runs fn(chunk, v0, v1) over them)
Plan PlanVertices(int64_t V, int64_t work_per_vertex) { return MakePlan(V, kVertexTile, work_per_vertex); }

// The ring means (or adjoint sums) of the vertices [i0, i0 + nt) in P planes at base + p * pstride, as rows into
// buf + p * kVertexTile * 9, in runs of up to 4 planes (RingSums: each ring's indices read once per run, 4
// independent chains of additions in registers). On the horse rings in runs of 5 planes (the training split's
// shapes), one plane at a time took 11.7-12.3 ns per vertex and plane on a 2-core EPYC, this way 8.4 ns.
// kWeighted: the sums weighted by weights[n_k] (RingSums' kAdjoint), else plain; kScaled: times scale (the
// vertex's 1 / D_i), else not. Ring mean: plain, scaled. Its adjoint: weighted by inv, not scaled. Ring mean of
// rows times a per-vertex weight (the masked inputs of EncoderForward): weighted by it, scaled.
template <typename T, bool kWeighted, bool kScaled, int kRun>
void RingRun(const T* base, int64_t pstride, const int32_t* ring, int32_t n, const T* weights, T scale, T* out) {
  Row9<T> r[kRun];
  RingSums<T, kWeighted, kRun>(base, pstride, ring, n, weights, r);
  for (int q = 0; q < kRun; ++q) {
    if constexpr (kScaled) r[q].Scale(scale);
    r[q].Store(out + q * kVertexTile * 9);
  }
}

template <typename T, bool kWeighted, bool kScaled>
void TileRingsPlanesT(const T* base, int64_t P, int64_t pstride, const int32_t* nbr, const int32_t* count,
                      const T* weights, const T* inv, int64_t K, int64_t i0, int64_t nt, T* buf) {
  for (int64_t t = 0; t < nt; ++t) {
    const int64_t i = i0 + t;
    const int32_t* ring = nbr + i * K;
    const int32_t n = count[i];
    const T scale = inv[i];
    int64_t p = 0;
    for (; p + 4 <= P; p += 4)
      RingRun<T, kWeighted, kScaled, 4>(base + p * pstride, pstride, ring, n, weights, scale,
                                        buf + (p * kVertexTile + t) * 9);
    T* out = buf + (p * kVertexTile + t) * 9;
    switch (P - p) {
      case 3: RingRun<T, kWeighted, kScaled, 3>(base + p * pstride, pstride, ring, n, weights, scale, out); break;
      case 2: RingRun<T, kWeighted, kScaled, 2>(base + p * pstride, pstride, ring, n, weights, scale, out); break;
      case 1: RingRun<T, kWeighted, kScaled, 1>(base + p * pstride, pstride, ring, n, weights, scale, out); break;
      default: break;
    }
  }
}

template <typename T>
void TileRingsPlanes(const T* base, int64_t P, int64_t pstride, const int32_t* nbr, const int32_t* count,
                     const T* inv, int64_t K, int64_t i0, int64_t nt, bool adjoint, T* buf) {
  if (adjoint) TileRingsPlanesT<T, true, false>(base, P, pstride, nbr, count, inv, inv, K, i0, nt, buf);
  else TileRingsPlanesT<T, false, true>(base, P, pstride, nbr, count, nullptr, inv, K, i0, nt, buf);
}

// Ring means of rows times a per-vertex weight w: inv[i] sum_k w[n_ik] a[n_ik]
template <typename T>
void TileWeightedRingMeans(const T* base, int64_t P, int64_t pstride, const int32_t* nbr, const int32_t* count,
                           const T* w, const T* inv, int64_t K, int64_t i0, int64_t nt, T* buf) {
  TileRingsPlanesT<T, true, true>(base, P, pstride, nbr, count, w, inv, K, i0, nt, buf);
}

// The products with C (z C, C^T h, the outer products of dC) mix no channels: they run on the rows of 9 as
// stored, kL<T> consecutive entries of a (..., V, 9) array at a time whatever their channels ("flat"), with no
// transposes. (Through Soa9 groups they took a transpose of each C row group per tile, and another for each
// dC row group written back: 5.5% of the horse training step's CPU time in FlushTileC alone.)
template <typename T>
using Flat = typename Soa9<T>::V;

// n entries at src; with n < kL<T> the rest read as zero
template <typename T>
Flat<T> LoadFlat(const T* src, int64_t n) {
  Flat<T> v;
  if (n >= kL<T>) {
    std::memcpy(&v, src, sizeof(v));
  } else {
    v = Flat<T>{};
    std::memcpy(&v, src, static_cast<size_t>(n) * sizeof(T));
  }
  return v;
}

// the first min(n, kL<T>) entries of v to dst
template <typename T>
void StoreFlat(T* dst, const Flat<T>& v, int64_t n) {
  if (n >= kL<T>) std::memcpy(dst, &v, sizeof(v));
  else std::memcpy(dst, &v, static_cast<size_t>(n) * sizeof(T));
}

// Writes (first) or adds v into the first min(n, kL<T>) entries at dst
template <typename T>
void WriteOrAddFlat(T* dst, const Flat<T>& v, int64_t n, bool first) {
  StoreFlat(dst, first ? v : LoadFlat(dst, n) + v, n);
}

// a[row t] *= w[t] for the n rows of a group (w: n entries; lanes past n are zero in a)
template <typename T>
void ScaleRows(Soa9<T>& a, const T* w, int n) {
  // one vector load for whole groups (a loop over the n weights compiled to a string move: 4-8% of each
  // caller's samples)
  const Flat<T> s = LoadFlat(w, n);
  for (auto& v : a.c) v *= s;
}

// Per chunk weight-gradient partial sums: gWp (81) | gWn (81) | gb (9) per output group.
constexpr int64_t kWeightStride = 2 * 81 + 9;  // ReduceWeightGrads' stride for 9 channels

// kL-lane accumulators of a^T d, a^T sg and d (gWp, gWn, gb of one group; sg: the adjoint ring sums of d, see
// ConvAdjointRows), summed over lanes at the end
template <typename T>
struct WeightGrads {
  typename Soa9<T>::V acc[kWeightStride];
  void Zero() {
    for (auto& v : acc) v = typename Soa9<T>::V{};
  }
  void Add(const Soa9<T>& a, const Soa9<T>& sg, const Soa9<T>& d) {
    for (int c = 0; c < 9; ++c)
      for (int e = 0; e < 9; ++e) {
        acc[c * 9 + e] += a.c[c] * d.c[e];
        acc[81 + c * 9 + e] += a.c[c] * sg.c[e];
      }
    for (int e = 0; e < 9; ++e) acc[162 + e] += d.c[e];
  }
  void FlushInto(T* out) const {
    for (int64_t e = 0; e < kWeightStride; ++e) out[e] += HSum<T>(acc[e]);
  }
};

template <typename T>
std::unique_ptr<T[]> Scratch(int64_t n) {
  return std::unique_ptr<T[]>(new T[static_cast<size_t>(std::max<int64_t>(n, 1))]);
}

// sum_e a[e] b[e] over n entries, in two independent chains of vector additions in registers (with one
// accumulator per latent entry in memory, the additions' latency bound the products with C)
template <typename T>
T DotFlat(const T* a, const T* b, int64_t n) {
  Flat<T> u0{}, u1{};
  int64_t e = 0;
  for (; e + 2 * kL<T> <= n; e += 2 * kL<T>) {
    u0 += LoadFlat(a + e, kL<T>) * LoadFlat(b + e, kL<T>);
    u1 += LoadFlat(a + e + kL<T>, kL<T>) * LoadFlat(b + e + kL<T>, kL<T>);
  }
  for (; e < n; e += kL<T>) u0 += LoadFlat(a + e, n - e) * LoadFlat(b + e, n - e);
  return HSum<T>(u0 + u1);
}

// Flat entries of one tile (kVertexTile rows of 9)
template <typename T>
constexpr int64_t kTileFlat = kVertexTile * 9 / kL<T>;
static_assert(kVertexTile * 9 % kL<float> == 0 && kVertexTile * 9 % kL<double> == 0, "tiles of whole vectors");

// ---- encoder ----

template <typename T>
void EncoderForward(const AeGeometry& s, const T* x, Masked<T> mask, const int32_t* nbr, const int32_t* count,
                    const T* inv, const T* wp, const T* wn, const T* b, const T* c, T* z, T* hidden) {
  const int64_t Kz = s.Kz, V = s.V, P = s.P;  // hidden: the output h, also read back for z (in cache)
  const Plan plan = PlanVertices(V, s.G * P * (s.K + 10 + Kz) * 9);
  std::vector<T> part(static_cast<size_t>(plan.chunks * s.G * P * Kz), T(0));
  RunPlan(plan, V, [&](int64_t t, int64_t v0, int64_t v1) {
    T* zp = part.data() + t * s.G * P * Kz;
    std::vector<T> rms(static_cast<size_t>(P * kVertexTile * 9));
    ConvW<T> w;
    for (int64_t g = 0; g < s.G; ++g) {
      w.Load(wp, wn, b, s.w[g], false);
      const T* cg = c + s.c[g] * Kz * V * 9;
      const T* amg = mask.Of(s, g);
      for (int64_t i0 = v0; i0 < v1; i0 += kVertexTile) {
        const int64_t nt = std::min(v1, i0 + kVertexTile) - i0;
        if (amg != nullptr)
          TileWeightedRingMeans(x + s.in[g] * P * V * 9, P, V * 9, nbr, count, amg, inv, s.K, i0, nt, rms.data());
        else
          TileRingsPlanes(x + s.in[g] * P * V * 9, P, V * 9, nbr, count, inv, s.K, i0, nt, false, rms.data());
        for (int64_t p = 0; p < P; ++p) {
          const T* plane = x + (s.in[g] * P + p) * V * 9;
          const T* rm = rms.data() + p * kVertexTile * 9;
          T* hrows = hidden + ((g * P + p) * V + i0) * 9;
          for (int64_t j = 0; j * kL<T> < nt; ++j) {
            const int n = static_cast<int>(std::min<int64_t>(kL<T>, nt - kL<T> * j));
            Soa9<T> h = w.Bias();
            Soa9<T> xr = Soa9<T>::FromRows(plane + (i0 + kL<T> * j) * 9, n);
            if (amg != nullptr) ScaleRows(xr, amg + i0 + kL<T> * j, n);
            MixAdd(h, xr, w.p);
            MixAdd(h, Soa9<T>::FromRows(rm + kL<T> * j * 9, n), w.n);
            TanhSoa(h);
            h.ToRows(hrows + kL<T> * j * 9, n);
          }
          // z[k] += sum over the tile's entries of C[k] h, flat (the rows just written, still in cache)
          for (int64_t k = 0; k < Kz; ++k) zp[(g * P + p) * Kz + k] += DotFlat(cg + (k * V + i0) * 9, hrows, nt * 9);
        }
      }
    }
  });
  SumChunkParts(part, s.G * P * Kz, z);
}

// With a masked input (mask.am: the rows a are am[g] x, see Masked), out takes the cotangent of x instead: the
// sum over the blocks g reading each x of am[g] (conv^T(d[g]) + the cotangent of the block's target), the target
// being its input too (the decoder's error err[g,p] = ||x_hat[g,p] - am[g] x||^2, cotangent derr): -2 derr[g,p]
// (x_hat[g,p] - am[g] x); xh and derr null: no target term.
// Without a mask, out[g,p] = conv^T(d[g,p]): the input cotangent of a conv with input rows a and pre-activation cotangent d;
// its weight gradients go to acc (per chunk and output group; sized here): gWp = sum_i a_i^T d_i, gb = sum_i d_i and
// gWn = sum_i ring_mean(a)_i^T d_i = sum_j a_j^T sg_j with sg_j = sum_{i in N(j)} d_i / D_i (symmetric rings),
// the adjoint ring sums the input cotangent needs anyway.
template <typename T>
void ConvAdjointRows(const AeGeometry& s, const T* d, const T* a, Masked<T> mask, const T* xh, const T* derr,
                     const int32_t* nbr, const int32_t* count, const T* inv, const T* wp, const T* wn, T* out,
                     std::vector<T>& acc, int64_t weight_groups) {
  const Plan plan = PlanVertices(s.V, s.G * s.P * (s.K + 40) * 9);
  acc.assign(static_cast<size_t>(plan.chunks * weight_groups * kWeightStride), T(0));
  const int64_t in_groups = s.in.empty() ? 0 : *std::max_element(s.in.begin(), s.in.end()) + 1;
  RunPlan(plan, s.V, [&](int64_t t, int64_t v0, int64_t v1) {
    ConvW<T> w;
    std::vector<T> sgs(static_cast<size_t>(s.P * kVertexTile * 9));
    std::vector<char> written(static_cast<size_t>(in_groups), 0);  // masked: the x groups this chunk has begun
    auto wg = std::make_unique<WeightGrads<T>>();
    for (int64_t g = 0; g < s.G; ++g) {
      w.Load(wp, wn, nullptr, s.w[g], true);
      wg->Zero();
      const T* amg = mask.Of(s, g);
      const bool first = amg == nullptr || !written[static_cast<size_t>(s.in[g])];
      for (int64_t i0 = v0; i0 < v1; i0 += kVertexTile) {
        const int64_t nt = std::min(v1, i0 + kVertexTile) - i0;
        TileRingsPlanes(d + g * s.P * s.V * 9, s.P, s.V * 9, nbr, count, inv, s.K, i0, nt, true, sgs.data());
        for (int64_t p = 0; p < s.P; ++p) {
          const T* dp = d + (g * s.P + p) * s.V * 9;
          const T* ap = a + (s.in[g] * s.P + p) * s.V * 9;
          T* o = out + ((amg != nullptr ? s.in[g] : g) * s.P + p) * s.V * 9;
          const T* sg = sgs.data() + p * kVertexTile * 9;
          const T* xhp = xh != nullptr ? xh + (g * s.P + p) * s.V * 9 : nullptr;
          const T m2d = derr != nullptr ? T(-2) * derr[g * s.P + p] : T(0);
          for (int64_t j = 0; j * kL<T> < nt; ++j) {
            const int n = static_cast<int>(std::min<int64_t>(kL<T>, nt - kL<T> * j));
            const Soa9<T> ds = Soa9<T>::FromRows(dp + (i0 + kL<T> * j) * 9, n);
            const Soa9<T> ss = Soa9<T>::FromRows(sg + kL<T> * j * 9, n);
            Soa9<T> ar = Soa9<T>::FromRows(ap + (i0 + kL<T> * j) * 9, n);
            if (amg != nullptr) ScaleRows(ar, amg + i0 + kL<T> * j, n);
            Soa9<T> r = Soa9<T>::Zero();
            MixAdd(r, ds, w.p);
            MixAdd(r, ss, w.n);
            if (amg != nullptr) {
              if (xhp != nullptr) {
                const Soa9<T> xr = Soa9<T>::FromRows(xhp + (i0 + kL<T> * j) * 9, n);
                for (int ch = 0; ch < 9; ++ch) r.c[ch] += m2d * (xr.c[ch] - ar.c[ch]);
              }
              ScaleRows(r, amg + i0 + kL<T> * j, n);
              if (!first) {
                const Soa9<T> prev = Soa9<T>::FromRows(o + (i0 + kL<T> * j) * 9, n);
                for (int ch = 0; ch < 9; ++ch) r.c[ch] += prev.c[ch];
              }
            }
            r.ToRows(o + (i0 + kL<T> * j) * 9, n);
            wg->Add(ar, ss, ds);
          }
        }
      }
      wg->FlushInto(acc.data() + (t * weight_groups + (weight_groups == 1 ? 0 : g)) * kWeightStride);
      if (amg != nullptr) written[static_cast<size_t>(s.in[g])] = 1;
    }
  });
}

// Given the forward's hidden layer h = tanh(conv(x)) (its second output)
template <typename T>
void EncoderBackward(const AeGeometry& s, int64_t weight_groups, int64_t c_groups, const T* x, Masked<T> mask,
                     const T* xh, const T* derr, const T* hidden, const T* dz, const int32_t* nbr, const int32_t* count, const T* inv, const T* wp,
                     const T* wn, const T* c, T* dx, T* gwp, T* gwn, T* gb, T* dc) {
  const int64_t Kz = s.Kz, V = s.V, P = s.P;
  auto dpre = Scratch<T>(s.G * P * V * 9);  // cotangent of the conv's pre-activation
  // flat (see Flat): dh = sum_k dz[k] C[k], dpre = dh (1 - h^2), dC[k] (+)= sum_p dz[p, k] h[p]
  RunPlan(PlanVertices(V, s.G * P * (10 + 2 * Kz) * 9), V, [&](int64_t, int64_t v0, int64_t v1) {
    typedef Flat<T> Vec;
    std::vector<Vec> ck(static_cast<size_t>(Kz)), dck(static_cast<size_t>(Kz));
    const int64_t n9 = V * 9, f1 = v1 * 9;
    for (int64_t g = 0; g < s.G; ++g) {
      const T* cg = c + s.c[g] * Kz * n9;
      T* dcg = dc + (c_groups == 1 ? 0 : g) * Kz * n9;
      const bool first = c_groups != 1 || g == 0;
      for (int64_t f = v0 * 9; f < f1; f += kL<T>) {
        const int64_t n = f1 - f;
        for (int64_t k = 0; k < Kz; ++k) {
          ck[k] = LoadFlat(cg + k * n9 + f, n);
          dck[k] = Vec{};
        }
        for (int64_t p = 0; p < P; ++p) {
          const Vec h = LoadFlat(hidden + (s.aux[g] * P + p) * n9 + f, n);
          const T* dzp = dz + (s.cot[g] * P + p) * Kz;
          Vec d{};  // cotangent of h, then of the pre-activation
          for (int64_t k = 0; k < Kz; ++k) {
            d += dzp[k] * ck[k];
            dck[k] += dzp[k] * h;
          }
          d -= d * h * h;
          StoreFlat(dpre.get() + (g * P + p) * n9 + f, d, n);
        }
        for (int64_t k = 0; k < Kz; ++k) {
          WriteOrAddFlat(dcg + k * n9 + f, dck[k], n, first);
        }
      }
    }
  });
  std::vector<T> acc;  // sized by ConvAdjointRows
  ConvAdjointRows(s, dpre.get(), x, mask, xh, derr, nbr, count, inv, wp, wn, dx, acc, weight_groups);
  ReduceWeightGrads(acc, weight_groups, int64_t{81}, int64_t{9}, gwp, gwn, gb);
}

// ---- decoder ----

// S[g,p,i] = tanh(sum_k z[g,p,k] C[g,k,i]) for vertices [v0, v1), flat (see Flat)
template <typename T>
void DecoderHidden(const AeGeometry& s, const T* z, const T* c, T* S, int64_t v0, int64_t v1) {
  typedef Flat<T> Vec;
  const int64_t Kz = s.Kz, P = s.P, n9 = s.V * 9, f1 = v1 * 9;
  std::vector<Vec> ck(static_cast<size_t>(Kz));
  for (int64_t g = 0; g < s.G; ++g) {
    const T* cg = c + s.c[g] * Kz * n9;
    for (int64_t f = v0 * 9; f < f1; f += kL<T>) {
      const int64_t n = f1 - f;
      for (int64_t k = 0; k < Kz; ++k) ck[k] = LoadFlat(cg + k * n9 + f, n);
      for (int64_t p = 0; p < P; ++p) {
        const T* zp = z + (s.in[g] * P + p) * Kz;
        Vec a{};
        for (int64_t k = 0; k < Kz; ++k) a += zp[k] * ck[k];
        StoreFlat(S + (g * P + p) * n9 + f, TanhV<T>(a), n);
      }
    }
  }
}

// With a target (same layout as x_hat, groups mapped by s.tgt; masked: am[g] target, see Masked), also
// err[g,p] = sum_i ||x_hat - target||^2 per plane, summed while x_hat is in registers: the reconstruction loss of the block, which XLA on CPU otherwise
// computes by writing the squared differences out in full before a tree reduction over them.
template <typename T>
void DecoderForward(const AeGeometry& s, const T* z, const int32_t* nbr, const int32_t* count, const T* inv,
                    const T* wp, const T* wn, const T* b, const T* c, const T* target, Masked<T> mask, T* xh,
                    T* S, T* err) {
  typedef typename Soa9<T>::V Vec;
  const int64_t V = s.V, P = s.P;
  RunPlan(PlanVertices(V, s.G * P * (s.Kz + 10) * 9), V, [&](int64_t, int64_t v0, int64_t v1) {
    DecoderHidden(s, z, c, S, v0, v1);
  });
  const Plan plan = PlanVertices(V, s.G * P * (s.K + 10) * 9);
  std::vector<T> part(static_cast<size_t>(target != nullptr ? plan.chunks * s.G * P : 0), T(0));
  RunPlan(plan, V, [&](int64_t chunk, int64_t v0, int64_t v1) {
    ConvW<T> w;
    std::vector<T> rms(static_cast<size_t>(P * kVertexTile * 9));
    for (int64_t g = 0; g < s.G; ++g) {
      w.Load(wp, wn, b, s.w[g], false);
      const T* amg = mask.Of(s, g);
      for (int64_t i0 = v0; i0 < v1; i0 += kVertexTile) {
        const int64_t nt = std::min(v1, i0 + kVertexTile) - i0;
        TileRingsPlanes(S + g * P * V * 9, P, V * 9, nbr, count, inv, s.K, i0, nt, false, rms.data());
        for (int64_t p = 0; p < P; ++p) {
          const T* plane = S + (g * P + p) * V * 9;
          T* out = xh + (g * P + p) * V * 9;
          const T* rm = rms.data() + p * kVertexTile * 9;
          Vec sq{};
          for (int64_t j = 0; j * kL<T> < nt; ++j) {
            const int n = static_cast<int>(std::min<int64_t>(kL<T>, nt - kL<T> * j));
            Soa9<T> h = w.Bias();
            MixAdd(h, Soa9<T>::FromRows(plane + (i0 + kL<T> * j) * 9, n), w.p);
            MixAdd(h, Soa9<T>::FromRows(rm + kL<T> * j * 9, n), w.n);
            TanhSoa(h);
            h.ToRows(out + (i0 + kL<T> * j) * 9, n);
            if (target != nullptr) {
              Soa9<T> t = Soa9<T>::FromRows(target + ((s.tgt[g] * P + p) * V + i0 + kL<T> * j) * 9, n);
              if (amg != nullptr) ScaleRows(t, amg + i0 + kL<T> * j, n);
              Vec e{};
              for (int ch = 0; ch < 9; ++ch) {
                const Vec d = h.c[ch] - t.c[ch];
                e += d * d;
              }
              for (int lane = n; lane < kL<T>; ++lane) e[lane] = T(0);  // rows past the end (x_hat there: tanh(b))
              sq += e;
            }
          }
          if (target != nullptr) part[(chunk * s.G + g) * P + p] += HSum<T>(sq);
        }
      }
    }
  });
  if (target != nullptr) SumChunkParts(part, s.G * P, err);
}

// Given the forward's hidden layer S = tanh(z C) (its second output) and the cotangent of the conv's
// pre-activation, dpre = dx_hat (1 - x_hat^2): the caller forms it (native.ae_decoder_backward), where XLA fuses it into the
// operation that makes dx_hat, instead of a pass of its own here over x_hat and dx_hat.
template <typename T>
void DecoderBackward(const AeGeometry& s, int64_t weight_groups, int64_t c_groups, const T* z, const T* S,
                     const T* dpre, const int32_t* nbr, const int32_t* count, const T* inv, const T* wp,
                     const T* wn, const T* c, T* dz, T* gwp, T* gwn, T* gb, T* dc) {
  typedef typename Soa9<T>::V Vec;
  const int64_t Kz = s.Kz, V = s.V, P = s.P;
  const Plan plan = PlanVertices(V, s.G * P * (s.K + 40 + 2 * Kz) * 9);
  std::vector<T> acc(static_cast<size_t>(plan.chunks * weight_groups * kWeightStride), T(0));
  std::vector<T> part(static_cast<size_t>(plan.chunks * s.G * P * Kz), T(0));
  RunPlan(plan, V, [&](int64_t t, int64_t v0, int64_t v1) {
    ConvW<T> w;
    std::vector<Vec> dcb(static_cast<size_t>(Kz * kTileFlat<T>));  // the tile's dC, flat
    std::vector<T> darow(static_cast<size_t>(kVertexTile * 9));     // one plane's cotangent of (z C), as rows
    T* da_rows = darow.data();
    std::vector<T> sgs(static_cast<size_t>(P * kVertexTile * 9));
    auto wg = std::make_unique<WeightGrads<T>>();
    T* zpart = part.data() + t * s.G * P * Kz;
    for (int64_t g = 0; g < s.G; ++g) {
      w.Load(wp, wn, nullptr, s.w[g], true);
      const T* cg = c + s.c[g] * Kz * V * 9;
      T* dcg = dc + (c_groups == 1 ? 0 : g) * Kz * V * 9;
      wg->Zero();
      for (int64_t i0 = v0; i0 < v1; i0 += kVertexTile) {
        const int64_t nt = std::min(v1, i0 + kVertexTile) - i0;
        const int64_t nf = nt * 9;  // the tile's flat entries
        const T* ct = cg + i0 * 9;
        for (auto& a : dcb) a = Vec{};
        TileRingsPlanes(dpre + s.cot[g] * P * V * 9, P, V * 9, nbr, count, inv, s.K, i0, nt, true, sgs.data());
        for (int64_t p = 0; p < P; ++p) {
          const T* sp = S + (s.aux[g] * P + p) * V * 9;
          const T* dp = dpre + (s.cot[g] * P + p) * V * 9;
          const T* zp = z + (s.in[g] * P + p) * Kz;
          const T* sg = sgs.data() + p * kVertexTile * 9;
          for (int64_t j = 0; j * kL<T> < nt; ++j) {
            const int n = static_cast<int>(std::min<int64_t>(kL<T>, nt - kL<T> * j));
            const Soa9<T> dd = Soa9<T>::FromRows(dp + (i0 + kL<T> * j) * 9, n);
            const Soa9<T> ss = Soa9<T>::FromRows(sp + (i0 + kL<T> * j) * 9, n);
            const Soa9<T> gs = Soa9<T>::FromRows(sg + kL<T> * j * 9, n);
            Soa9<T> da = Soa9<T>::Zero();  // cotangent of S, then of (z C)
            MixAdd(da, dd, w.p);
            MixAdd(da, gs, w.n);
            for (int ch = 0; ch < 9; ++ch) da.c[ch] -= da.c[ch] * ss.c[ch] * ss.c[ch];
            da.ToRows(da_rows + kL<T> * j * 9, n);
            wg->Add(ss, gs, dd);  // zero in the missing rows; gWn as in ConvAdjointRows
          }
          // dz[k] += sum C[k] da and dC[k] += z[k] da over the tile, flat (see Flat)
          for (int64_t k = 0; k < Kz; ++k) {
            zpart[(g * P + p) * Kz + k] += DotFlat(ct + k * V * 9, da_rows, nf);
            Vec* dk = dcb.data() + k * kTileFlat<T>;
            for (int64_t f = 0, q = 0; f < nf; f += kL<T>, ++q) dk[q] += zp[k] * LoadFlat(da_rows + f, nf - f);
          }
        }
        const bool first = c_groups != 1 || g == 0;
        for (int64_t k = 0; k < Kz; ++k)
          for (int64_t f = 0, q = 0; f < nf; f += kL<T>, ++q)
            WriteOrAddFlat(dcg + k * V * 9 + i0 * 9 + f, dcb[k * kTileFlat<T> + q], nf - f, first);
      }
      wg->FlushInto(acc.data() + (t * weight_groups + (weight_groups == 1 ? 0 : g)) * kWeightStride);
    }
  });
  ReduceWeightGrads(acc, weight_groups, int64_t{81}, int64_t{9}, gwp, gwn, gb);
  SumChunkParts(part, s.G * P * Kz, dz);
}

// ---- shapes and dispatch ----

int64_t Groups(ffi::AnyBuffer a, int64_t inner) {
  return inner == 0 ? 0 : static_cast<int64_t>(a.element_count()) / inner;
}

typedef std::vector<int64_t> Dims;

Dims DimsOf(ffi::AnyBuffer a) {
  auto d = a.dimensions();
  return Dims(d.begin(), d.end());
}

// The trailing `core` dimensions of a buffer, or an empty vector where it has fewer
Dims Core(const Dims& d, size_t core) { return d.size() < core ? Dims() : Dims(d.end() - core, d.end()); }

// map[g] = the group of an input with dimensions d (its last `core` ones per group) that output group g of
// the batch shape `batch` reads; false where the leading dimensions do not broadcast against `batch`.
bool BroadcastMap(const Dims& d, size_t core, const Dims& batch, std::vector<int64_t>* map) {
  if (d.size() < core || d.size() - core > batch.size()) return false;
  const size_t nb = d.size() - core, off = batch.size() - nb;
  Dims stride(batch.size(), 0);
  int64_t st = 1;
  for (size_t k = nb; k-- > 0;) {
    if (d[k] != batch[off + k] && d[k] != 1) return false;
    if (d[k] != 1) stride[off + k] = st;
    st *= d[k];
  }
  int64_t groups = 1;
  for (int64_t b : batch) groups *= b;
  map->assign(static_cast<size_t>(groups), 0);
  for (int64_t g = 0; g < groups; ++g) {
    int64_t rest = g, at = 0;
    for (size_t r = batch.size(); r-- > 0;) {
      at += (rest % batch[r]) * stride[r];
      rest /= batch[r];
    }
    (*map)[static_cast<size_t>(g)] = at;
  }
  return true;
}

ffi::Error RingsFor(const AeGeometry& s, ffi::AnyBuffer nbr, ffi::AnyBuffer count, ffi::AnyBuffer inv) {
  Geometry g;
  g.V = s.V;
  g.K = s.K;
  return CheckRings(g, nbr, count, inv);
}

// Shapes from an output `out` of (batch..., P, V, 9) (planes) or (batch..., P, Kz) (codes), C (..., Kz, 9V)
// and the rings (checked); the group maps of C and the conv weights.
ffi::Error MakeAeGeometry(const Dims& out, bool planes, ffi::AnyBuffer nbr, ffi::AnyBuffer count, ffi::AnyBuffer inv,
                          ffi::AnyBuffer wp, ffi::AnyBuffer wn, ffi::AnyBuffer b, ffi::AnyBuffer c, AeGeometry* s) {
  const Dims cd = DimsOf(c), nd = DimsOf(nbr);
  if (cd.size() < 2 || nd.size() < 2) return ffi::Error::InvalidArgument("ae_block: C and neighbors need rank >= 2");
  s->Kz = cd[cd.size() - 2];
  if (cd.back() % 9 != 0) return ffi::Error::InvalidArgument("ae_block: C's rows are not 9 per vertex");
  s->V = cd.back() / 9;
  s->K = nd.back();
  if (nd[nd.size() - 2] != s->V) return ffi::Error::InvalidArgument("ae_block: neighbors do not match C's vertices");
  const size_t core = planes ? 3 : 2;
  if (out.size() < core || (planes && (out.back() != 9 || out[out.size() - 2] != s->V)) ||
      (!planes && out.back() != s->Kz))
    return ffi::Error::InvalidArgument("ae_block: the output does not match C's latent size or vertices");
  s->P = out[out.size() - core];
  const Dims batch(out.begin(), out.end() - core);
  s->G = 1;
  for (int64_t e : batch) s->G *= e;
  std::vector<int64_t> wn_map, b_map;
  if (Core(DimsOf(wp), 2) != Dims{9, 9} || Core(DimsOf(wn), 2) != Dims{9, 9} || Core(DimsOf(b), 1) != Dims{9})
    return ffi::Error::InvalidArgument("ae_block: conv weights must be (..., 9, 9) with biases (..., 9)");
  if (!BroadcastMap(cd, 2, batch, &s->c) || !BroadcastMap(DimsOf(wp), 2, batch, &s->w) ||
      !BroadcastMap(DimsOf(wn), 2, batch, &wn_map) || !BroadcastMap(DimsOf(b), 1, batch, &b_map) ||
      wn_map != s->w || b_map != s->w)
    return ffi::Error::InvalidArgument("ae_block: batch dimensions of the arrays do not line up");
  return RingsFor(*s, nbr, count, inv);
}

// The dimensions of `out` with its last `core` ones replaced by `with`
Dims WithCore(const Dims& out, size_t core, std::initializer_list<int64_t> with) {
  Dims d(out.begin(), out.end() - static_cast<std::ptrdiff_t>(core));
  d.insert(d.end(), with);
  return d;
}

// The group map of an input of planes (..., P, V, 9) or codes (..., P, Kz) against the output batch shape
ffi::Error InputMap(ffi::AnyBuffer a, bool planes, const Dims& out, const AeGeometry& s, std::vector<int64_t>* map) {
  const size_t core = planes ? 3 : 2;
  const Dims want = planes ? Dims{s.P, s.V, 9} : Dims{s.P, s.Kz};
  const Dims d = DimsOf(a);
  if (Core(d, core) != want || !BroadcastMap(d, core, WithCore(out, core, {}), map))
    return ffi::Error::InvalidArgument("ae_block: an input's shape does not match the output's");
  return ffi::Error::Success();
}

// Gradient outputs: one group (summed) or one per output group
ffi::Error CheckOutGroups(const AeGeometry& s, int64_t groups) {
  if (groups != 1 && groups != s.G) return ffi::Error::InvalidArgument("ae_block: gradient batch dimensions do not line up");
  return ffi::Error::Success();
}

template <typename T>
const T* In(ffi::AnyBuffer a) { return static_cast<const T*>(a.untyped_data()); }
template <typename T>
T* Out(ffi::Result<ffi::AnyBuffer>& a) { return static_cast<T*>(a->untyped_data()); }
const int32_t* Ints(ffi::AnyBuffer a) { return static_cast<const int32_t*>(a.untyped_data()); }

// n >= 1 more buffer arguments (Args) or results (Rets) on a binding (bindings only move into a longer one)
template <int n, typename B>
auto Args(B&& bind) {
  if constexpr (n == 1)
    return std::move(bind).template Arg<ffi::AnyBuffer>();
  else
    return Args<n - 1>(std::move(bind).template Arg<ffi::AnyBuffer>());
}
template <int n, typename B>
auto Rets(B&& bind) {
  if constexpr (n == 1)
    return std::move(bind).template Ret<ffi::AnyBuffer>();
  else
    return Rets<n - 1>(std::move(bind).template Ret<ffi::AnyBuffer>());
}

// The arguments every block half takes after its own: neighbors, counts, inverse degrees, W_point, W_neighbor, b,
// C (..., Kz, 9V)
template <typename B>
auto BlockArgs(B&& bind) { return Args<7>(std::move(bind)); }

// The adjoints' results: the input cotangent (dx or dz), gW_point, gW_neighbor, gb, dC
template <typename B>
auto GradRets(B&& bind) { return Rets<5>(std::move(bind)); }

// The group counts of the adjoints' gradient outputs (gW_point, gW_neighbor, gb: wg; dC: cg), checked
ffi::Error GradOutputs(const AeGeometry& s, ffi::Result<ffi::AnyBuffer>& gwp, ffi::Result<ffi::AnyBuffer>& gwn,
                       ffi::Result<ffi::AnyBuffer>& gb, ffi::Result<ffi::AnyBuffer>& dc, int64_t* wg, int64_t* cg) {
  *wg = Groups(*gwp, 81);
  *cg = Groups(*dc, s.Kz * s.V * 9);
  if (auto e = CheckOutGroups(s, *wg); e.failure()) return e;
  if (auto e = CheckOutGroups(s, *cg); e.failure()) return e;
  if (Groups(*gwn, 81) != *wg || Groups(*gb, 9) != *wg)
    return ffi::Error::InvalidArgument("ae_block: gradient buffers have the wrong sizes");
  return ffi::Error::Success();
}

// The group map of a masked input's row weights (..., V) against the output batch shape
ffi::Error MaskMap(ffi::AnyBuffer am, const Dims& out, size_t core, AeGeometry* s) {
  const Dims d = DimsOf(am);
  if (Core(d, 1) != Dims{s->V} || !BroadcastMap(d, 1, WithCore(out, core, {}), &s->am))
    return ffi::Error::InvalidArgument("ae_block: the mask's shape does not match the output's");
  return ffi::Error::Success();
}

// The encoder forward, of x or (am not null) of the masked input am x
ffi::Error EncoderFwd(ffi::ThreadPool& pool, ffi::AnyBuffer x, const ffi::AnyBuffer* am, ffi::AnyBuffer nbr,
                      ffi::AnyBuffer count, ffi::AnyBuffer inv, ffi::AnyBuffer wp, ffi::AnyBuffer wn, ffi::AnyBuffer b,
                      ffi::AnyBuffer c, ffi::Result<ffi::AnyBuffer>& z, ffi::Result<ffi::AnyBuffer>& h) {
  PoolScope scope(&pool);
  AeGeometry s;
  const Dims out = DimsOf(*h);
  if (auto e = MakeAeGeometry(out, true, nbr, count, inv, wp, wn, b, c, &s); e.failure()) return e;
  if (auto e = InputMap(x, true, out, s, &s.in); e.failure()) return e;
  if (Groups(*z, s.P * s.Kz) != s.G) return ffi::Error::InvalidArgument("ae_block: z has the wrong size");
  std::vector<ffi::DataType> types = {x.element_type(), inv.element_type(), wp.element_type(), wn.element_type(),
                                      b.element_type(), c.element_type(), z->element_type(), h->element_type()};
  if (am != nullptr) {
    if (auto e = MaskMap(*am, out, 3, &s); e.failure()) return e;
    types.push_back(am->element_type());
  }
  ffi::DataType t;
  if (!SameFloat(types, &t))
    return ffi::Error::InvalidArgument("ae_block: float arrays must all be float32 or all float64");
  return ByFloat(t, [&](auto zero) {
    using T = decltype(zero);
    EncoderForward<T>(s, In<T>(x), Masked<T>{am != nullptr ? In<T>(*am) : nullptr}, Ints(nbr), Ints(count), In<T>(inv),
                      In<T>(wp), In<T>(wn), In<T>(b), In<T>(c), Out<T>(z), Out<T>(h));
  });
}

ffi::Error EncoderFwdDispatch(ffi::ThreadPool pool, ffi::AnyBuffer x, ffi::AnyBuffer nbr, ffi::AnyBuffer count,
                              ffi::AnyBuffer inv, ffi::AnyBuffer wp, ffi::AnyBuffer wn, ffi::AnyBuffer b,
                              ffi::AnyBuffer c, ffi::Result<ffi::AnyBuffer> z, ffi::Result<ffi::AnyBuffer> h) {
  return EncoderFwd(pool, x, nullptr, nbr, count, inv, wp, wn, b, c, z, h);
}

ffi::Error EncoderFwdMaskedDispatch(ffi::ThreadPool pool, ffi::AnyBuffer x, ffi::AnyBuffer am, ffi::AnyBuffer nbr,
                                    ffi::AnyBuffer count, ffi::AnyBuffer inv, ffi::AnyBuffer wp, ffi::AnyBuffer wn,
                                    ffi::AnyBuffer b, ffi::AnyBuffer c, ffi::Result<ffi::AnyBuffer> z,
                                    ffi::Result<ffi::AnyBuffer> h) {
  return EncoderFwd(pool, x, &am, nbr, count, inv, wp, wn, b, c, z, h);
}

// The encoder adjoint, of x or (am not null) of the masked input am x (EncoderFwd). Masked, the blocks' decoders
// had that input as their target too: given their x_hat and the cotangent of their errors (..., P), it returns the
// cotangent of x shaped like x, summed over the blocks reading it (ConvAdjointRows), and the blocks' planes are
// those of h.
ffi::Error EncoderBwd(ffi::ThreadPool& pool, ffi::AnyBuffer x, const ffi::AnyBuffer* am, ffi::AnyBuffer h,
                      ffi::AnyBuffer dz, const ffi::AnyBuffer* xh, const ffi::AnyBuffer* derr, ffi::AnyBuffer nbr,
                      ffi::AnyBuffer count, ffi::AnyBuffer inv, ffi::AnyBuffer wp, ffi::AnyBuffer wn, ffi::AnyBuffer b,
                      ffi::AnyBuffer c, ffi::Result<ffi::AnyBuffer>& dx, ffi::Result<ffi::AnyBuffer>& gwp,
                      ffi::Result<ffi::AnyBuffer>& gwn, ffi::Result<ffi::AnyBuffer>& gb,
                      ffi::Result<ffi::AnyBuffer>& dc) {
  PoolScope scope(&pool);
  AeGeometry s;
  const Dims out = am != nullptr ? DimsOf(h) : DimsOf(*dx);
  if (auto e = MakeAeGeometry(out, true, nbr, count, inv, wp, wn, b, c, &s); e.failure()) return e;
  if (auto e = InputMap(x, true, out, s, &s.in); e.failure()) return e;
  if (auto e = InputMap(h, true, out, s, &s.aux); e.failure()) return e;
  if (auto e = InputMap(dz, false, WithCore(out, 3, {s.P, s.Kz}), s, &s.cot); e.failure()) return e;
  int64_t wg, cg;
  if (auto e = GradOutputs(s, gwp, gwn, gb, dc, &wg, &cg); e.failure()) return e;
  std::vector<ffi::DataType> types = {x.element_type(), h.element_type(), dz.element_type(), inv.element_type(),
                                      wp.element_type(), wn.element_type(), b.element_type(), c.element_type(),
                                      dx->element_type(), gwp->element_type(), gwn->element_type(),
                                      gb->element_type(), dc->element_type()};
  if (am != nullptr) {
    if (auto e = MaskMap(*am, out, 3, &s); e.failure()) return e;
    std::vector<int64_t> xh_map;
    if (auto e = InputMap(*xh, true, out, s, &xh_map); e.failure()) return e;
    if (Groups(*xh, s.P * s.V * 9) != s.G || static_cast<int64_t>(derr->element_count()) != s.G * s.P)
      return ffi::Error::InvalidArgument("ae_block: x_hat and the error cotangent need one group per block");
    if (DimsOf(*dx) != DimsOf(x)) return ffi::Error::InvalidArgument("ae_block: dx must be shaped like x");
    types.insert(types.end(), {am->element_type(), xh->element_type(), derr->element_type()});
  }
  ffi::DataType t;
  if (!SameFloat(types, &t))
    return ffi::Error::InvalidArgument("ae_block: float arrays must all be float32 or all float64");
  return ByFloat(t, [&](auto zero) {
    using T = decltype(zero);
    auto opt = [](const ffi::AnyBuffer* a) -> const T* { return a != nullptr ? In<T>(*a) : nullptr; };
    EncoderBackward<T>(s, wg, cg, In<T>(x), Masked<T>{opt(am)}, opt(xh), opt(derr), In<T>(h), In<T>(dz), Ints(nbr),
                       Ints(count), In<T>(inv), In<T>(wp), In<T>(wn), In<T>(c), Out<T>(dx), Out<T>(gwp),
                       Out<T>(gwn), Out<T>(gb), Out<T>(dc));
  });
}

ffi::Error EncoderBwdDispatch(ffi::ThreadPool pool, ffi::AnyBuffer x, ffi::AnyBuffer h, ffi::AnyBuffer dz,
                              ffi::AnyBuffer nbr, ffi::AnyBuffer count, ffi::AnyBuffer inv, ffi::AnyBuffer wp,
                              ffi::AnyBuffer wn, ffi::AnyBuffer b, ffi::AnyBuffer c, ffi::Result<ffi::AnyBuffer> dx,
                              ffi::Result<ffi::AnyBuffer> gwp, ffi::Result<ffi::AnyBuffer> gwn,
                              ffi::Result<ffi::AnyBuffer> gb, ffi::Result<ffi::AnyBuffer> dc) {
  return EncoderBwd(pool, x, nullptr, h, dz, nullptr, nullptr, nbr, count, inv, wp, wn, b, c, dx, gwp, gwn, gb, dc);
}

ffi::Error EncoderBwdMaskedDispatch(ffi::ThreadPool pool, ffi::AnyBuffer x, ffi::AnyBuffer am, ffi::AnyBuffer h,
                                    ffi::AnyBuffer dz, ffi::AnyBuffer xh, ffi::AnyBuffer derr, ffi::AnyBuffer nbr,
                                    ffi::AnyBuffer count, ffi::AnyBuffer inv, ffi::AnyBuffer wp, ffi::AnyBuffer wn,
                                    ffi::AnyBuffer b, ffi::AnyBuffer c, ffi::Result<ffi::AnyBuffer> dx,
                                    ffi::Result<ffi::AnyBuffer> gwp, ffi::Result<ffi::AnyBuffer> gwn,
                                    ffi::Result<ffi::AnyBuffer> gb, ffi::Result<ffi::AnyBuffer> dc) {
  return EncoderBwd(pool, x, &am, h, dz, &xh, &derr, nbr, count, inv, wp, wn, b, c, dx, gwp, gwn, gb, dc);
}

// The decoder forward, with target and err (the per-plane squared error) or without (both null)
ffi::Error DecoderFwd(ffi::ThreadPool& pool, ffi::AnyBuffer z, ffi::AnyBuffer nbr, ffi::AnyBuffer count,
                      ffi::AnyBuffer inv, ffi::AnyBuffer wp, ffi::AnyBuffer wn, ffi::AnyBuffer b, ffi::AnyBuffer c,
                      const ffi::AnyBuffer* target, const ffi::AnyBuffer* am, ffi::Result<ffi::AnyBuffer>& xh,
                      ffi::Result<ffi::AnyBuffer>& hidden, ffi::Result<ffi::AnyBuffer>* err) {
  PoolScope scope(&pool);
  AeGeometry s;
  const Dims out = DimsOf(*xh);
  if (auto e = MakeAeGeometry(out, true, nbr, count, inv, wp, wn, b, c, &s); e.failure()) return e;
  if (auto e = InputMap(z, false, WithCore(out, 3, {s.P, s.Kz}), s, &s.in); e.failure()) return e;
  ffi::DataType t;
  if (hidden->element_count() != xh->element_count())
    return ffi::Error::InvalidArgument("ae_block: the hidden layer has the wrong size");
  std::vector<ffi::DataType> types = {z.element_type(), inv.element_type(), wp.element_type(), wn.element_type(),
                                      b.element_type(), c.element_type(), xh->element_type(), hidden->element_type()};
  if (target != nullptr) {
    if (auto e = InputMap(*target, true, out, s, &s.tgt); e.failure()) return e;
    if (static_cast<int64_t>((*err)->element_count()) != s.G * s.P)
      return ffi::Error::InvalidArgument("ae_block: the error output has the wrong size");
    types.push_back(target->element_type());
    types.push_back((*err)->element_type());
  }
  if (am != nullptr) {
    if (auto e = MaskMap(*am, out, 3, &s); e.failure()) return e;
    types.push_back(am->element_type());
  }
  if (!SameFloat(types, &t))
    return ffi::Error::InvalidArgument("ae_block: float arrays must all be float32 or all float64");
  return ByFloat(t, [&](auto zero) {
    using T = decltype(zero);
    DecoderForward<T>(s, In<T>(z), Ints(nbr), Ints(count), In<T>(inv), In<T>(wp), In<T>(wn), In<T>(b), In<T>(c),
                      target != nullptr ? In<T>(*target) : nullptr, Masked<T>{am != nullptr ? In<T>(*am) : nullptr},
                      Out<T>(xh), Out<T>(hidden),
                      err != nullptr ? Out<T>(*err) : nullptr);
  });
}

ffi::Error DecoderFwdDispatch(ffi::ThreadPool pool, ffi::AnyBuffer z, ffi::AnyBuffer nbr, ffi::AnyBuffer count,
                              ffi::AnyBuffer inv, ffi::AnyBuffer wp, ffi::AnyBuffer wn, ffi::AnyBuffer b,
                              ffi::AnyBuffer c, ffi::Result<ffi::AnyBuffer> xh, ffi::Result<ffi::AnyBuffer> hidden) {
  return DecoderFwd(pool, z, nbr, count, inv, wp, wn, b, c, nullptr, nullptr, xh, hidden, nullptr);
}

ffi::Error DecoderFwdErrDispatch(ffi::ThreadPool pool, ffi::AnyBuffer z, ffi::AnyBuffer nbr, ffi::AnyBuffer count,
                                 ffi::AnyBuffer inv, ffi::AnyBuffer wp, ffi::AnyBuffer wn, ffi::AnyBuffer b,
                                 ffi::AnyBuffer c, ffi::AnyBuffer target, ffi::Result<ffi::AnyBuffer> xh,
                                 ffi::Result<ffi::AnyBuffer> hidden, ffi::Result<ffi::AnyBuffer> err) {
  return DecoderFwd(pool, z, nbr, count, inv, wp, wn, b, c, &target, nullptr, xh, hidden, &err);
}

ffi::Error DecoderFwdErrMaskedDispatch(ffi::ThreadPool pool, ffi::AnyBuffer z, ffi::AnyBuffer nbr, ffi::AnyBuffer count,
                                       ffi::AnyBuffer inv, ffi::AnyBuffer wp, ffi::AnyBuffer wn, ffi::AnyBuffer b,
                                       ffi::AnyBuffer c, ffi::AnyBuffer target, ffi::AnyBuffer am,
                                       ffi::Result<ffi::AnyBuffer> xh, ffi::Result<ffi::AnyBuffer> hidden,
                                       ffi::Result<ffi::AnyBuffer> err) {
  return DecoderFwd(pool, z, nbr, count, inv, wp, wn, b, c, &target, &am, xh, hidden, &err);
}

ffi::Error DecoderBwdDispatch(ffi::ThreadPool pool, ffi::AnyBuffer z, ffi::AnyBuffer hidden, ffi::AnyBuffer dpre,
                              ffi::AnyBuffer nbr,
                              ffi::AnyBuffer count, ffi::AnyBuffer inv, ffi::AnyBuffer wp, ffi::AnyBuffer wn,
                              ffi::AnyBuffer b, ffi::AnyBuffer c, ffi::Result<ffi::AnyBuffer> dz,
                              ffi::Result<ffi::AnyBuffer> gwp, ffi::Result<ffi::AnyBuffer> gwn,
                              ffi::Result<ffi::AnyBuffer> gb, ffi::Result<ffi::AnyBuffer> dc) {
  PoolScope scope(&pool);
  AeGeometry s;
  const Dims out = DimsOf(*dz);
  if (auto e = MakeAeGeometry(out, false, nbr, count, inv, wp, wn, b, c, &s); e.failure()) return e;
  if (auto e = InputMap(z, false, out, s, &s.in); e.failure()) return e;
  const Dims pout = WithCore(out, 2, {s.P, s.V, 9});
  if (auto e = InputMap(hidden, true, pout, s, &s.aux); e.failure()) return e;
  if (auto e = InputMap(dpre, true, pout, s, &s.cot); e.failure()) return e;
  int64_t wg, cg;
  if (auto e = GradOutputs(s, gwp, gwn, gb, dc, &wg, &cg); e.failure()) return e;
  ffi::DataType t;
  if (!SameFloat({z.element_type(), hidden.element_type(), dpre.element_type(), inv.element_type(), wp.element_type(),
                  wn.element_type(), b.element_type(), c.element_type(), dz->element_type(), gwp->element_type(),
                  gwn->element_type(), gb->element_type(), dc->element_type()}, &t))
    return ffi::Error::InvalidArgument("ae_block: float arrays must all be float32 or all float64");
  return ByFloat(t, [&](auto zero) {
    using T = decltype(zero);
    DecoderBackward<T>(s, wg, cg, In<T>(z), In<T>(hidden), In<T>(dpre), Ints(nbr), Ints(count), In<T>(inv), In<T>(wp),
                       In<T>(wn), In<T>(c), Out<T>(dz), Out<T>(gwp), Out<T>(gwn), Out<T>(gb), Out<T>(dc));
  });
}

// ---- Adam ----
//
// One step of Adam, optax.adam's arithmetic, over a parameter array p and its moments mu, nu in one pass (the
// results alias them): g = the sum of the gradient parts + coef[row] p (coef: one entry per row of r entries,
// or none), mu' = (1 - b1) g + b1 mu, nu' = (1 - b2) g^2 + b2 nu, p' = p + step (mu' / bc1) / (sqrt(nu' / bc2)
// + eps), scalars = (b1, b2, bc1, bc2, eps, step). Why: XLA on CPU updates mu, nu and p in three passes, each
// reading the gradient's terms again (on the horse model's level 1, 15 MB arrays: 6.8 ms of a 58 ms step).
// coef p is the gradient of a weighted sum of row norms (seed 000's group sparsity), taken here instead of an
// array of its own.
constexpr int64_t kAdamRows = 8, kAdamMaxRow = 64;  // rows of the coefficient term: at most 64 entries

// sqrt of a scalar or, lane by lane, of a vector
template <typename X>
X Sqrt(X x) {
  if constexpr (std::is_arithmetic_v<X>) {
    return std::sqrt(x);
#if defined(__AVX2__)
  } else if constexpr (sizeof(X) == 32 && std::is_same_v<std::remove_cv_t<std::remove_reference_t<decltype(x[0])>>, float>) {
    return reinterpret_cast<X>(_mm256_sqrt_ps(reinterpret_cast<__m256>(x)));
#endif
  } else {
    for (int t = 0; t < static_cast<int>(sizeof(X) / sizeof(x[0])); ++t) x[t] = std::sqrt(x[t]);
    return x;
  }
}

template <typename T>
void AdamUpdate(int64_t rows, int64_t r, const T* p, const T* mu, const T* nu, const T* coef,
                const std::vector<const T*>& parts, const T* sc, T* po, T* muo, T* nuo) {
  typedef T V8 __attribute__((vector_size(8 * sizeof(T))));
  const T b1 = sc[0], b2 = sc[1], bc1 = sc[2], bc2 = sc[3], eps = sc[4], step = sc[5];
  const T a1 = T(1) - b1, a2 = T(1) - b2;
  const int64_t np = static_cast<int64_t>(parts.size());
  auto load = [](const T* a) {
    V8 v;
    std::memcpy(&v, a, sizeof(V8));
    return v;
  };
  RunPlan(MakePlan(rows, kAdamRows, r * (8 + np)), rows, [&](int64_t, int64_t r0, int64_t r1) {
    alignas(64) T cb[kAdamRows * kAdamMaxRow];  // the block's row coefficients, one per entry
    const bool per_entry = coef != nullptr;
    for (int64_t q0 = r0; q0 < r1; q0 += kAdamRows) {
      const int64_t e0 = q0 * r, ne = (std::min(r1, q0 + kAdamRows) - q0) * r;
      if (per_entry)
        for (int64_t q = 0; q * r < ne; ++q)
          for (int64_t c = 0; c < r; ++c) cb[q * r + c] = coef[q0 + q];
      auto entry = [&](auto g, auto m, auto v, auto x) {  // scalar or vector entries
        m = a1 * g + b1 * m;
        v = a2 * (g * g) + b2 * v;
        return std::make_tuple(m, v, x + step * ((m / bc1) / (Sqrt(v / bc2) + eps)));
      };
      int64_t e = 0;
      for (; e + 8 <= ne; e += 8) {
        const int64_t at = e0 + e;
        V8 g = load(parts[0] + at);
        for (int64_t k = 1; k < np; ++k) g += load(parts[static_cast<size_t>(k)] + at);
        const V8 x0 = load(p + at);
        if (per_entry) g += load(cb + e) * x0;
        auto [m, v, x] = entry(g, load(mu + at), load(nu + at), x0);
        std::memcpy(muo + at, &m, sizeof(V8));
        std::memcpy(nuo + at, &v, sizeof(V8));
        std::memcpy(po + at, &x, sizeof(V8));
      }
      for (; e < ne; ++e) {
        const int64_t at = e0 + e;
        T g = parts[0][at];
        for (int64_t k = 1; k < np; ++k) g += parts[static_cast<size_t>(k)][at];
        if (per_entry) g += cb[e] * p[at];
        auto [m, v, x] = entry(g, mu[at], nu[at], p[at]);
        muo[at] = m;
        nuo[at] = v;
        po[at] = x;
      }
    }
  });
}

ffi::Error AdamDispatch(ffi::ThreadPool pool, ffi::AnyBuffer p, ffi::AnyBuffer mu, ffi::AnyBuffer nu,
                        ffi::AnyBuffer scalars, ffi::AnyBuffer coef, ffi::Result<ffi::AnyBuffer> po,
                        ffi::Result<ffi::AnyBuffer> muo, ffi::Result<ffi::AnyBuffer> nuo, ffi::RemainingArgs grads) {
  PoolScope scope(&pool);
  const int64_t n = static_cast<int64_t>(p.element_count());
  const int64_t nc = static_cast<int64_t>(coef.element_count());
  if (grads.size() < 1) return ffi::Error::InvalidArgument("adam: no gradient given");
  if (static_cast<int64_t>(mu.element_count()) != n || static_cast<int64_t>(nu.element_count()) != n ||
      static_cast<int64_t>(po->element_count()) != n || static_cast<int64_t>(muo->element_count()) != n ||
      static_cast<int64_t>(nuo->element_count()) != n || scalars.element_count() != 6)
    return ffi::Error::InvalidArgument("adam: the moments and results must be shaped like the parameter");
  if (nc != 0 && (n % nc != 0 || n / nc > kAdamMaxRow))
    return ffi::Error::InvalidArgument("adam: the row coefficients do not divide the parameter into rows of at most 64");
  std::vector<ffi::AnyBuffer> gs;
  std::vector<ffi::DataType> types = {p.element_type(), mu.element_type(), nu.element_type(), scalars.element_type(),
                                      po->element_type(), muo->element_type(), nuo->element_type()};
  if (nc != 0) types.push_back(coef.element_type());
  for (size_t k = 0; k < grads.size(); ++k) {
    auto g = grads.get<ffi::AnyBuffer>(k);
    if (!g.has_value()) return g.error();
    if (static_cast<int64_t>(g->element_count()) != n)
      return ffi::Error::InvalidArgument("adam: a gradient part is not shaped like the parameter");
    gs.push_back(*g);
    types.push_back(g->element_type());
  }
  ffi::DataType t;
  if (!SameFloat(types, &t)) return ffi::Error::InvalidArgument("adam: float arrays must all be float32 or all float64");
  const int64_t r = nc != 0 ? n / nc : 1;
  return ByFloat(t, [&](auto zero) {
    using T = decltype(zero);
    std::vector<const T*> parts;
    for (auto& g : gs) parts.push_back(In<T>(g));
    AdamUpdate<T>(n / r, r, In<T>(p), In<T>(mu), In<T>(nu), nc != 0 ? In<T>(coef) : nullptr, parts, In<T>(scalars),
                  Out<T>(po), Out<T>(muo), Out<T>(nuo));
  });
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxdeformMeshConvFwd, ForwardDispatch,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
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
                                  .Ctx<ffi::ThreadPool>()
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

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxdeformAeEncoderFwd, EncoderFwdDispatch,
                              BlockArgs(ffi::Ffi::Bind().Ctx<ffi::ThreadPool>().Arg<ffi::AnyBuffer>())  // x (..., P, V, 9), then BlockArgs
                                  .Ret<ffi::AnyBuffer>()  // z (..., P, Kz)
                                  .Ret<ffi::AnyBuffer>());  // h = tanh(conv(x)) (..., P, V, 9), for the adjoint

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxdeformAeEncoderBwd, EncoderBwdDispatch,
                              GradRets(BlockArgs(ffi::Ffi::Bind().Ctx<ffi::ThreadPool>()
                                                     .Arg<ffi::AnyBuffer>()     // x
                                                     .Arg<ffi::AnyBuffer>()     // h (the forward's second output)
                                                     .Arg<ffi::AnyBuffer>())));  // cotangent of z; returns dx first

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxdeformAeDecoderFwd, DecoderFwdDispatch,
                              BlockArgs(ffi::Ffi::Bind().Ctx<ffi::ThreadPool>().Arg<ffi::AnyBuffer>())  // z (..., P, Kz), then BlockArgs
                                  .Ret<ffi::AnyBuffer>()                        // x_hat (..., P, V, 9)
                                  .Ret<ffi::AnyBuffer>());  // S = tanh(reshape(z C)) (..., P, V, 9), for the adjoint

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxdeformAeDecoderFwdErr, DecoderFwdErrDispatch,
                              BlockArgs(ffi::Ffi::Bind().Ctx<ffi::ThreadPool>().Arg<ffi::AnyBuffer>())  // z, then BlockArgs
                                  .Arg<ffi::AnyBuffer>()  // target (..., P, V, 9)
                                  .Ret<ffi::AnyBuffer>()  // x_hat
                                  .Ret<ffi::AnyBuffer>()  // S
                                  .Ret<ffi::AnyBuffer>());  // err (..., P): sum over V and 9 of (x_hat - target)^2

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxdeformAeEncoderFwdMasked, EncoderFwdMaskedDispatch,
                              BlockArgs(ffi::Ffi::Bind().Ctx<ffi::ThreadPool>()
                                            .Arg<ffi::AnyBuffer>()    // x (..., P, V, 9), broadcast over the blocks
                                            .Arg<ffi::AnyBuffer>())  // am (..., V): block g reads am[g] x
                                  .Ret<ffi::AnyBuffer>()  // z
                                  .Ret<ffi::AnyBuffer>());  // h

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxdeformAeEncoderBwdMasked, EncoderBwdMaskedDispatch,
                              GradRets(BlockArgs(ffi::Ffi::Bind().Ctx<ffi::ThreadPool>()
                                                     .Arg<ffi::AnyBuffer>()      // x
                                                     .Arg<ffi::AnyBuffer>()      // am
                                                     .Arg<ffi::AnyBuffer>()      // h
                                                     .Arg<ffi::AnyBuffer>()      // cotangent of z
                                                     .Arg<ffi::AnyBuffer>()      // the decoders' x_hat
                                                     .Arg<ffi::AnyBuffer>())));  // cotangent of their errors; returns dx (like x) first

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxdeformAeDecoderFwdErrMasked, DecoderFwdErrMaskedDispatch,
                              BlockArgs(ffi::Ffi::Bind().Ctx<ffi::ThreadPool>().Arg<ffi::AnyBuffer>())  // z, then BlockArgs
                                  .Arg<ffi::AnyBuffer>()  // target x, broadcast over the blocks
                                  .Arg<ffi::AnyBuffer>()  // am: block g's target is am[g] x
                                  .Ret<ffi::AnyBuffer>()  // x_hat
                                  .Ret<ffi::AnyBuffer>()  // S
                                  .Ret<ffi::AnyBuffer>());  // err

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxdeformAeDecoderBwd, DecoderBwdDispatch,
                              GradRets(BlockArgs(ffi::Ffi::Bind().Ctx<ffi::ThreadPool>()
                                                     .Arg<ffi::AnyBuffer>()      // z
                                                     .Arg<ffi::AnyBuffer>()      // S (the forward's second output)
                                                     .Arg<ffi::AnyBuffer>())));  // dx_hat (1 - x_hat^2); returns dz first

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxdeformAdam, AdamDispatch,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()  // p
                                  .Arg<ffi::AnyBuffer>()  // mu
                                  .Arg<ffi::AnyBuffer>()  // nu
                                  .Arg<ffi::AnyBuffer>()  // (b1, b2, bc1, bc2, eps, step)
                                  .Arg<ffi::AnyBuffer>()  // coefficient per row of p, or empty
                                  .Ret<ffi::AnyBuffer>()  // p' (aliases p)
                                  .Ret<ffi::AnyBuffer>()  // mu' (aliases mu)
                                  .Ret<ffi::AnyBuffer>()  // nu' (aliases nu)
                                  .RemainingArgs());      // the gradient parts (at least one), summed
