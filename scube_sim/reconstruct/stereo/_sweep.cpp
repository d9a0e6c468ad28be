// The compiled plane sweep of multi-view stereo (mvs.py's `_volume` on the census cost): per depth
// hypothesis and source view the bilinear warp of the source onto the reference through the
// hypothesis plane, the census of the warped grey against the reference's, the window-box average
// over the valid pixels, the robust mean over the sources, and per source its own curve's minimum,
// its hypothesis and its maximum. compiled.py wraps it; mvs.py's `_volume_reference` (torch) is the
// reference it is tested against. Then the semi-global aggregation of the volume (sgm.py's
// `semi_global`) and its winner-take-all (sweep.py's `winner_take_all`), each the reference's
// operations in its order (their sections below).
//
// Each step repeats the reference's arithmetic operation by operation so that most outputs are the
// same bytes (sweep.py's `warp_to_reference` and `cost_census`, torch's CPU kernels underneath):
// - plane point, projection and grid coordinate in float64 (d * a + b, x / z, 2 x / Ws - 1), then
//   float32 (grid_sample's grid);
// - grid_sample (align_corners=False, border padding): (g + 1) * (W / 2) - 0.5 clamped to
//   [0, W - 1], bilinear weights from the floor, the four corners summed nw, ne, sw, se; torch's
//   vectorised kernel evaluates the unnormalisation and the corner sum with fused multiply-adds,
//   and so does this file (std::fma), so the samples agree bit for bit where torch runs that kernel;
//   nearest sampling (the source's mask) rounds half to even;
// - grey: BT.601 luma of RGB, channel by channel (float32 products, then sums);
// - census: a bit per neighbour of the window (off the image: not counted), set where the
//   neighbour is darker than the centre; differing bits counted over the neighbours whose warped
//   pixel is valid, divided by their count;
// - the box mean: a row pass then a column pass, each the in-order float32 sum of the window's taps
//   divided by the window (avg_pool2d's count_include_pad), of the masked cost and of the mask;
// - robust mean: the sources that see the entry sorted by cost, the first k summed in that order,
//   k = max(ceil(n / 2), min(n, 2)), divided by k.
//
// Threads: the hypotheses of a block are shared out (each hypothesis's planes written by the one
// thread that computes it), then the rows (each source's minimum, hypothesis and maximum updated
// in hypothesis order by the thread owning the row): no value depends on the thread count.
//
// Builds: the hot loops are compiled twice, for x86-64 CPUs with AVX2 and FMA (chosen at run time)
// and portably (std::fma in software where the CPU has none): the same values either way. The
// extension is compiled with -ffp-contract=off (no fused operation but those written) and
// -fno-trapping-math (lets the compiler vectorise branch-free selects; no value changes).
//
// Frames: reference pixels row-major, centres at (u + 0.5, v + 0.5); `a` (3, h*w) and `b` (3,)
// float64 give the plane point of reference pixel p at depth d (metres, reference camera z) in the
// source's homogeneous pixels: d * a[:, p] + b.

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <exception>
#include <limits>
#include <memory>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

namespace py = pybind11;

namespace {

constexpr float kNaNf = std::numeric_limits<float>::quiet_NaN();
constexpr float kInff = std::numeric_limits<float>::infinity();

template <typename T>
using Arr = py::array_t<T, py::array::c_style | py::array::forcecast>;

struct Source {
  Arr<float> img;       // (C, Hs, Ws)
  Arr<double> a;        // (3, h*w)
  Arr<double> b;        // (3,)
  Arr<uint8_t> ref_mask;  // (h, w), 1: not matched there; empty: none
  Arr<float> src_mask;  // (Hs, Ws), >= 0.5: masked in the source; empty: none
  bool has_ref_mask = false, has_src_mask = false;
  int C = 0, Hs = 0, Ws = 0;
  std::vector<float> luma;  // grey weights per channel (float32, as torch multiplies by them)
  std::vector<float> pixels;  // C <= 4: the image interleaved, 4 floats a pixel (zeros past C)
};

// Planes with a border: `r` rows above and below, `r` columns left and (at least) right of each
// row, rows `pitch` floats apart, so that every census neighbour of an image pixel lies inside and
// whole vectors of kLanes pixels can be read along a row. Pixel (y, x) sits at
// (y + r) * pitch + r + x. The border's validity is 0: its neighbours are not counted, as those
// off the image are not.
constexpr int kLanes = 8;
struct Padded {
  int h = 0, w = 0, r = 0, pitch = 0;
  Padded() = default;
  Padded(int h_, int w_, int r_)
      : h(h_), w(w_), r(r_), pitch(((w_ + kLanes - 1) / kLanes) * kLanes + 2 * r_ + kLanes) {}
  int64_t size() const { return static_cast<int64_t>(h + 2 * r) * pitch; }
  int64_t at(int y, int x) const { return static_cast<int64_t>(y + r) * pitch + r + x; }
};

// The reference side of a sweep: its grey (h*w, and padded), usable pixels, size, census window
// and the nearest plane point a source may see (metres in front of it).
struct Reference {
  const uint8_t* ok = nullptr;
  int h = 0, w = 0, window = 0;
  int64_t hw = 0;
  double min_z = 0.0;
  Padded pad;
  std::vector<float> grey;         // padded (pad.size()), zeros in the border
  std::vector<int64_t> neighbours;  // the census offsets in the padded planes, row-major, centre skipped
};

// Per-thread buffers: the warped grey and validity (padded like the reference), the per-pixel cost
// and mask (rows of `cost_pitch` with r zeros before each row and zeros after it), their row
// pass (rows of `row_pitch`, whole vectors).
struct Scratch {
  int cost_pitch = 0, row_pitch = 0;
  std::vector<float> ux, uy, grey, cost, mask, row_cost, row_mask;
  std::vector<int32_t> valid;  // padded: -1 valid, 0 not (the border stays 0)
  std::vector<uint8_t> ok;
  explicit Scratch(const Reference& ref)
      : cost_pitch(((ref.w + kLanes - 1) / kLanes) * kLanes + 2 * (ref.window / 2) + kLanes),
        row_pitch(((ref.w + kLanes - 1) / kLanes) * kLanes),
        ux(ref.hw),
        uy(ref.hw),
        grey(ref.pad.size(), 0.0f),
        cost(static_cast<size_t>(ref.h) * cost_pitch, 0.0f),
        mask(static_cast<size_t>(ref.h) * cost_pitch, 0.0f),
        row_cost(static_cast<size_t>(ref.h) * row_pitch),
        row_mask(static_cast<size_t>(ref.h) * row_pitch),
        valid(ref.pad.size(), 0),
        ok(ref.hw) {}
};

// Runs fn(item, thread) for item in [0, n) on up to `threads` std::threads (items claimed in order
// from a shared counter); each item's outputs are its own, so which thread ran it does not matter.
template <typename Fn>
void parallel_items(int64_t n, int threads, Fn fn) {
  const int nt = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(threads, n)));
  std::atomic<int64_t> next{0};
  std::vector<std::exception_ptr> errors(nt);
  auto work = [&](int tid) {
    try {
      for (int64_t i = next++; i < n; i = next++) fn(i, tid);
    } catch (...) {
      errors[tid] = std::current_exception();
    }
  };
  if (nt == 1) {
    work(0);
  } else {
    std::vector<std::thread> pool;
    for (int t = 1; t < nt; ++t) pool.emplace_back(work, t);
    work(0);
    for (auto& th : pool) th.join();
  }
  for (auto& e : errors)
    if (e) std::rethrow_exception(e);
}

#define SWEEP_INLINE inline __attribute__((always_inline))

// kLanes floats / int32 (GCC vector extensions: AVX2 registers in the AVX2 build, pairs of SSE2
// registers in the portable one; either way IEEE operations lane by lane).
typedef float VecF __attribute__((vector_size(4 * kLanes)));
typedef int32_t VecI __attribute__((vector_size(4 * kLanes)));

#define SWEEP_LOAD(v, p) std::memcpy(&(v), (p), sizeof(v))   // an unaligned vector load
#define SWEEP_STORE(p, v) std::memcpy((p), &(v), sizeof(v))  // an unaligned vector store

typedef float Vec4 __attribute__((vector_size(16)));

// One channel's bilinear sample: the corners nw, ne, sw, se of plane p around pixel o (de, ds: the
// offsets of the east and south corners, 0 where they lie beyond the image, whose values count 0).
SWEEP_INLINE float corners(const float* __restrict p, int o, int de, int ds, bool e_in, bool s_in, float nw, float ne,
                           float sw, float se) {
  const float r_nw = p[o], r_ne = p[o + de], r_sw = p[o + ds], r_se = p[o + ds + de];
  const float v_ne = e_in ? r_ne : 0.0f;
  const float v_sw = s_in ? r_sw : 0.0f;
  const float v_se = (e_in & s_in) ? r_se : 0.0f;
  float u = r_nw * nw;
  u = std::fma(v_ne, ne, u);
  u = std::fma(v_sw, sw, u);
  return std::fma(v_se, se, u);
}

// The same for up to 4 interleaved channels at once (lane by lane the same operations).
SWEEP_INLINE Vec4 corners4(const float* __restrict px, int o, int de, int ds, bool e_in, bool s_in, float nw, float ne,
                           float sw, float se) {
  Vec4 r_nw, r_ne, r_sw, r_se;
  std::memcpy(&r_nw, px + 4 * o, sizeof(Vec4));
  std::memcpy(&r_ne, px + 4 * (o + de), sizeof(Vec4));
  std::memcpy(&r_sw, px + 4 * (o + ds), sizeof(Vec4));
  std::memcpy(&r_se, px + 4 * (o + ds + de), sizeof(Vec4));
  const Vec4 zero = {};
  const Vec4 v_ne = e_in ? r_ne : zero;
  const Vec4 v_sw = s_in ? r_sw : zero;
  const Vec4 v_se = (e_in & s_in) ? r_se : zero;
  Vec4 u = r_nw * nw;
  for (int c = 0; c < 4; ++c) {  // lane by lane: std::fma
    u[c] = std::fma(v_ne[c], ne, u[c]);
    u[c] = std::fma(v_sw[c], sw, u[c]);
    u[c] = std::fma(v_se[c], se, u[c]);
  }
  return u;
}

// The bilinear samples' grey and the validity of the warp (`warp_impl`) from its grid (sc.ux, sc.uy,
// sc.ok): weights from the floor, the corners summed nw, ne, sw, se (torch: fused multiply-adds),
// a corner beyond the last row or column read as 0 (its weight is 0 there); kC channels
// interleaved (1 to 4), or (0) s.C planar ones.
template <int kC>
SWEEP_INLINE void bilinear(const Source& s, const Reference& ref, Scratch& sc) {
  const int W = s.Ws, H = s.Hs, C = kC > 0 ? kC : s.C;
  const float* __restrict img = s.img.data();
  const float* __restrict px = s.pixels.data();
  const int64_t plane = static_cast<int64_t>(H) * W;
  const float* __restrict smask = s.has_src_mask ? s.src_mask.data() : nullptr;
  const uint8_t* __restrict rmask = s.has_ref_mask ? s.ref_mask.data() : nullptr;
  const float* luma = s.luma.data();
  float l[4] = {0.0f, 0.0f, 0.0f, 0.0f};
  for (int c = 0; c < std::min(C, 4); ++c) l[c] = luma[c];
  const float* __restrict ux = sc.ux.data();
  const float* __restrict uy = sc.uy.data();
  const uint8_t* __restrict okp = sc.ok.data();
  const uint8_t* __restrict ref_ok = ref.ok;
  float* __restrict grey = sc.grey.data();
  int32_t* __restrict valid = sc.valid.data();
  const int rh = ref.h, rw = ref.w;  // locals: the stores below cannot change them
  for (int yr = 0; yr < rh; ++yr) {
    const int64_t i0 = static_cast<int64_t>(yr) * rw, o0 = ref.pad.at(yr, 0);
    for (int xr = 0; xr < rw; ++xr) {
      const int64_t i = i0 + xr;
      const float fx = ux[i], fy = uy[i];
      const float xw = std::floor(fx), yn = std::floor(fy);
      const float we = fx - xw, ea = 1.0f - we, no = fy - yn, so = 1.0f - no;
      const float nw = so * ea, ne = so * we, sw = no * ea, se = no * we;
      const int ix = static_cast<int>(xw), iy = static_cast<int>(yn);
      const bool e_in = ix + 1 < W, s_in = iy + 1 < H;
      const int o = iy * W + ix;
      const int de = e_in ? 1 : 0, ds = s_in ? W : 0;  // in-image reads, selected away
      float g;
      if (kC > 0) {  // channel by channel: products, then sums in channel order (`sweep.grey`)
        const Vec4 t = corners4(px, o, de, ds, e_in, s_in, nw, ne, sw, se);
        if (kC == 1) {
          g = t[0];
        } else {
          g = t[0] * l[0];
          g = g + t[1] * l[1];
          if (kC > 2) g = g + t[2] * l[2];
          if (kC > 3) g = g + t[3] * l[3];
        }
      } else {
        g = 0.0f;
        for (int c = 0; c < C; ++c) {
          const float u = corners(img + c * plane, o, de, ds, e_in, s_in, nw, ne, sw, se);
          g = C == 1 ? u : (c == 0 ? u * luma[0] : g + u * luma[c]);
        }
      }
      grey[o0 + xr] = g;
    }
    // validity: the grid's, the reference's, and the source mask at the nearest pixel
    for (int xr = 0; xr < rw; ++xr) {
      const int64_t i = i0 + xr;
      bool v = okp[i] & ref_ok[i];
      if (rmask) v = v & !rmask[i];
      valid[o0 + xr] = v ? -1 : 0;
    }
    if (smask) {
      for (int xr = 0; xr < rw; ++xr) {
        const int64_t i = i0 + xr;
        const int nx = static_cast<int>(std::nearbyint(ux[i])), ny = static_cast<int>(std::nearbyint(uy[i]));
        const bool seen = smask[ny * W + nx] < 0.5f;
        valid[o0 + xr] = seen ? valid[o0 + xr] : 0;
      }
    }
  }
}

// The warp of source s at depth d into sc.grey (padded): the bilinear sample's grey, and sc.valid
// (padded): the plane point lies in front of the source (z > min_z) and lands in [0, Ws] x [0, Hs],
// the reference pixel is usable (ref.ok, not s.ref_mask) and the nearest source pixel is not
// masked (s.src_mask < 0.5).
SWEEP_INLINE void warp_impl(const Source& s, const Reference& ref, double d, Scratch& sc) {
  const int64_t hw = ref.hw;
  const double* a0 = s.a.data();
  const double* a1 = a0 + hw;
  const double* a2 = a1 + hw;
  const double b0 = s.b.data()[0], b1 = s.b.data()[1], b2 = s.b.data()[2];
  const int W = s.Ws, H = s.Hs;
  const double wd = static_cast<double>(W), hd = static_cast<double>(H), min_z = ref.min_z;
  const float sx = static_cast<float>(W) / 2, sy = static_cast<float>(H) / 2;
  const float xmax = static_cast<float>(W - 1), ymax = static_cast<float>(H - 1);
  float* __restrict ux = sc.ux.data();
  float* __restrict uy = sc.uy.data();
  uint8_t* __restrict okp = sc.ok.data();
  // the grid: float64 plane point and projection, float32 grid coordinate, grid_sample's
  // unnormalisation (a fused multiply-add in torch's kernel) and border clamp
  for (int64_t i = 0; i < hw; ++i) {
    const double px = d * a0[i] + b0;
    const double py = d * a1[i] + b1;
    const double pz = d * a2[i] + b2;
    const bool front = pz > min_z;
    const double zs = front ? pz : 1.0;
    const double x = px / zs, y = py / zs;
    const bool ok = front & (x >= 0.0) & (x <= wd) & (y >= 0.0) & (y <= hd);
    const float gx0 = static_cast<float>(2.0 * x / wd - 1.0);
    const float gy0 = static_cast<float>(2.0 * y / hd - 1.0);
    const float gx = ok ? gx0 : 0.0f;
    const float gy = ok ? gy0 : 0.0f;
    const float fx = std::fma(gx + 1.0f, sx, -0.5f);
    const float fy = std::fma(gy + 1.0f, sy, -0.5f);
    const float cx = fx > 0.0f ? fx : 0.0f, cy = fy > 0.0f ? fy : 0.0f;  // NaN-free: as clamp_min
    ux[i] = cx < xmax ? cx : xmax;
    uy[i] = cy < ymax ? cy : ymax;
    okp[i] = ok;
  }
  switch (s.C) {
    case 1:
      bilinear<1>(s, ref, sc);
      break;
    case 2:
      bilinear<2>(s, ref, sc);
      break;
    case 3:
      bilinear<3>(s, ref, sc);
      break;
    case 4:
      bilinear<4>(s, ref, sc);
      break;
    default:
      bilinear<0>(s, ref, sc);
  }
}

// One source's census cost plane at depth d into out (h*w): NaN where the centre is invalid or no
// neighbour of it is valid.
SWEEP_INLINE void cost_impl(const Source& s, const Reference& ref, double d, Scratch& sc, float* out) {
  const int h = ref.h, w = ref.w, r = ref.window / 2, window = ref.window;
  const int cp = sc.cost_pitch, rp = sc.row_pitch;
  const int64_t* nb = ref.neighbours.data();
  const int64_t n_nb = static_cast<int64_t>(ref.neighbours.size());
  warp_impl(s, ref, d, sc);
  const float* rg = ref.grey.data();
  const float* g = sc.grey.data();
  const int32_t* v = sc.valid.data();
  float* pc = sc.cost.data();
  float* pm = sc.mask.data();
  const VecF zero_f = {}, one_f = zero_f + 1.0f;
  const VecI zero_i = {}, one_i = zero_i + 1;
  // census: per kLanes pixels of a row, the differing bits and the neighbours counted over the
  // window's offsets (integer counts: exact in any order), then the share of differing bits,
  // zero where it is not counted (`_window_mean`'s mask). Lanes beyond the row's end read the
  // border, whose validity is 0: they store zeros, as the row pass needs there.
  for (int y = 0; y < h; ++y) {
    for (int xb = 0; xb < w; xb += kLanes) {
      const int64_t c = ref.pad.at(y, xb);
      VecF gc, rc, gn, rn;
      VecI ok, centre, differ = zero_i, counted = zero_i;
      SWEEP_LOAD(gc, g + c);
      SWEEP_LOAD(rc, rg + c);
#pragma GCC unroll 8
      for (int64_t k = 0; k < n_nb; ++k) {
        const int64_t n = c + nb[k];
        SWEEP_LOAD(ok, v + n);
        SWEEP_LOAD(rn, rg + n);
        SWEEP_LOAD(gn, g + n);
        differ -= ((rn < rc) ^ (gn < gc)) & ok;
        counted -= ok;
      }
      SWEEP_LOAD(centre, v + c);
      const VecI m = centre & (counted > zero_i);
      const VecF share = __builtin_convertvector(differ, VecF) /
                         __builtin_convertvector(counted > zero_i ? counted : one_i, VecF);
      const VecF cost = m ? share : zero_f;
      const VecF mask = m ? one_f : zero_f;
      const int64_t at = static_cast<int64_t>(y) * cp + r + xb;
      SWEEP_STORE(pc + at, cost);
      SWEEP_STORE(pm + at, mask);
    }
  }
  // the box's row pass of both: out[y, x] = (in-order sum of in[y, x - r .. x + r], zeros beyond
  // the image) / window; zeros added before the first tap or after the last leave the sum as it is
  const VecF win = zero_f + static_cast<float>(window);
  float* rc_p = sc.row_cost.data();
  float* rm_p = sc.row_mask.data();
  for (int y = 0; y < h; ++y) {
    const float* a = pc + static_cast<int64_t>(y) * cp;
    const float* b = pm + static_cast<int64_t>(y) * cp;
    for (int xb = 0; xb < rp; xb += kLanes) {
      VecF sa = zero_f, sb = zero_f, ta, tb;
      for (int t = 0; t < window; ++t) {
        SWEEP_LOAD(ta, a + xb + t);
        SWEEP_LOAD(tb, b + xb + t);
        sa += ta;
        sb += tb;
      }
      sa = sa / win;
      sb = sb / win;
      SWEEP_STORE(rc_p + static_cast<int64_t>(y) * rp + xb, sa);
      SWEEP_STORE(rm_p + static_cast<int64_t>(y) * rp + xb, sb);
    }
  }
  // the column pass of both, then their ratio where the centre counts
  const VecF floor_den = zero_f + static_cast<float>(1e-12);
  const VecF nan = zero_f + kNaNf;
  for (int y = 0; y < h; ++y) {
    const int ya = std::max(0, y - r), yb = std::min(h, y + r + 1);
    for (int xb = 0; xb < w; xb += kLanes) {
      VecF sa = zero_f, sb = zero_f, ta, tb, centre;
      for (int yy = ya; yy < yb; ++yy) {
        SWEEP_LOAD(ta, rc_p + static_cast<int64_t>(yy) * rp + xb);
        SWEEP_LOAD(tb, rm_p + static_cast<int64_t>(yy) * rp + xb);
        sa += ta;
        sb += tb;
      }
      const VecF num = sa / win, den0 = sb / win;
      const VecF den = den0 > floor_den ? den0 : floor_den;
      SWEEP_LOAD(centre, pm + static_cast<int64_t>(y) * cp + r + xb);
      const VecF res = centre != zero_f ? num / den : nan;
      const int n_out = std::min(kLanes, w - xb);
      float* o = out + static_cast<int64_t>(y) * w + xb;
      if (n_out == kLanes) {
        SWEEP_STORE(o, res);
      } else {
        for (int k = 0; k < n_out; ++k) o[k] = res[k];
      }
    }
  }
}

// The robust mean of n cost planes (n, hw) into out (hw): per entry the mean of the best k of the
// m sources that see it (not NaN), k = max(ceil(m / 2), min(m, 2)), their costs summed in
// ascending order (as the reference sorts them), divided by k; NaN where none sees it.
SWEEP_INLINE void robust_mean_impl(const float* planes, int64_t n, int64_t hw, float* out) {
  if (n <= 4) {
    // k <= 2: the two smallest costs (their sum is the same in either order), kLanes entries at a
    // time, then the rest one by one with the same operations
    const VecF inf_v = VecF{} + kInff, nan_v = VecF{} + kNaNf, one = VecF{} + 1.0f, two = VecF{} + 2.0f;
    const VecI zero_i = {}, two_i = zero_i + 2;
    int64_t i = 0;
    for (; i + kLanes <= hw; i += kLanes) {
      VecF m1 = inf_v, m2 = inf_v, c0;
      VecI m = zero_i;
      for (int64_t k = 0; k < n; ++k) {
        SWEEP_LOAD(c0, planes + k * hw + i);
        const VecI seen = c0 == c0;
        const VecF c = seen ? c0 : inf_v;
        m -= seen;
        const VecF lo = c < m1 ? c : m1, hi = c < m1 ? m1 : c;
        m1 = lo;
        m2 = hi < m2 ? hi : m2;
      }
      const VecF total = m >= two_i ? m1 + m2 : m1;
      const VecF kf = m >= two_i ? two : one;
      const VecF res = m > zero_i ? total / kf : nan_v;
      SWEEP_STORE(out + i, res);
    }
    for (; i < hw; ++i) {
      float m1 = kInff, m2 = kInff;
      int m = 0;
      for (int64_t k = 0; k < n; ++k) {
        const float c0 = planes[k * hw + i];
        const bool seen = c0 == c0;
        const float c = seen ? c0 : kInff;
        m += seen;
        const float lo = c < m1 ? c : m1, hi = c < m1 ? m1 : c;
        m1 = lo;
        m2 = hi < m2 ? hi : m2;
      }
      const float total = m >= 2 ? m1 + m2 : m1;
      const float kf = m >= 2 ? 2.0f : 1.0f;
      out[i] = m > 0 ? total / kf : kNaNf;
    }
    return;
  }
  std::vector<float> vals(n);
  for (int64_t i = 0; i < hw; ++i) {
    int64_t m = 0;
    for (int64_t k = 0; k < n; ++k) {
      const float c = planes[k * hw + i];
      if (std::isnan(c)) continue;
      int64_t at = m++;  // insertion: ascending
      while (at > 0 && vals[at - 1] > c) {
        vals[at] = vals[at - 1];
        --at;
      }
      vals[at] = c;
    }
    if (m == 0) {
      out[i] = kNaNf;
      continue;
    }
    const int64_t k = std::max((m + 1) / 2, std::min<int64_t>(m, 2));
    float total = 0.0f;
    for (int64_t j = 0; j < k; ++j) total += vals[j];
    out[i] = total / static_cast<float>(k);
  }
}

// One source's minimum (best, its hypothesis arg) and maximum (worst) over n entries updated with
// the costs c of hypothesis `index` (NaN: unseen, no change; a strictly lower cost moves the minimum).
SWEEP_INLINE void extremes_impl(const float* __restrict c, int64_t n, int64_t index, float* __restrict best,
                                int64_t* __restrict arg, float* __restrict worst) {
  for (int64_t i = 0; i < n; ++i) {
    const float v = c[i];
    const bool lower = v < best[i];
    best[i] = lower ? v : best[i];
    arg[i] = lower ? index : arg[i];
    worst[i] = v > worst[i] ? v : worst[i];
  }
}

// --- semi-global aggregation (sgm.py's `semi_global`) -----------------------------------------------
//
// The volume pixel-major (h, w, D) so that each step of a path reads and writes D contiguous floats;
// per path pair (left/right, up/down, and for 8 paths the two diagonal families as sgm.py shears
// them, the cells beyond the image costing `fill`) the forward pass's L, then the backward pass
// adds its L to it (a + b = b + a: exact); the pairs are summed in sgm.py's order, divided by the
// path count. Each step: m = min_k L(p - r, k); L(p, d) = C(p, d) + (min(L(p - r, d),
// min(L(p - r, d - 1), L(p - r, d + 1)) + p1, m + p2) - m), each operation one float32 rounding as
// torch's elementwise kernels. Lines are shared out among the threads, each written by one.

// One step of a path: L (D) at the next cell from prev (D) and the cell's cost c (D).
SWEEP_INLINE void sgm_step(const float* __restrict prev, const float* __restrict c, float* __restrict out, int D,
                           float p1, float p2) {
  // the minimum over the hypotheses (exact in any order: lanes first, then across them)
  float m = prev[0];
  int d0 = 0;
  if (D >= kLanes) {
    VecF lanes, v;
    SWEEP_LOAD(lanes, prev);
    for (d0 = kLanes; d0 + kLanes <= D; d0 += kLanes) {
      SWEEP_LOAD(v, prev + d0);
      lanes = v < lanes ? v : lanes;
    }
    for (int k = 0; k < kLanes; ++k) m = lanes[k] < m ? lanes[k] : m;
  }
  for (int d = d0; d < D; ++d) m = prev[d] < m ? prev[d] : m;
  const float mp = m + p2;
  {
    const float a = prev[1] + p1;
    float b = prev[0] < a ? prev[0] : a;
    b = b < mp ? b : mp;
    out[0] = c[0] + (b - m);
  }
  for (int d = 1; d < D - 1; ++d) {
    const float nb = prev[d - 1] < prev[d + 1] ? prev[d - 1] : prev[d + 1];
    const float a = nb + p1;
    float b = prev[d] < a ? prev[d] : a;
    b = b < mp ? b : mp;
    out[d] = c[d] + (b - m);
  }
  {
    const float a = prev[D - 2] + p1;
    float b = prev[D - 1] < a ? prev[D - 1] : a;
    b = b < mp ? b : mp;
    out[D - 1] = c[D - 1] + (b - m);
  }
}

// One line of n cells both ways: cell(i) gives the cost D-vector of step i and dst(i) where its
// L pair's sum goes (kAdd: is added to what is there; nullptr: a cell beyond the image, scanned but
// not kept); buf: (n + 2) * D floats.
template <bool kAdd, typename CellFn, typename DstFn>
SWEEP_INLINE void sgm_line(int n, int D, float p1, float p2, CellFn cell, DstFn dst, float* buf) {
  float* fwd = buf;  // n * D: the forward pass's L
  for (int i = 0; i < n; ++i) {
    const float* c = cell(i);
    if (i == 0) {
      std::copy(c, c + D, fwd);
    } else {
      sgm_step(fwd + static_cast<int64_t>(i - 1) * D, c, fwd + static_cast<int64_t>(i) * D, D, p1, p2);
    }
  }
  float* prev = buf + static_cast<int64_t>(n) * D;  // the backward pass's L, two D-vectors in turn
  float* next = prev + D;
  for (int i = n - 1; i >= 0; --i) {
    const float* c = cell(i);
    if (i == n - 1) {
      std::copy(c, c + D, prev);
    } else {
      sgm_step(prev, c, next, D, p1, p2);
      std::swap(prev, next);
    }
    float* o = dst(i);
    if (o) {
      const float* f = fwd + static_cast<int64_t>(i) * D;
      if (kAdd) {
        for (int d = 0; d < D; ++d) o[d] = o[d] + (f[d] + prev[d]);
      } else {
        for (int d = 0; d < D; ++d) o[d] = f[d] + prev[d];
      }
    }
  }
}

// The aggregated volume: cost (D, h, w) (NaN: unseen) -> out (D, h, w), NaN where cost is.
SWEEP_INLINE void semi_global_impl(const float* cost, int D, int h, int w, float p1, float p2, int paths, float fill,
                                   int threads, float* out) {
  const int64_t hw = static_cast<int64_t>(h) * w;
  // pixel-major (h, w, D) buffers, every entry written before it is read
  std::unique_ptr<float[]> c_buf(new float[hw * D]), total_buf(new float[hw * D]);
  float* c = c_buf.get();
  float* total = total_buf.get();
  parallel_items(h, threads, [&](int64_t y, int) {  // pixel-major, unseen entries filled
    for (int x = 0; x < w; ++x) {
      float* px = c + (y * w + x) * D;
      for (int d = 0; d < D; ++d) {
        const float v = cost[d * hw + y * w + x];
        px[d] = v == v ? v : fill;
      }
    }
  });
  const int longest = std::max(w, h);
  std::vector<std::vector<float>> bufs(std::max(1, threads),
                                       std::vector<float>(static_cast<size_t>(longest + 2) * D));
  auto at = [&](float* v, int64_t y, int64_t x) { return v + (y * w + x) * D; };
  // left and right along each row: total = L_lr + L_rl
  parallel_items(h, threads, [&](int64_t y, int tid) {
    sgm_line<false>(
        w, D, p1, p2, [&](int i) -> const float* { return at(c, y, i); }, [&](int i) { return at(total, y, i); },
        bufs[tid].data());
  });
  // up and down along each column: total = total + (L_tb + L_bt)
  parallel_items(w, threads, [&](int64_t x, int tid) {
    sgm_line<true>(
        h, D, p1, p2, [&](int i) -> const float* { return at(c, i, x); }, [&](int i) { return at(total, i, x); },
        bufs[tid].data());
  });
  if (paths == 8) {
    std::vector<float> fills(D, fill);
    for (int shift : {1, -1}) {
      // sgm.py's shear: row y starts at column y (shift 1) or h - 1 - y (shift -1) of a (h, w + h)
      // volume whose cells beyond the image cost `fill`; a path runs down a sheared column, and
      // total = total + (L_forward + L_backward) of each family in turn
      parallel_items(static_cast<int64_t>(w) + h, threads, [&](int64_t j, int tid) {
        auto col = [&](int y) -> int64_t { return j - (shift > 0 ? y : h - 1 - y); };
        sgm_line<true>(
            h, D, p1, p2,
            [&](int y) -> const float* {
              const int64_t x = col(y);
              return (x >= 0 && x < w) ? at(c, y, x) : fills.data();
            },
            [&](int y) -> float* {
              const int64_t x = col(y);
              return (x >= 0 && x < w) ? at(total, y, x) : nullptr;
            },
            bufs[tid].data());
      });
    }
  }
  const float np = static_cast<float>(paths);
  parallel_items(h, threads, [&](int64_t y, int) {
    for (int x = 0; x < w; ++x) {
      const float* t = total + (y * w + x) * D;
      for (int d = 0; d < D; ++d) {
        const int64_t i = d * hw + y * w + x;
        const float v = cost[i];
        out[i] = v == v ? t[d] / np : kNaNf;
      }
    }
  });
}

// --- winner takes all (sweep.py's `winner_take_all`) -----------------------------------------------
//
// Per pixel, over the hypotheses in order: the first lowest cost (NaN as +inf), the parabola through
// it and its neighbours (float32 offset, clamped to half a step, float64 inverse depth), and the
// peak ratio against the lowest other local minimum more than one hypothesis away (else the
// curve's highest cost). A row's pixels at a time, the hypotheses' planes read in order.
SWEEP_INLINE void wta_impl(const float* cost, int D, int h, int w, const double* inv, float conf_eps, int threads,
                           float* depth, float* best_out, float* conf, int64_t* winner) {
  const int64_t hw = static_cast<int64_t>(h) * w;
  parallel_items(h, threads, [&](int64_t y, int) {
    std::vector<float> best_v(w), second_v(w), highest_v(w), prev_v(w), cur_v(w);
    std::vector<int32_t> k_v(w);
    float* __restrict best = best_v.data();
    float* __restrict second = second_v.data();
    float* __restrict highest = highest_v.data();
    float* __restrict prev = prev_v.data();
    float* __restrict cur = cur_v.data();
    int32_t* __restrict k = k_v.data();
    const float* __restrict row0 = cost + y * w;
    auto at = [&](int d, int x) {  // the cost of hypothesis d at pixel x, NaN as +inf
      const float v = row0[d * hw + x];
      return v == v ? v : kInff;
    };
    for (int x = 0; x < w; ++x) {
      best[x] = kInff;
      k[x] = 0;
      highest[x] = -kInff;
    }
    for (int d = 0; d < D; ++d) {
      const float* __restrict plane = row0 + d * hw;
      for (int x = 0; x < w; ++x) {
        const float v = plane[x];
        const float c = v == v ? v : kInff;
        const bool lower = c < best[x];
        best[x] = lower ? c : best[x];
        k[x] = lower ? d : k[x];
        highest[x] = (c != kInff && c > highest[x]) ? c : highest[x];
      }
    }
    // the lowest local minimum away from the winner: c < left, c <= right, finite, |d - k| > 1
    for (int x = 0; x < w; ++x) {
      second[x] = kInff;
      prev[x] = kInff;  // left of the first hypothesis
      cur[x] = at(0, x);
    }
    for (int d = 0; d < D; ++d) {
      const float* __restrict next_plane = row0 + static_cast<int64_t>(std::min(d + 1, D - 1)) * hw;
      const bool last = d == D - 1;
      for (int x = 0; x < w; ++x) {
        const float c = cur[x], left = prev[x];
        const float nv = next_plane[x];
        const float right = last ? kInff : (nv == nv ? nv : kInff);
        const int away = d - k[x];
        const bool other = (c < left) & (c <= right) & (c != kInff) & ((away > 1) | (away < -1));
        second[x] = (other & (c < second[x])) ? c : second[x];
        prev[x] = c;
        cur[x] = right;
      }
    }
    for (int x = 0; x < w; ++x) {
      const int kk = k[x];
      const float b = best[x];
      const bool found = b != kInff;
      const int km = std::max(kk - 1, 0), kp = std::min(kk + 1, D - 1);
      const float c_m = at(km, x), c_p = at(kp, x);
      const float curv = (c_m - 2.0f * b) + c_p;
      const bool fit = found && kk > 0 && kk < D - 1 && c_m != kInff && c_p != kInff && curv > 0.0f;
      float off = fit ? (0.5f * (c_m - c_p)) / curv : 0.0f;
      off = std::min(0.5f, std::max(-0.5f, off));
      const double o = static_cast<double>(off);
      const double step = o >= 0.0 ? inv[kp] - inv[kk] : inv[kk] - inv[km];
      const double dep = 1.0 / (inv[kk] + o * step);
      const float sec = second[x] != kInff ? second[x] : highest[x];
      const float ratio = 1.0f - (b + conf_eps) / (sec + conf_eps);
      const int64_t i = y * w + x;
      depth[i] = found ? static_cast<float>(dep) : kNaNf;
      best_out[i] = found ? b : kNaNf;
      conf[i] = found ? std::min(1.0f, std::max(0.0f, ratio)) : 0.0f;
      winner[i] = kk;
    }
  });
}

// Two builds of the same code: one for CPUs with AVX2 and FMA (the fused multiply-adds in
// hardware), one for any other (std::fma in software: the same values, slower).
#if defined(__x86_64__) || defined(__i386__)
#define SWEEP_AVX2 __attribute__((target("avx2,fma")))
bool cpu_has_avx2_fma() { return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"); }
#else
#define SWEEP_AVX2
bool cpu_has_avx2_fma() { return false; }
#endif
SWEEP_AVX2 void cost_avx2(const Source& s, const Reference& ref, double d, Scratch& sc, float* out) {
  cost_impl(s, ref, d, sc, out);
}
SWEEP_AVX2 void warp_avx2(const Source& s, const Reference& ref, double d, Scratch& sc) { warp_impl(s, ref, d, sc); }
SWEEP_AVX2 void robust_mean_avx2(const float* planes, int64_t n, int64_t hw, float* out) {
  robust_mean_impl(planes, n, hw, out);
}
SWEEP_AVX2 void extremes_avx2(const float* c, int64_t n, int64_t index, float* best, int64_t* arg, float* worst) {
  extremes_impl(c, n, index, best, arg, worst);
}
SWEEP_AVX2 void semi_global_avx2(const float* cost, int D, int h, int w, float p1, float p2, int paths, float fill,
                                  int threads, float* out) {
  semi_global_impl(cost, D, h, w, p1, p2, paths, fill, threads, out);
}
void semi_global_generic(const float* cost, int D, int h, int w, float p1, float p2, int paths, float fill,
                         int threads, float* out) {
  semi_global_impl(cost, D, h, w, p1, p2, paths, fill, threads, out);
}
SWEEP_AVX2 void wta_avx2(const float* cost, int D, int h, int w, const double* inv, float conf_eps, int threads,
                          float* depth, float* best, float* conf, int64_t* winner) {
  wta_impl(cost, D, h, w, inv, conf_eps, threads, depth, best, conf, winner);
}
void wta_generic(const float* cost, int D, int h, int w, const double* inv, float conf_eps, int threads, float* depth,
                 float* best, float* conf, int64_t* winner) {
  wta_impl(cost, D, h, w, inv, conf_eps, threads, depth, best, conf, winner);
}
void cost_generic(const Source& s, const Reference& ref, double d, Scratch& sc, float* out) {
  cost_impl(s, ref, d, sc, out);
}
void warp_generic(const Source& s, const Reference& ref, double d, Scratch& sc) { warp_impl(s, ref, d, sc); }
void robust_mean_generic(const float* planes, int64_t n, int64_t hw, float* out) {
  robust_mean_impl(planes, n, hw, out);
}
void extremes_generic(const float* c, int64_t n, int64_t index, float* best, int64_t* arg, float* worst) {
  extremes_impl(c, n, index, best, arg, worst);
}

class CensusSweep {
 public:
  CensusSweep(Arr<float> ref_grey, Arr<uint8_t> ref_ok, py::list imgs, py::list as, py::list bs, py::list ref_masks,
              py::list src_masks, int window, double min_z, bool portable)
      : ref_grey_(ref_grey), ref_ok_(ref_ok) {
    if (ref_grey_.ndim() != 2) throw std::invalid_argument("ref_grey: expected (h, w) float32");
    ref_.h = static_cast<int>(ref_grey_.shape(0));
    ref_.w = static_cast<int>(ref_grey_.shape(1));
    ref_.hw = static_cast<int64_t>(ref_.h) * ref_.w;
    if (ref_ok_.ndim() != 2 || ref_ok_.shape(0) != ref_.h || ref_ok_.shape(1) != ref_.w)
      throw std::invalid_argument("ref_ok: expected (h, w) uint8 like ref_grey");
    if (window < 3 || window % 2 == 0 || window > 31)
      throw std::invalid_argument("window: expected an odd size from 3 to 31, got " + std::to_string(window));
    ref_.window = window;
    ref_.min_z = min_z;
    ref_.ok = ref_ok_.data();
    ref_.pad = Padded(ref_.h, ref_.w, window / 2);
    ref_.grey.assign(ref_.pad.size(), 0.0f);
    for (int y = 0; y < ref_.h; ++y)
      std::copy(ref_grey_.data() + static_cast<int64_t>(y) * ref_.w,
                ref_grey_.data() + static_cast<int64_t>(y + 1) * ref_.w, ref_.grey.begin() + ref_.pad.at(y, 0));
    for (int dy = -(window / 2); dy <= window / 2; ++dy)
      for (int dx = -(window / 2); dx <= window / 2; ++dx)
        if (dy != 0 || dx != 0) ref_.neighbours.push_back(static_cast<int64_t>(dy) * ref_.pad.pitch + dx);
    const size_t n = imgs.size();
    if (as.size() != n || bs.size() != n || ref_masks.size() != n || src_masks.size() != n)
      throw std::invalid_argument("sources: imgs, a, b, ref_masks and src_masks must have the same length");
    if (n == 0) throw std::invalid_argument("sources: none given");
    for (size_t k = 0; k < n; ++k) {
      Source s;
      s.img = imgs[k].cast<Arr<float>>();
      if (s.img.ndim() != 3 || s.img.shape(0) < 1 || s.img.shape(1) < 1 || s.img.shape(2) < 1)
        throw std::invalid_argument("source image: expected (C, Hs, Ws) float32");
      s.C = static_cast<int>(s.img.shape(0));
      s.Hs = static_cast<int>(s.img.shape(1));
      s.Ws = static_cast<int>(s.img.shape(2));
      s.a = as[k].cast<Arr<double>>();
      s.b = bs[k].cast<Arr<double>>();
      if (s.a.ndim() != 2 || s.a.shape(0) != 3 || s.a.shape(1) != ref_.hw)
        throw std::invalid_argument("a: expected (3, h*w) float64");
      if (s.b.size() != 3) throw std::invalid_argument("b: expected (3,) float64");
      if (!ref_masks[k].is_none()) {
        s.ref_mask = ref_masks[k].cast<Arr<uint8_t>>();
        if (s.ref_mask.size() != ref_.hw) throw std::invalid_argument("ref_mask: expected (h, w) uint8");
        s.has_ref_mask = true;
      }
      if (!src_masks[k].is_none()) {
        s.src_mask = src_masks[k].cast<Arr<float>>();
        if (s.src_mask.size() != static_cast<int64_t>(s.Hs) * s.Ws)
          throw std::invalid_argument("src_mask: expected (Hs, Ws) float32 like its image");
        s.has_src_mask = true;
      }
      // sweep.grey: BT.601 luma of RGB, the channel itself of one, else the mean
      if (s.C == 3) {
        s.luma = {static_cast<float>(0.299), static_cast<float>(0.587), static_cast<float>(0.114)};
      } else {
        s.luma.assign(s.C, static_cast<float>(1.0 / s.C));
      }
      if (s.C <= 4) {
        const int64_t plane = static_cast<int64_t>(s.Hs) * s.Ws;
        s.pixels.assign(plane * 4, 0.0f);
        for (int c = 0; c < s.C; ++c)
          for (int64_t i = 0; i < plane; ++i) s.pixels[i * 4 + c] = s.img.data()[c * plane + i];
      }
      sources_.push_back(std::move(s));
    }
    avx2_ = !portable && cpu_has_avx2_fma();
  }

  int64_t sources() const { return static_cast<int64_t>(sources_.size()); }
  bool vectorised() const { return avx2_; }

  // Hypotheses `depths` (B,) metres, the first of them hypothesis number `first` of the sweep:
  // fills agg (B, h, w) with the robust mean over the sources and updates best, worst (n, h, w)
  // float32 and arg (n, h, w) int64 with this block's costs (a strictly lower cost moves the
  // minimum: over blocks in hypothesis order, the first minimum of the curve).
  void run(Arr<double> depths, int64_t first, py::array_t<float, py::array::c_style> agg,
           py::array_t<float, py::array::c_style> best, py::array_t<int64_t, py::array::c_style> arg,
           py::array_t<float, py::array::c_style> worst, int threads) {
    const int64_t nb = depths.size(), ns = sources(), hw = ref_.hw;
    const int h = ref_.h, w = ref_.w;
    if (agg.ndim() != 3 || agg.shape(0) != nb || agg.shape(1) != h || agg.shape(2) != w)
      throw std::invalid_argument("agg: expected (B, h, w) float32");
    for (auto* x : {&best, &worst})
      if (x->ndim() != 3 || x->shape(0) != ns || x->shape(1) != h || x->shape(2) != w)
        throw std::invalid_argument("best, worst: expected (n, h, w) float32");
    if (arg.ndim() != 3 || arg.shape(0) != ns || arg.shape(1) != h || arg.shape(2) != w)
      throw std::invalid_argument("arg: expected (n, h, w) int64");
    if (threads < 1) throw std::invalid_argument("threads: expected >= 1");
    const double* dep = depths.data();
    float* agg_p = agg.mutable_data();
    float* best_p = best.mutable_data();
    int64_t* arg_p = arg.mutable_data();
    float* worst_p = worst.mutable_data();
    py::gil_scoped_release release;
    const int nt = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(threads, nb)));
    std::vector<float> costs(static_cast<size_t>(nb * ns * hw));  // (B, n, h*w)
    std::vector<Scratch> scratch;
    scratch.reserve(nt);
    for (int t = 0; t < nt; ++t) scratch.emplace_back(ref_);
    // phase 1: each hypothesis's cost planes and its robust mean, by the thread that claims it
    parallel_items(nb, nt, [&](int64_t j, int tid) {
      float* planes = costs.data() + j * ns * hw;
      for (int64_t k = 0; k < ns; ++k) plane_cost(sources_[k], dep[j], scratch[tid], planes + k * hw);
      if (avx2_) {
        robust_mean_avx2(planes, ns, hw, agg_p + j * hw);
      } else {
        robust_mean_generic(planes, ns, hw, agg_p + j * hw);
      }
    });
    // phase 2: per row, each source's minimum, its hypothesis and its maximum, in hypothesis order
    parallel_items(h, threads, [&](int64_t y, int) {
      for (int64_t j = 0; j < nb; ++j)
        for (int64_t k = 0; k < ns; ++k) {
          const int64_t at = k * hw + y * w;
          const float* c = costs.data() + (j * ns + k) * hw + y * w;
          if (avx2_) {
            extremes_avx2(c, w, first + j, best_p + at, arg_p + at, worst_p + at);
          } else {
            extremes_generic(c, w, first + j, best_p + at, arg_p + at, worst_p + at);
          }
        }
    });
  }

  // Test hook: the warped grey (h, w) float32 and valid (h, w) uint8 of source k at depth d.
  py::tuple warp(int64_t k, double d) const {
    if (k < 0 || k >= sources()) throw std::invalid_argument("warp: no such source");
    Scratch sc(ref_);
    if (avx2_) {
      warp_avx2(sources_[k], ref_, d, sc);
    } else {
      warp_generic(sources_[k], ref_, d, sc);
    }
    py::array_t<float> grey({ref_.h, ref_.w});
    py::array_t<uint8_t> valid({ref_.h, ref_.w});
    for (int y = 0; y < ref_.h; ++y)
      for (int x = 0; x < ref_.w; ++x) {
        const int64_t i = static_cast<int64_t>(y) * ref_.w + x;
        grey.mutable_data()[i] = sc.grey[ref_.pad.at(y, x)];
        valid.mutable_data()[i] = sc.valid[ref_.pad.at(y, x)] != 0;
      }
    return py::make_tuple(grey, valid);
  }

  // Test hook: the census cost (h, w) float32 of source k at depth d (NaN: centre invalid).
  py::array_t<float> cost(int64_t k, double d) const {
    if (k < 0 || k >= sources()) throw std::invalid_argument("cost: no such source");
    py::array_t<float> out({ref_.h, ref_.w});
    Scratch sc(ref_);
    plane_cost(sources_[k], d, sc, out.mutable_data());
    return out;
  }

 private:
  void plane_cost(const Source& s, double d, Scratch& sc, float* out) const {
    if (avx2_) {
      cost_avx2(s, ref_, d, sc, out);
    } else {
      cost_generic(s, ref_, d, sc, out);
    }
  }

  Arr<float> ref_grey_;
  Arr<uint8_t> ref_ok_;
  Reference ref_;
  bool avx2_ = false;
  std::vector<Source> sources_;
};

// sgm.py's `semi_global`: cost (D, h, w) float32 -> (D, h, w) float32.
py::array_t<float> semi_global(Arr<float> cost, double p1, double p2, int paths, double fill, int threads,
                               bool portable) {
  if (cost.ndim() != 3 || cost.shape(0) < 2) throw std::invalid_argument("cost: expected (D, h, w) float32, D >= 2");
  if (paths != 4 && paths != 8) throw std::invalid_argument("paths: expected 4 or 8");
  if (threads < 1) throw std::invalid_argument("threads: expected >= 1");
  const int D = static_cast<int>(cost.shape(0));
  const int h = static_cast<int>(cost.shape(1)), w = static_cast<int>(cost.shape(2));
  py::array_t<float> out({D, h, w});
  const float* src = cost.data();
  float* dst = out.mutable_data();
  // the penalties and the fill as torch takes them: float32
  const float fp1 = static_cast<float>(p1), fp2 = static_cast<float>(p2), ff = static_cast<float>(fill);
  const bool avx2 = !portable && cpu_has_avx2_fma();
  {
    py::gil_scoped_release release;
    if (h > 0 && w > 0) {
      if (avx2) {
        semi_global_avx2(src, D, h, w, fp1, fp2, paths, ff, threads, dst);
      } else {
        semi_global_generic(src, D, h, w, fp1, fp2, paths, ff, threads, dst);
      }
    }
  }
  return out;
}

// sweep.py's `winner_take_all`: cost (D, h, w) float32, inv (D,) float64 (1 / depth) -> depth, best,
// confidence (h, w) float32 and the winning hypothesis (h, w) int64.
py::tuple winner_take_all(Arr<float> cost, Arr<double> inv, double conf_eps, int threads, bool portable) {
  if (cost.ndim() != 3 || cost.shape(0) < 2) throw std::invalid_argument("cost: expected (D, h, w) float32, D >= 2");
  if (inv.size() != cost.shape(0)) throw std::invalid_argument("inv: expected (D,) float64");
  if (threads < 1) throw std::invalid_argument("threads: expected >= 1");
  const int D = static_cast<int>(cost.shape(0));
  const int h = static_cast<int>(cost.shape(1)), w = static_cast<int>(cost.shape(2));
  py::array_t<float> depth({h, w}), best({h, w}), conf({h, w});
  py::array_t<int64_t> winner({h, w});
  const float* src = cost.data();
  const double* iv = inv.data();
  float *dp = depth.mutable_data(), *bp = best.mutable_data(), *cp = conf.mutable_data();
  int64_t* wp = winner.mutable_data();
  const float eps = static_cast<float>(conf_eps);
  const bool avx2 = !portable && cpu_has_avx2_fma();
  {
    py::gil_scoped_release release;
    if (h > 0 && w > 0) {
      if (avx2) {
        wta_avx2(src, D, h, w, iv, eps, threads, dp, bp, cp, wp);
      } else {
        wta_generic(src, D, h, w, iv, eps, threads, dp, bp, cp, wp);
      }
    }
  }
  return py::make_tuple(depth, best, conf, winner);
}

}  // namespace

PYBIND11_MODULE(_sweep, m) {
  m.doc() = "Compiled census plane sweep of multi-view stereo (see _sweep.cpp and compiled.py).";
  py::class_<CensusSweep>(m, "CensusSweep")
      .def(py::init<Arr<float>, Arr<uint8_t>, py::list, py::list, py::list, py::list, py::list, int, double, bool>(),
           py::arg("ref_grey"), py::arg("ref_ok"), py::arg("imgs"), py::arg("a"), py::arg("b"), py::arg("ref_masks"),
           py::arg("src_masks"), py::arg("window"), py::arg("min_z"), py::arg("portable") = false,
           "The sweep of one reference: ref_grey (h, w) float32, ref_ok (h, w) uint8; per source its image "
           "(C, Hs, Ws) float32, a (3, h*w) and b (3,) float64 (the plane point d * a + b in its pixels), "
           "ref_mask (h, w) uint8 or None, src_mask (Hs, Ws) float32 or None; the census window; min_z (m); "
           "portable: the portable build even where the AVX2 / FMA one runs (the same values; for tests).")
      .def_property_readonly("sources", &CensusSweep::sources)
      .def_property_readonly("vectorised", &CensusSweep::vectorised,
                             "Whether it runs the AVX2 / FMA build (else the portable one: the same values)")
      .def("run", &CensusSweep::run, py::arg("depths"), py::arg("first"), py::arg("agg").noconvert(),
           py::arg("best").noconvert(), py::arg("arg").noconvert(), py::arg("worst").noconvert(), py::arg("threads"),
           "Sweep the hypotheses `depths` (B,) (metres; the first is hypothesis `first`): fills agg (B, h, w) "
           "and updates best, worst (n, h, w) float32 and arg (n, h, w) int64.")
      .def("warp", &CensusSweep::warp, py::arg("source"), py::arg("depth"),
           "Test hook: (grey (h, w) float32, valid (h, w) uint8) of one source warped at one depth.")
      .def("cost", &CensusSweep::cost, py::arg("source"), py::arg("depth"),
           "Test hook: the census cost (h, w) float32 of one source at one depth (NaN where unseen).");
  m.def("semi_global", &semi_global, py::arg("cost"), py::arg("p1"), py::arg("p2"), py::arg("paths"), py::arg("fill"),
        py::arg("threads"), py::arg("portable") = false,
        "sgm.py's semi_global: cost (D, h, w) float32 (NaN: unseen) -> the mean of the path costs over `paths` "
        "(4 or 8) directions, (D, h, w) float32, NaN where cost is.");
  m.def("winner_take_all", &winner_take_all, py::arg("cost"), py::arg("inv"), py::arg("conf_eps"), py::arg("threads"),
        py::arg("portable") = false,
        "sweep.py's winner_take_all: cost (D, h, w) float32, inv (D,) float64 inverse depths -> (depth, best, "
        "confidence) (h, w) float32 and the winning hypothesis (h, w) int64.");
}
