// The compiled trace core: one Embree traversal per ray over user-geometry Gaussians, with the
// exact float64 ray-ellipsoid test inside the intersect callback (see gaussian_math.py for the
// algebra, reference.py for the NumPy walk this core is tested against).
//
// Each Gaussian is one Embree user primitive whose bounds are its padded k-sigma box. Embree
// traverses in float32 (the ray starts where it enters the scene bounds, so float32 rounding
// stays below the box padding); the callback tests in float64 on the caller's ray and, in the
// hard modes, shrinks the ray's far limit to the best hit so far (plus a margin covering the
// float32 rounding), so every box that could hold a nearer hit is still visited. Soft mode keeps
// the K nearest contributions (by max-response distance, then index) in a sorted buffer and
// re-traverses past the last one until the transmittance falls below its threshold (3DGRT's
// k-buffer). Ties are broken by (t, Gaussian index), so the answer does not depend on the
// traversal order, the BVH or the thread count: the same bytes for any number of threads.
//
// Frames: everything is in the scene's local frame (world = local + origin), float64, unit
// directions; only Embree's traversal is float32.
//
// Builds against Embree 3 (Debian 12's libembree-dev) or Embree 4 (SCUBE_EMBREE4, set by setup.py
// where embree4/rtcore.h is found): they differ here only in the ray query context and in how
// rtcIntersect1 receives it.

#if defined(SCUBE_EMBREE4)
#include <embree4/rtcore.h>
#else
#include <embree3/rtcore.h>
#endif
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <limits>
#include <memory>
#include <stdexcept>
#include <string>
#include <thread>
#include <type_traits>
#include <vector>

namespace py = pybind11;

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr int kModeEntry = 0, kModeMaxResponse = 1, kModeSoft = 2;
constexpr int64_t kChunk = 512;  // rays per work item handed to a thread

template <typename T>
using Arr = py::array_t<T, py::array::c_style | py::array::forcecast>;

// The build threads of the device (0: Embree's default), set before the device exists.
int g_device_threads = 0;
bool g_device_made = false;

RTCDevice shared_device() {
  // One device per process; its TBB pool builds every scene's BVH.
  static RTCDevice device = [] {
    const std::string config = g_device_threads > 0 ? "threads=" + std::to_string(g_device_threads) : "";
    RTCDevice d = rtcNewDevice(config.empty() ? nullptr : config.c_str());
    g_device_made = true;
    if (!d) throw std::runtime_error("Embree: rtcNewDevice failed (error " +
                                     std::to_string(rtcGetDeviceError(nullptr)) + ")");
    return d;
  }();
  return device;
}

// A robust scene of one committed geometry (none: an empty scene), its BVH built with the GIL
// released; `what` names it in the error.
// A scene that releases itself (and, being a unique_ptr, cannot be copied).
struct SceneRelease {
  void operator()(RTCScene s) const { rtcReleaseScene(s); }
};
using ScenePtr = std::unique_ptr<std::remove_pointer_t<RTCScene>, SceneRelease>;

ScenePtr build_scene(RTCGeometry geom, RTCBuildQuality quality, const char* what) {
  RTCDevice dev = shared_device();
  RTCScene scene = rtcNewScene(dev);
  rtcSetSceneFlags(scene, RTC_SCENE_FLAG_ROBUST);  // no ray slips between primitives sharing a face
  rtcSetSceneBuildQuality(scene, quality);
  if (geom) {
    rtcCommitGeometry(geom);
    rtcAttachGeometry(scene, geom);
    rtcReleaseGeometry(geom);
    py::gil_scoped_release release;
    rtcCommitScene(scene);
  }
  RTCError err = rtcGetDeviceError(dev);
  if (err != RTC_ERROR_NONE) {
    rtcReleaseScene(scene);
    throw std::runtime_error(std::string("Embree: ") + what + " build failed (error " + std::to_string(err) + ")");
  }
  return ScenePtr(scene);
}

float round_down(double x) {
  float f = static_cast<float>(x);
  return static_cast<double>(f) > x ? std::nextafter(f, -std::numeric_limits<float>::infinity()) : f;
}

float round_up(double x) {
  float f = static_cast<float>(x);
  return static_cast<double>(f) < x ? std::nextafter(f, std::numeric_limits<float>::infinity()) : f;
}

struct Contribution {
  double t;  // max-response distance
  double alpha;
  double log1m;  // log(1 - alpha)
  double cum;    // log transmittance after this entry (the round's base plus the log1m so far)
  int64_t g;
};

bool key_less(double ta, int64_t ga, double tb, int64_t gb) { return ta < tb || (ta == tb && ga < gb); }

class GaussianScene;

// Doubles per Gaussian record, in traversal order (a slot): mean (3), A (9), opacity, the
// Gaussian's own index (exact in a double), 2 unused; 128 bytes, two cache lines when aligned.
constexpr int kGeo = 16;
constexpr int kOpacity = 12, kIndex = 13;

// Morton code of a point quantised to 21 bits per axis in [lo, lo + 2^21 * cell).
uint64_t spread_bits(uint64_t v) {
  v &= 0x1FFFFF;
  v = (v | v << 32) & 0x1F00000000FFFFull;
  v = (v | v << 16) & 0x1F0000FF0000FFull;
  v = (v | v << 8) & 0x100F00F00F00F00Full;
  v = (v | v << 4) & 0x10C30C30C30C30C3ull;
  v = (v | v << 2) & 0x1249249249249249ull;
  return v;
}

struct AlignedFree {
  void operator()(double* p) const { std::free(p); }
};

// transforms.quat_to_rotmat of one wxyz quaternion (normalize_quat's rules), row-major R.
void rotation(const double* q, double* R) {
  double w = q[0], x = q[1], y = q[2], z = q[3];
  double n = std::sqrt(w * w + x * x + y * y + z * z);
  if (std::isinf(n) && std::isfinite(w) && std::isfinite(x) && std::isfinite(y) && std::isfinite(z)) {
    const double m = std::max(std::max(std::abs(w), std::abs(x)), std::max(std::abs(y), std::abs(z)));
    w /= m, x /= m, y /= m, z /= m;
    n = std::sqrt(w * w + x * x + y * y + z * z);
  }
  if (!std::isfinite(n) || n < 1e-12) {
    w = 1.0, x = y = z = 0.0;
  } else {
    w /= n, x /= n, y /= n, z /= n;
  }
  const double xx = x * x, yy = y * y, zz = z * z, xy = x * y, xz = x * z, yz = y * z;
  const double wx = w * x, wy = w * y, wz = w * z;
  R[0] = 1 - 2 * (yy + zz), R[1] = 2 * (xy - wz), R[2] = 2 * (xz + wy);
  R[3] = 2 * (xy + wz), R[4] = 1 - 2 * (xx + zz), R[5] = 2 * (yz - wx);
  R[6] = 2 * (xz - wy), R[7] = 2 * (yz + wx), R[8] = 1 - 2 * (xx + yy);
}

#if defined(SCUBE_EMBREE4)
using QueryContext = RTCRayQueryContext;
#else
using QueryContext = RTCIntersectContext;
#endif

// Per-ray state, reached from the intersect callback through the context (Embree passes the
// context it was given; ours extends it).
struct RayState {
  QueryContext ctx;  // must stay first
#if defined(SCUBE_EMBREE4)
  RTCIntersectArguments args;  // points at ctx
#endif
  const GaussianScene* scene;
  double o[3], d[3];
  double t0;          // where the float32 Embree ray starts, along the float64 ray
  double tmin, tmax;  // the asked range (exact tests use it)
  double margin;      // float32 slack on the Embree ray's parameter
  int mode;
  // hard modes
  double best_t;
  int64_t best_g;
  // soft mode: the sorted k-buffer and the key the next contribution must exceed
  Contribution* buf;
  int cap, count;
  double after_t;
  int64_t after_g;
  double alpha_min;
  double log_tr_base;  // log transmittance before this round's contributions
  double log_t_min;
  bool cut;            // the buffer already ends where the transmittance falls below the threshold
  uint64_t tests;
};

// An Embree ray and an empty hit.
void set_ray(RTCRayHit& rh, float ox, float oy, float oz, float dx, float dy, float dz, float tnear, float tfar) {
  rh.ray.org_x = ox, rh.ray.org_y = oy, rh.ray.org_z = oz;
  rh.ray.dir_x = dx, rh.ray.dir_y = dy, rh.ray.dir_z = dz;
  rh.ray.tnear = tnear;
  rh.ray.tfar = tfar;
  rh.ray.time = 0.0f;
  rh.ray.mask = 0xFFFFFFFFu;
  rh.ray.id = 0;
  rh.ray.flags = 0;
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.primID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
}

// One ray through `scene` with the query context of `st`.
void intersect1(RTCScene scene, RayState& st, RTCRayHit& rh) {
#if defined(SCUBE_EMBREE4)
  rtcIntersect1(scene, &rh, &st.args);
#else
  rtcIntersect1(scene, &st.ctx, &rh);
#endif
}

class GaussianScene {
 public:
  // means (G, 3), quats (G, 4) wxyz of any norm, scales (G, 3) (positive), opacity (G,) float64;
  // k sigma; pad (m): the float32 slack of rays against the boxes. Derives, per Gaussian, what
  // the traversal reads (mean, world-to-unit-frame matrix A = S^-1 R^T, flat axis, opacity, packed
  // together) and its box padded by `pad`, with the formulas of transforms.py and
  // gaussian_math.py (a zero or non-finite quaternion is the identity).
  // alpha_min > 0 builds a scene for soft mode only: each box reaches only as far as the
  // Gaussian's response can reach alpha_min (opacity * exp(-d2 / 2) >= alpha_min, so
  // d2 <= 2 log(opacity / alpha_min), at most k^2; 3DGRT's adaptive bounds), so a faint Gaussian
  // is tested only where it can contribute. The exact tests are the same either way.
  GaussianScene(Arr<double> means, Arr<double> quats, Arr<double> scales, Arr<double> opacity, double k, double pad,
                double alpha_min, bool morton)
      : k_(k), kk_(k * k), pad_(pad), alpha_min_(alpha_min) {
    n_ = means.shape(0);
    if (means.ndim() != 2 || means.shape(1) != 3) throw std::invalid_argument("means: expected (G, 3)");
    if (quats.ndim() != 2 || quats.shape(0) != n_ || quats.shape(1) != 4)
      throw std::invalid_argument("quats: expected (G, 4)");
    if (scales.ndim() != 2 || scales.shape(0) != n_ || scales.shape(1) != 3)
      throw std::invalid_argument("scales: expected (G, 3)");
    if (opacity.ndim() != 1 || opacity.shape(0) != n_) throw std::invalid_argument("opacity: expected (G,)");
    const double *mp = means.data(), *qp = quats.data(), *sp = scales.data(), *opp = opacity.data();
    // The records are stored in Morton order of the means, so the Gaussians a ray meets one
    // after another, and the next ray's, share cache lines and pages (a trained splat file lists
    // them in no spatial order; measured in bench_tracer). Embree's primitive IDs are slots in
    // this order; everything outside the traversal speaks of a Gaussian by its own index, and
    // ties are broken by it, so the order changes no result.
    std::vector<int64_t> order(static_cast<size_t>(n_));  // slot -> Gaussian (kept in the records)
    slot_.resize(static_cast<size_t>(n_));
    {
      double mlo[3] = {kInf, kInf, kInf}, mhi[3] = {-kInf, -kInf, -kInf};
      for (int64_t i = 0; i < n_; ++i)
        for (int c = 0; c < 3; ++c)
          if (std::isfinite(mp[3 * i + c])) mlo[c] = std::min(mlo[c], mp[3 * i + c]), mhi[c] = std::max(mhi[c], mp[3 * i + c]);
      std::vector<std::pair<uint64_t, int64_t>> keyed(static_cast<size_t>(n_));
      for (int64_t i = 0; i < n_; ++i) {
        uint64_t code = 0;
        for (int c = 0; c < 3; ++c) {
          const double span = mhi[c] - mlo[c];
          const double u = span > 0 ? (mp[3 * i + c] - mlo[c]) / span : 0.0;
          const double q = std::isfinite(u) ? std::min(std::max(u, 0.0), 1.0) * 2097151.0 : 0.0;
          code |= spread_bits(static_cast<uint64_t>(q)) << c;
        }
        keyed[static_cast<size_t>(i)] = {morton ? code : 0, i};
      }
      std::sort(keyed.begin(), keyed.end());
      for (int64_t p = 0; p < n_; ++p) order[p] = keyed[p].second, slot_[keyed[p].second] = p;
    }
    geo_.reset(n_ > 0 ? static_cast<double*>(std::aligned_alloc(64, sizeof(double) * kGeo * static_cast<size_t>(n_)))
                      : nullptr);
    if (n_ > 0 && !geo_) throw std::bad_alloc();
    flat_.resize(static_cast<size_t>(n_) * 3);
    box_.resize(static_cast<size_t>(n_) * 6);
    for (int c = 0; c < 3; ++c) lo_[c] = kInf, hi_[c] = -kInf;
    for (int64_t p = 0; p < n_; ++p) {
      const int64_t i = order[p];
      double R[9];
      rotation(qp + 4 * i, R);
      const double* m = mp + 3 * i;
      const double* sc = sp + 3 * i;
      double* G = geo_.get() + kGeo * p;
      G[0] = m[0], G[1] = m[1], G[2] = m[2];
      for (int r = 0; r < 3; ++r) {
        const double inv = 1.0 / sc[r];
        for (int c = 0; c < 3; ++c) G[3 + 3 * r + c] = R[3 * c + r] * inv;  // A = S^-1 R^T
      }
      G[kOpacity] = opp[i];
      G[kIndex] = static_cast<double>(i);
      G[14] = G[15] = 0.0;
      int flat = 0;  // the first smallest scale, as numpy's argmin
      for (int c = 1; c < 3; ++c)
        if (sc[c] < sc[flat]) flat = c;
      flat_[3 * i] = R[flat], flat_[3 * i + 1] = R[3 + flat], flat_[3 * i + 2] = R[6 + flat];
      // The box reaches `reach` sigmas; the relative margin covers the rounding of log and exp
      // at the edge of the soft reach. lo_ / hi_ stay the k-sigma bounds in either case.
      double reach = k;
      if (alpha_min > 0.0) {
        const double r2 = 2.0 * std::log(opp[i] / alpha_min);
        reach = r2 < k * k ? std::sqrt(std::max(r2, 0.0)) * (1.0 + 1e-7) : k;
      }
      float* b = box_.data() + 6 * p;
      for (int r = 0; r < 3; ++r) {
        double v = 0.0;
        for (int c = 0; c < 3; ++c) v += (R[3 * r + c] * R[3 * r + c]) * (sc[c] * sc[c]);
        const double sd = std::sqrt(v), half = reach * sd, khalf = k * sd;
        b[2 * r] = round_down((m[r] - half) - pad);
        b[2 * r + 1] = round_up((m[r] + half) + pad);
        lo_[r] = std::min(lo_[r], static_cast<double>(round_down((m[r] - khalf) - pad)));
        hi_[r] = std::max(hi_[r], static_cast<double>(round_up((m[r] + khalf) + pad)));
      }
    }
    if (n_ == 0)
      for (int c = 0; c < 3; ++c) lo_[c] = hi_[c] = 0.0;
    RTCGeometry geom = nullptr;
    if (n_ > 0) {
      geom = rtcNewGeometry(shared_device(), RTC_GEOMETRY_TYPE_USER);
      rtcSetGeometryUserPrimitiveCount(geom, static_cast<unsigned>(n_));
      rtcSetGeometryUserData(geom, this);
      rtcSetGeometryBoundsFunction(geom, &GaussianScene::bounds_fn, this);
      rtcSetGeometryIntersectFunction(geom, &GaussianScene::intersect_fn);
      rtcSetGeometryOccludedFunction(geom, &GaussianScene::occluded_fn);
    }
    scene_ = build_scene(geom, RTC_BUILD_QUALITY_MEDIUM, "scene");
  }

  int64_t size() const { return n_; }

  // out = A v for a row-major 3x3 A (the unit-frame matrix of a Gaussian).
  static void apply(const double* A, const double* v, double* out) {
    out[0] = A[0] * v[0] + A[1] * v[1] + A[2] * v[2];
    out[1] = A[3] * v[0] + A[4] * v[1] + A[5] * v[2];
    out[2] = A[6] * v[0] + A[7] * v[1] + A[8] * v[2];
  }

  // The exact test of Gaussian g on ray (o, d): false when the ray misses the k-sigma ellipsoid;
  // otherwise d2 (squared Mahalanobis distance at the max-response point) and t* (the max-response
  // distance). The miss is decided without a division first, by a bound that never rejects what
  // d2 <= k^2 accepts (the rounding of either side is below 1e-15 relative); what passes is
  // computed with the formulas of gaussian_math, operation for operation.
  bool exact(int64_t p, const double* o, const double* d, double& t_star, double& d2, double& aa) const {
    const double* m = geo_.get() + kGeo * p;
    const double w[3] = {o[0] - m[0], o[1] - m[1], o[2] - m[2]};
    double op[3], dp[3];
    apply(m + 3, w, op);
    apply(m + 3, d, dp);
    const double op0 = op[0], op1 = op[1], op2 = op[2], dp0 = dp[0], dp1 = dp[1], dp2 = dp[2];
    aa = std::max(dp0 * dp0 + dp1 * dp1 + dp2 * dp2, 1e-300);
    const double c0 = op1 * dp2 - op2 * dp1, c1 = op2 * dp0 - op0 * dp2, c2 = op0 * dp1 - op1 * dp0;
    const double cc = c0 * c0 + c1 * c1 + c2 * c2;
    if (cc > kk_ * aa * (1.0 + 1e-12)) return false;
    d2 = cc / aa;
    if (!(d2 <= kk_)) return false;
    const double b = op0 * dp0 + op1 * dp1 + op2 * dp2;
    t_star = -b / aa;
    return true;
  }

  // The half chord of the k-sigma ellipsoid for a ray that passed `exact`.
  double half_chord(double d2, double aa) const { return std::sqrt(std::max(kk_ - d2, 0.0) / aa); }

  // Outward unit normal of the ellipsoid level set through p: A^T A (p - mu), normalised.
  void ellipsoid_normal(int64_t g, const double* p, double* n) const {
    const double* m = geo_.get() + kGeo * slot_[g];
    const double* A = m + 3;
    const double w[3] = {p[0] - m[0], p[1] - m[1], p[2] - m[2]};
    double u[3];
    apply(A, w, u);
    const double u0 = u[0], u1 = u[1], u2 = u[2];
    n[0] = A[0] * u0 + A[3] * u1 + A[6] * u2;
    n[1] = A[1] * u0 + A[4] * u1 + A[7] * u2;
    n[2] = A[2] * u0 + A[5] * u1 + A[8] * u2;
    const double len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    if (len > 0) {
      n[0] /= len, n[1] /= len, n[2] /= len;
    } else {
      n[0] = n[1] = n[2] = 0.0;
    }
  }

  // Starts a ray's Embree query: float32 origin at t0 along the float64 ray, far limit s_hi.
  void init_ray(RayState& st, RTCRayHit& rh, double s_near, double s_far) const {
    set_ray(rh, static_cast<float>(st.o[0] + st.t0 * st.d[0]), static_cast<float>(st.o[1] + st.t0 * st.d[1]),
            static_cast<float>(st.o[2] + st.t0 * st.d[2]), static_cast<float>(st.d[0]), static_cast<float>(st.d[1]),
            static_cast<float>(st.d[2]), std::max(0.0f, round_down(s_near)),
            std::isfinite(s_far) ? std::min(round_up(s_far), std::numeric_limits<float>::max())
                                 : std::numeric_limits<float>::infinity());
  }

  // The Embree ray's parameter that surely lies beyond the float64 ray's point at t.
  double param_beyond(const RayState& st, double t) const {
    const double s = t - st.t0;
    return s + st.margin + 4e-7 * std::abs(s);
  }

  void intersect1(RayState& st, RTCRayHit& rh) const { ::intersect1(scene_.get(), st, rh); }

  // --- one ray -----------------------------------------------------------------------------
  void trace_hard_ray(RayState& st, double t_lo, double t_hi) const {
    st.best_t = kInf;
    st.best_g = -1;
    if (!(t_hi >= t_lo) || n_ == 0) return;
    st.t0 = t_lo;
    RTCRayHit rh;
    init_ray(st, rh, 0.0, param_beyond(st, t_hi));
    intersect1(st, rh);
  }

  // Returns the number of traversals; depth / best / acc as composite_front_to_back.
  int trace_soft_ray(RayState& st, double t_lo, double t_hi, double log_t_min, int max_rounds, double& depth,
                     int64_t& best, double& acc, bool& unfinished) const {
    depth = kInf;
    best = -1;
    acc = 0.0;
    unfinished = false;
    if (!(t_hi >= t_lo) || n_ == 0) return 0;
    st.t0 = t_lo;
    st.after_t = -kInf;
    st.after_g = -1;
    double log_tr = 0.0, wsum = 0.0, wt = 0.0, best_w = 0.0;
    int rounds = 0;
    while (true) {
      if (rounds >= max_rounds) {
        unfinished = true;
        break;
      }
      ++rounds;
      st.count = 0;
      st.cut = false;
      st.log_tr_base = log_tr;
      st.log_t_min = log_t_min;
      RTCRayHit rh;
      const double s_near = std::isfinite(st.after_t) ? st.after_t - st.t0 - st.margin - 4e-7 * std::abs(st.after_t - st.t0) : 0.0;
      init_ray(st, rh, s_near, param_beyond(st, t_hi));
      intersect1(st, rh);
      bool stopped = false;
      for (int i = 0; i < st.count; ++i) {
        const Contribution& c = st.buf[i];
        if (log_tr < log_t_min) {
          stopped = true;
          break;
        }
        const double w = std::exp(log_tr) * c.alpha;
        wsum += w;
        wt += w * c.t;
        if (w > best_w) best_w = w, best = c.g;
        log_tr += c.log1m;
      }
      if (stopped || log_tr < log_t_min || st.count < st.cap) break;
      st.after_t = st.buf[st.count - 1].t;
      st.after_g = st.buf[st.count - 1].g;
    }
    if (wsum > 0) depth = wt / wsum;
    acc = wsum;
    if (!(best_w > 0)) best = -1;
    return rounds;
  }

 private:
  static void bounds_fn(const RTCBoundsFunctionArguments* args) {
    const GaussianScene* self = static_cast<const GaussianScene*>(args->geometryUserPtr);
    const float* b = self->box_.data() + 6 * static_cast<size_t>(args->primID);
    RTCBounds* out = args->bounds_o;
    out->lower_x = b[0], out->upper_x = b[1];
    out->lower_y = b[2], out->upper_y = b[3];
    out->lower_z = b[4], out->upper_z = b[5];
  }

  static void occluded_fn(const RTCOccludedFunctionNArguments* args) { (void)args; }

  static void intersect_fn(const RTCIntersectFunctionNArguments* args) {
    if (!args->valid[0]) return;
    RayState& st = *reinterpret_cast<RayState*>(args->context);
    const GaussianScene& s = *st.scene;
    const int64_t slot = args->primID;
    RTCRayHit* rh = reinterpret_cast<RTCRayHit*>(args->rayhit);
    double t_star, d2, aa;
    ++st.tests;
    if (!s.exact(slot, st.o, st.d, t_star, d2, aa)) return;
    const double* rec = s.geo_.get() + kGeo * slot;
    const int64_t g = static_cast<int64_t>(rec[kIndex]);
    if (st.mode == kModeSoft) {
      s.add_contribution(st, rh, g, rec[kOpacity], t_star, d2);
      return;
    }
    double t_hit;
    if (st.mode == kModeEntry) {
      const double half = s.half_chord(d2, aa);
      const double t_in = t_star - half, t_out = t_star + half;
      if (!(t_out >= st.tmin && t_in <= st.tmax)) return;
      t_hit = std::max(t_in, st.tmin);  // a ray starting inside hits at once
    } else {
      if (!(t_star >= st.tmin && t_star <= st.tmax)) return;
      t_hit = t_star;
    }
    if (!key_less(t_hit, g, st.best_t, st.best_g)) return;
    st.best_t = t_hit;
    st.best_g = g;
    const float far = round_up(s.param_beyond(st, t_hit));
    if (far < rh->ray.tfar) rh->ray.tfar = far;
    rh->hit.geomID = args->geomID;
    rh->hit.primID = args->primID;
  }

  void add_contribution(RayState& st, RTCRayHit* rh, int64_t g, double opacity, double t_star, double d2) const {
    if (!(t_star >= st.tmin && t_star <= st.tmax)) return;
    const double alpha = opacity * std::exp(-0.5 * d2);
    if (!(alpha >= st.alpha_min)) return;
    if (!key_less(st.after_t, st.after_g, t_star, g)) return;  // composited in an earlier round
    Contribution* buf = st.buf;
    int n = st.count;
    if ((st.cut || n == st.cap) && !key_less(t_star, g, buf[n - 1].t, buf[n - 1].g)) return;
    int pos = n;
    while (pos > 0 && key_less(t_star, g, buf[pos - 1].t, buf[pos - 1].g)) --pos;
    if (pos > 0 && buf[pos - 1].g == g && buf[pos - 1].t == t_star) return;  // visited twice
    const int last = std::min(n, st.cap - 1);
    for (int i = last; i > pos; --i) buf[i] = buf[i - 1];
    const double a = std::min(alpha, 0.999);
    buf[pos] = Contribution{t_star, a, std::log1p(-a), 0.0, g};
    if (n < st.cap) st.count = n + 1;
    // Early termination inside the traversal: once the buffer's transmittance falls below the
    // threshold at entry j, nothing beyond j is composited (a nearer contribution found later
    // only moves that point nearer), so the buffer ends at j and the ray's far limit with it.
    // The running sums before `pos` are unchanged (and all above the threshold, or the buffer
    // would end there), so they are summed on from `pos`, in the same order as from the start.
    double log_tr = pos > 0 ? buf[pos - 1].cum : st.log_tr_base;
    for (int i = pos; i < st.count; ++i) {
      log_tr += buf[i].log1m;
      buf[i].cum = log_tr;
      if (log_tr < st.log_t_min) {
        st.count = i + 1;
        st.cut = true;
        break;
      }
    }
    if (st.cut || st.count == st.cap) {
      // Only contributions nearer than the last can still enter the buffer this round.
      const float far = round_up(param_beyond(st, buf[st.count - 1].t));
      if (far < rh->ray.tfar) rh->ray.tfar = far;
    }
  }

  std::unique_ptr<double[], AlignedFree> geo_;  // (G, kGeo) records by slot (kGeo's comment)
  std::vector<int64_t> slot_;                    // Gaussian -> slot
  std::vector<double> flat_;                     // (G, 3) flat axis by Gaussian
  double lo_[3], hi_[3];     // the boxes' bounds
  std::vector<float> box_;  // (G, 3, 2): lo, hi per axis, rounded outwards to float32
  double k_, kk_, pad_, alpha_min_;
  int64_t n_ = 0;
  ScenePtr scene_;

 public:
  double pad() const { return pad_; }
  double alpha_min() const { return alpha_min_; }
  const double* flat_axis(int64_t g) const { return flat_.data() + 3 * g; }
  py::tuple bounds() const {
    return py::make_tuple(py::make_tuple(lo_[0], lo_[1], lo_[2]), py::make_tuple(hi_[0], hi_[1], hi_[2]));
  }
};

void init_context(RayState& st) {
#if defined(SCUBE_EMBREE4)
  rtcInitRayQueryContext(&st.ctx);
  rtcInitIntersectArguments(&st.args);
  st.args.context = &st.ctx;
#else
  rtcInitIntersectContext(&st.ctx);
#endif
}

// Runs fn(first, last, thread) over [0, n) in chunks of `chunk` on `threads` std::threads; each
// chunk's items are independent, so the result does not depend on which thread ran which chunk.
template <typename Fn>
void parallel_chunks(int64_t n, int64_t chunk, int threads, Fn fn) {
  const int64_t chunks = (n + chunk - 1) / chunk;
  const int nt = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(threads, chunks)));
  std::atomic<int64_t> next{0};
  std::vector<std::exception_ptr> errors(nt);
  auto work = [&](int tid) {
    try {
      for (int64_t c = next++; c < chunks; c = next++) {
        const int64_t lo = c * chunk, hi = std::min(n, lo + chunk);
        fn(lo, hi, tid);
      }
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

// The rays in chunks of kChunk (`parallel_chunks`).
template <typename Fn>
void parallel_rays(int64_t n, int threads, Fn fn) {
  parallel_chunks(n, kChunk, threads, fn);
}

int resolve_threads(int threads) {
  if (threads > 0) return threads;
  const unsigned hc = std::thread::hardware_concurrency();
  return hc ? static_cast<int>(hc) : 1;
}

void check_rays(const Arr<double>& o, const Arr<double>& d, const Arr<double>& tmin, const Arr<double>& tmax,
                const Arr<double>& lo, const Arr<double>& hi) {
  const auto n = o.shape(0);
  if (o.ndim() != 2 || o.shape(1) != 3 || d.ndim() != 2 || d.shape(0) != n || d.shape(1) != 3)
    throw std::invalid_argument("o, d: expected (N, 3) float64");
  for (const Arr<double>* x : {&tmin, &tmax})
    if (x->ndim() != 1 || x->shape(0) != n) throw std::invalid_argument("tmin, tmax: expected (N,)");
  for (const Arr<double>* x : {&lo, &hi})
    if (x->ndim() != 1 || x->shape(0) != 3) throw std::invalid_argument("lo, hi: expected (3,)");
}

// The part [t_lo, t_hi] of [tmin, tmax] inside the box lo, hi; as gaussian_math.clip_to_box,
// operation for operation: a 0 * inf (a ray in a slab's plane) is NaN and means "inside".
void clip_to_box(const double* o, const double* d, double tmin, double tmax, const double* lo, const double* hi,
                 double& t_lo, double& t_hi) {
  double near = kNaN, far = kNaN;
  for (int c = 0; c < 3; ++c) {
    const double inv = 1.0 / d[c];
    const double t1 = (lo[c] - o[c]) * inv, t2 = (hi[c] - o[c]) * inv;
    const bool nan = std::isnan(t1) || std::isnan(t2);
    near = std::fmax(near, nan ? kNaN : std::min(t1, t2));
    far = std::fmin(far, nan ? kNaN : std::max(t1, t2));
  }
  t_lo = std::isnan(near) ? near : std::max(tmin, near);
  t_hi = std::isnan(far) ? far : std::min(tmax, far);
}

struct Outputs {
  // The per-ray fields of `Hits` that a Gaussian hit fills (arrays allocated by the caller).
  bool* hit;
  double* t;
  double* points;
  float* normals;
  int64_t* gaussian;
  int64_t* voxel;
  int16_t* label;
  float* color;
  float* alpha;
};

struct Attributes {
  // Per-Gaussian attributes copied into the hits: voxel (G,) int64, label (G,) int16, colour
  // (G, 3) float32.
  const int64_t* voxel;
  const int16_t* label;
  const float* color;
};

void fill_hit(const GaussianScene& s, const Attributes& at, const Outputs& out, int64_t i, const double* o,
              const double* d, double t, int64_t g, bool entry_normal, float alpha) {
  out.hit[i] = true;
  out.t[i] = t;
  double p[3] = {o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]};
  out.points[3 * i] = p[0], out.points[3 * i + 1] = p[1], out.points[3 * i + 2] = p[2];
  double nrm[3];
  if (entry_normal) {
    s.ellipsoid_normal(g, p, nrm);
  } else {
    const double* fa = s.flat_axis(g);
    nrm[0] = fa[0], nrm[1] = fa[1], nrm[2] = fa[2];
  }
  if (nrm[0] * d[0] + nrm[1] * d[1] + nrm[2] * d[2] > 0) nrm[0] = -nrm[0], nrm[1] = -nrm[1], nrm[2] = -nrm[2];
  for (int c = 0; c < 3; ++c) {
    out.normals[3 * i + c] = static_cast<float>(nrm[c]);
    out.color[3 * i + c] = at.color[3 * g + c];
  }
  out.gaussian[i] = g;
  out.voxel[i] = at.voxel[g];
  out.label[i] = at.label[g];
  out.alpha[i] = alpha;
}

// A miss, as `Hits.empty` writes it.
void fill_miss(const Outputs& out, int64_t i, float alpha) {
  out.hit[i] = false;
  out.t[i] = kInf;
  for (int c = 0; c < 3; ++c) {
    out.points[3 * i + c] = kNaN;
    out.normals[3 * i + c] = 0.0f;
    out.color[3 * i + c] = 0.0f;
  }
  out.gaussian[i] = -1;
  out.voxel[i] = -1;
  out.label[i] = 0;
  out.alpha[i] = alpha;
}

template <typename T>
T* mutable_data(py::array_t<T, py::array::c_style>& a, int64_t n, int64_t width, const char* name) {
  const bool ok = width == 1 ? (a.ndim() == 1 && a.shape(0) == n) : (a.ndim() == 2 && a.shape(0) == n && a.shape(1) == width);
  if (!ok) throw std::invalid_argument(std::string(name) + ": output array of the wrong shape");
  return a.mutable_data();
}

// trace(scene, mode, o, d, tmin, tmax, box lo, hi, attributes..., outputs..., options) -> stats;
// every output element is written, misses included.
py::tuple trace(const GaussianScene& s, int mode, Arr<double> o, Arr<double> d, Arr<double> tmin, Arr<double> tmax,
                Arr<double> lo, Arr<double> hi, Arr<int64_t> voxel, Arr<int16_t> label,
                Arr<float> color, py::array_t<bool, py::array::c_style> hit, py::array_t<double, py::array::c_style> t,
                py::array_t<double, py::array::c_style> points, py::array_t<float, py::array::c_style> normals,
                py::array_t<int64_t, py::array::c_style> gaussian, py::array_t<int64_t, py::array::c_style> vox_out,
                py::array_t<int16_t, py::array::c_style> label_out, py::array_t<float, py::array::c_style> color_out,
                py::array_t<float, py::array::c_style> alpha_out, double soft_min_transmittance,
                double soft_alpha_min, double soft_hit_alpha, int k_buffer, int max_rounds, int threads) {
  if (mode < kModeEntry || mode > kModeSoft) throw std::invalid_argument("mode: expected 0 (entry), 1 (max_response) or 2 (soft)");
  if (k_buffer < 1) throw std::invalid_argument("k_buffer: expected at least 1");
  check_rays(o, d, tmin, tmax, lo, hi);
  if (s.alpha_min() > 0.0 && (mode != kModeSoft || soft_alpha_min < s.alpha_min()))
    throw std::invalid_argument("this scene's boxes end at alpha_min " + std::to_string(s.alpha_min()) +
                                ": it answers soft mode with soft_alpha_min >= that only");
  const int64_t n = o.shape(0), G = s.size();
  if (voxel.shape(0) != G || label.shape(0) != G || color.shape(0) != G)
    throw std::invalid_argument("attributes: expected one row per Gaussian");
  Outputs out{mutable_data(hit, n, 1, "hit"),           mutable_data(t, n, 1, "t"),
              mutable_data(points, n, 3, "points"),     mutable_data(normals, n, 3, "normals"),
              mutable_data(gaussian, n, 1, "gaussian"), mutable_data(vox_out, n, 1, "voxel"),
              mutable_data(label_out, n, 1, "label"),   mutable_data(color_out, n, 3, "color"),
              mutable_data(alpha_out, n, 1, "alpha")};
  Attributes at{voxel.data(), label.data(), color.data()};
  const double *op = o.data(), *dp = d.data(), *tminp = tmin.data(), *tmaxp = tmax.data(), *box_lo = lo.data(),
               *box_hi = hi.data();
  const int nt = resolve_threads(threads);
  std::vector<uint64_t> tests(nt, 0), rounds(nt, 0), unfinished(nt, 0);
  const double log_t_min = std::log(soft_min_transmittance);
  {
    py::gil_scoped_release release;
    parallel_rays(n, nt, [&](int64_t lo, int64_t hi, int tid) {
      RayState st;
      init_context(st);
      st.scene = &s;
      st.mode = mode;
      st.margin = 2.0 * s.pad();
      st.alpha_min = soft_alpha_min;
      st.tests = 0;
      std::vector<Contribution> buf(static_cast<size_t>(k_buffer));
      st.buf = buf.data();
      st.cap = k_buffer;
      uint64_t casts = 0, unf = 0;
      for (int64_t i = lo; i < hi; ++i) {
        for (int c = 0; c < 3; ++c) st.o[c] = op[3 * i + c], st.d[c] = dp[3 * i + c];
        st.tmin = tminp[i];
        st.tmax = tmaxp[i];
        // Candidates are searched only inside the bounds; the exact tests use the whole range.
        double t_lo, t_hi;
        clip_to_box(st.o, st.d, st.tmin, st.tmax, box_lo, box_hi, t_lo, t_hi);
        if (mode == kModeSoft) {
          double depth, acc;
          int64_t g;
          bool unfinished_ray;
          casts += s.trace_soft_ray(st, t_lo, t_hi, log_t_min, max_rounds, depth, g, acc, unfinished_ray);
          unf += unfinished_ray;
          if (acc >= soft_hit_alpha && g >= 0) {
            fill_hit(s, at, out, i, st.o, st.d, depth, g, false, static_cast<float>(acc));
          } else {
            fill_miss(out, i, 0.0f);
          }
        } else {
          s.trace_hard_ray(st, t_lo, t_hi);
          casts += t_hi >= t_lo && G > 0;
          if (st.best_g >= 0) {
            fill_hit(s, at, out, i, st.o, st.d, st.best_t, st.best_g, mode == kModeEntry, 1.0f);
          } else {
            fill_miss(out, i, 0.0f);
          }
        }
      }
      tests[tid] += st.tests;
      rounds[tid] += casts;
      unfinished[tid] += unf;
    });
  }
  uint64_t total_tests = 0, total_rounds = 0, total_unfinished = 0;
  for (int i = 0; i < nt; ++i) total_tests += tests[i], total_rounds += rounds[i], total_unfinished += unfinished[i];
  return py::make_tuple(total_rounds, total_tests, total_unfinished);
}

// Triangle meshes (worlds, actors) on the same Embree device and threads: first hit per float32
// ray up to its far limit, traversed in Embree's float32 (the caller refines in float64).
class MeshScene {
 public:
  // vertices (V, 3) float32, faces (F, 3) int64 indices into them; local frame.
  MeshScene(Arr<float> vertices, Arr<int64_t> faces) {
    if (vertices.ndim() != 2 || vertices.shape(1) != 3) throw std::invalid_argument("vertices: expected (V, 3)");
    if (faces.ndim() != 2 || faces.shape(1) != 3) throw std::invalid_argument("faces: expected (F, 3)");
    const int64_t nv = vertices.shape(0);
    nf_ = faces.shape(0);
    const int64_t* fp = faces.data();
    for (int64_t i = 0; i < 3 * nf_; ++i)
      if (fp[i] < 0 || fp[i] >= nv) throw std::invalid_argument("faces: an index outside the vertices");
    RTCGeometry geom = nullptr;
    if (nf_ > 0) {
      geom = rtcNewGeometry(shared_device(), RTC_GEOMETRY_TYPE_TRIANGLE);
      float* vb = static_cast<float*>(rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                                             3 * sizeof(float), static_cast<size_t>(nv)));
      unsigned* ib = static_cast<unsigned*>(rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                                                   3 * sizeof(unsigned), static_cast<size_t>(nf_)));
      if (!vb || !ib) {
        rtcReleaseGeometry(geom);
        throw std::runtime_error("Embree: could not allocate the mesh buffers");
      }
      std::copy(vertices.data(), vertices.data() + 3 * nv, vb);
      for (int64_t i = 0; i < 3 * nf_; ++i) ib[i] = static_cast<unsigned>(fp[i]);
    }
    // A high-quality BVH (spatial splits) for meshes, which are small beside the Gaussian scenes:
    // faster sweeps, measured.
    scene_ = build_scene(geom, RTC_BUILD_QUALITY_HIGH, "mesh");
  }

  int64_t size() const { return nf_; }

  // o, d (N, 3) float32, far (N,) float32 -> t (N,) float32 (inf on a miss), prim (N,) int64 (-1).
  void first_hit(Arr<float> o, Arr<float> d, Arr<float> far, py::array_t<float, py::array::c_style> t_out,
                 py::array_t<int64_t, py::array::c_style> prim_out, int threads) const {
    const int64_t n = o.shape(0);
    if (o.ndim() != 2 || o.shape(1) != 3 || d.ndim() != 2 || d.shape(0) != n || d.shape(1) != 3)
      throw std::invalid_argument("o, d: expected (N, 3) float32");
    if (far.ndim() != 1 || far.shape(0) != n) throw std::invalid_argument("far: expected (N,)");
    float* t = mutable_data(t_out, n, 1, "t");
    int64_t* prim = mutable_data(prim_out, n, 1, "prim");
    const float *op = o.data(), *dp = d.data(), *fp = far.data();
    py::gil_scoped_release release;
    parallel_rays(n, resolve_threads(threads), [&](int64_t lo, int64_t hi, int) {
      RayState st;  // only its query context is used
      init_context(st);
      for (int64_t i = lo; i < hi; ++i) {
        t[i] = std::numeric_limits<float>::infinity();
        prim[i] = -1;
        if (nf_ == 0) continue;
        RTCRayHit rh;
        set_ray(rh, op[3 * i], op[3 * i + 1], op[3 * i + 2], dp[3 * i], dp[3 * i + 1], dp[3 * i + 2], 0.0f,
                std::min(fp[i], std::numeric_limits<float>::max()));
        if (!(rh.ray.tfar >= 0.0f)) continue;
        intersect1(scene_.get(), st, rh);
        if (rh.hit.geomID != RTC_INVALID_GEOMETRY_ID) {
          t[i] = rh.ray.tfar;
          prim[i] = rh.hit.primID;
        }
      }
    });
  }

 private:
  int64_t nf_ = 0;
  ScenePtr scene_;
};


// --- sparse voxel grids: the first voxel each ray enters ----------------------------------------
// model/voxel_rays.py's traversal (its docstring: a Chebyshev distance field on 8^3 blocks skips
// empty space, voxel steps next to occupied blocks, a binary search of the packed keys), written
// here operation for operation in float64 so that both give the same voxel and t for every ray
// (tests/model/test_voxel_rays.py). NaN propagates through min / max as torch's does.

constexpr int64_t kVoxelBlock = 8;
constexpr double kVoxelEps = 1e-6;  // voxel units: past a face into the next voxel

double nan_min(double a, double b) { return (std::isnan(a) || std::isnan(b)) ? kNaN : std::min(a, b); }
double nan_max(double a, double b) { return (std::isnan(a) || std::isnan(b)) ? kNaN : std::max(a, b); }

// floor(x) as torch's float64 -> int64 conversion gives it on x86 (out of range or NaN: INT64_MIN).
int64_t floor_to_int(double x) {
  const double f = std::floor(x);
  return (f >= -9.2233720368547758e18 && f < 9.2233720368547758e18) ? static_cast<int64_t>(f)
                                                                       : std::numeric_limits<int64_t>::min();
}

// o, d (R, 3) float64 in the grid's frame; origin (3,) float64 (voxel (0,0,0)'s corner, metres);
// lo, dims (3,) int64: the occupied voxels' lowest index and the extent from it; keys (K,) int64
// sorted packed keys of (ijk - lo), order (K,) int64 the voxel row of each; dist (Bx, By, Bz)
// int64 block distances; fills index (R,) int64 (-1: none within max_t) and t (R,) float64.
void voxel_first_hit(Arr<double> o, Arr<double> d, Arr<double> origin, double voxel_size, Arr<int64_t> lo,
                     Arr<int64_t> dims, Arr<int64_t> keys, Arr<int64_t> order, Arr<int64_t> dist, double max_t,
                     py::array_t<int64_t, py::array::c_style> index_out, py::array_t<double, py::array::c_style> t_out,
                     int threads) {
  const int64_t n = o.shape(0);
  if (o.ndim() != 2 || o.shape(1) != 3 || d.ndim() != 2 || d.shape(0) != n || d.shape(1) != 3)
    throw std::invalid_argument("o, d: expected (R, 3) float64");
  for (const Arr<int64_t>* x : {&lo, &dims})
    if (x->ndim() != 1 || x->shape(0) != 3) throw std::invalid_argument("lo, dims: expected (3,)");
  if (origin.ndim() != 1 || origin.shape(0) != 3) throw std::invalid_argument("origin: expected (3,)");
  const int64_t nk = keys.shape(0);
  if (keys.ndim() != 1 || order.ndim() != 1 || order.shape(0) != nk || nk == 0)
    throw std::invalid_argument("keys, order: expected (K,) each, K > 0");
  const int64_t *dm = dims.data(), *lp = lo.data();
  int64_t nb[3];
  for (int c = 0; c < 3; ++c) nb[c] = (dm[c] + kVoxelBlock - 1) / kVoxelBlock;
  if (dist.ndim() != 3 || dist.shape(0) != nb[0] || dist.shape(1) != nb[1] || dist.shape(2) != nb[2])
    throw std::invalid_argument("dist: expected one entry per 8^3 block of dims");
  int64_t* index = mutable_data(index_out, n, 1, "index");
  double* tp = mutable_data(t_out, n, 1, "t");
  const double *op = o.data(), *dp = d.data(), *org = origin.data();
  const int64_t *kp = keys.data(), *ordp = order.data(), *distp = dist.data();
  py::gil_scoped_release release;
  parallel_rays(n, resolve_threads(threads), [&](int64_t first, int64_t last, int) {
    for (int64_t i = first; i < last; ++i) {
      index[i] = -1;
      tp[i] = kInf;
      double p0[3], dv[3], inv[3], step[3];
      double vmax = kNaN, t_enter = kNaN, t_exit = kNaN;
      for (int c = 0; c < 3; ++c) {
        p0[c] = (op[3 * i + c] - org[c]) / voxel_size - static_cast<double>(lp[c]);
        dv[c] = dp[3 * i + c] / voxel_size;
        inv[c] = 1.0 / (dv[c] == 0 ? 1e-300 : dv[c]);
        step[c] = dv[c] > 0 ? 1.0 : 0.0;
        const double ta = (0.0 - p0[c]) * inv[c], tb = (static_cast<double>(dm[c]) - p0[c]) * inv[c];
        vmax = c == 0 ? std::abs(dv[c]) : nan_max(vmax, std::abs(dv[c]));
        t_enter = c == 0 ? nan_min(ta, tb) : nan_max(t_enter, nan_min(ta, tb));
        t_exit = c == 0 ? nan_max(ta, tb) : nan_min(t_exit, nan_max(ta, tb));
      }
      const double per_voxel = 1.0 / nan_max(vmax, 1e-300);
      t_enter = nan_max(t_enter, 0.0);
      t_exit = nan_min(t_exit, max_t);
      if (!(t_enter < t_exit)) continue;
      double t = t_enter;
      while (true) {
        double p[3];
        int64_t cell[3];
        for (int c = 0; c < 3; ++c) {
          p[c] = p0[c] + t * dv[c];
          cell[c] = std::min(std::max(floor_to_int(p[c]), int64_t{0}), dm[c] - 1);
        }
        const int64_t bd = distp[((cell[0] / kVoxelBlock) * nb[1] + cell[1] / kVoxelBlock) * nb[2] + cell[2] / kVoxelBlock];
        const bool near = bd <= 1;
        if (near) {
          const int64_t key = (cell[0] * dm[1] + cell[1]) * dm[2] + cell[2];
          const int64_t pos = std::min<int64_t>(std::lower_bound(kp, kp + nk, key) - kp, nk - 1);
          if (kp[pos] == key) {
            index[i] = ordp[pos];
            double te = kNaN;
            for (int c = 0; c < 3; ++c) {
              const double cf = static_cast<double>(cell[c]);
              const double a0 = (cf - p0[c]) * inv[c], a1 = (cf + 1 - p0[c]) * inv[c];
              te = c == 0 ? nan_min(a0, a1) : nan_max(te, nan_min(a0, a1));
            }
            tp[i] = nan_max(te, 0.0);
            break;
          }
        }
        double t_next;
        if (near) {
          double t_face = kNaN;
          for (int c = 0; c < 3; ++c) {
            const double f = std::abs((static_cast<double>(cell[c]) + step[c] - p[c]) * inv[c]);
            t_face = c == 0 ? f : nan_min(t_face, f);
          }
          t_next = t + t_face + kVoxelEps * per_voxel;
        } else {
          t_next = t + static_cast<double>(std::max<int64_t>(bd - 1, 0)) * kVoxelBlock * per_voxel;
        }
        if (!(t_next < t_exit)) break;
        t = t_next;
      }
    }
  });
}

// The fusion's carving walk (model/geometry/fusion.py `_misses`, its NumPy reference): each ray
// o + t d, d (R, 3) float64 unit, sampled at t = (s + 0.5) step while t < reach (R,); a sample's
// voxel floor((p - origin) / voxel_size), a run of samples in one voxel counted once; a voxel found
// in `candidates` (K,) sorted keys (voxsplat.voxel_keys' packing) takes the ray's conf (R,). Rays
// go in batches of `batch` (the reference's chunk_rays): per batch each voxel's confidences are
// summed in ray order, and the batches' sums added to conf_sum (K,) in batch order, the NumPy
// walk's order of float additions, so the bytes are its and the same for any thread count.
// conf_cnt (K,) float64 counts the rays, hit (K,) is set where any did. Returns false where a
// sample's voxel index reached +-2^20 (the reference refuses such grids).
bool carve_misses(Arr<double> oc, Arr<double> d, Arr<double> reach, Arr<double> conf, Arr<double> origin,
                  double voxel_size, double step, int64_t batch, Arr<int64_t> candidates,
                  py::array_t<double, py::array::c_style> conf_sum_out,
                  py::array_t<double, py::array::c_style> conf_cnt_out,
                  py::array_t<bool, py::array::c_style> hit_out, int threads) {
  const int64_t n = d.shape(0), nk = candidates.shape(0);
  if (d.ndim() != 2 || d.shape(1) != 3) throw std::invalid_argument("d: expected (R, 3) float64");
  if (reach.ndim() != 1 || reach.shape(0) != n || conf.ndim() != 1 || conf.shape(0) != n)
    throw std::invalid_argument("reach, conf: expected (R,) each");
  if (oc.ndim() != 1 || oc.shape(0) != 3 || origin.ndim() != 1 || origin.shape(0) != 3)
    throw std::invalid_argument("oc, origin: expected (3,)");
  if (candidates.ndim() != 1 || batch < 1 || !(step > 0) || !(voxel_size > 0))
    throw std::invalid_argument("candidates (K,), batch >= 1, step > 0, voxel_size > 0 expected");
  double* conf_sum = mutable_data(conf_sum_out, nk, 1, "conf_sum");
  double* conf_cnt = mutable_data(conf_cnt_out, nk, 1, "conf_cnt");
  bool* hit = mutable_data(hit_out, nk, 1, "hit");
  const double *o = oc.data(), *dp = d.data(), *rp = reach.data(), *cp = conf.data(), *org = origin.data();
  const int64_t* kp = candidates.data();
  const int64_t batches = (n + batch - 1) / batch;
  struct Entry { int64_t slot; double sum; int64_t count; };
  std::vector<std::vector<Entry>> per_batch(batches);
  std::atomic<bool> in_range{true};
  const int nt = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(resolve_threads(threads), batches)));
  std::vector<std::vector<double>> sums(nt);  // per thread, per candidate: the batch's running sums ...
  std::vector<std::vector<int64_t>> counts(nt);  // ... and ray counts, zero between batches
  constexpr int64_t kBias = int64_t{1} << 20;
  {
    py::gil_scoped_release release;
    parallel_chunks(n, batch, nt, [&](int64_t lo, int64_t hi, int tid) {
      std::vector<double>& sum = sums[tid];
      std::vector<int64_t>& count = counts[tid];
      if (sum.empty()) {
        sum.assign(nk, 0.0);
        count.assign(nk, 0);
      }
      std::vector<int64_t> touched;
      double most = rp[lo];
      for (int64_t i = lo + 1; i < hi; ++i) most = std::max(most, rp[i]);
      const double steps = std::ceil(most / step);
      const int64_t n_steps = steps > 0 ? static_cast<int64_t>(steps) : 0;
      for (int64_t i = lo; i < hi; ++i) {
        int64_t prev = -1;
        for (int64_t s = 0; s < n_steps; ++s) {
          const double t = (static_cast<double>(s) + 0.5) * step;
          if (!(t < rp[i])) break;
          int64_t key = 0;
          for (int c = 0; c < 3; ++c) {
            const double x = std::floor(((o[c] + dp[3 * i + c] * t) - org[c]) / voxel_size);
            if (!(std::abs(x) < static_cast<double>(kBias))) {
              in_range = false;
              key = -1;
              break;
            }
            key = (key << 21) | (static_cast<int64_t>(x) + kBias);
          }
          if (key < 0 || key == prev) continue;
          prev = key;
          const int64_t pos = std::lower_bound(kp, kp + nk, key) - kp;
          if (pos == nk || kp[pos] != key) continue;
          if (count[pos] == 0) touched.push_back(pos);
          sum[pos] += cp[i];
          ++count[pos];
        }
      }
      std::vector<Entry>& out = per_batch[lo / batch];
      out.reserve(touched.size());
      for (int64_t k : touched) {
        out.push_back({k, sum[k], count[k]});
        sum[k] = 0.0;
        count[k] = 0;
      }
    });
    for (const auto& entries : per_batch)
      for (const Entry& e : entries) {
        conf_sum[e.slot] += e.sum;
        conf_cnt[e.slot] += static_cast<double>(e.count);
        hit[e.slot] = true;
      }
  }
  return in_range.load();
}

}  // namespace

PYBIND11_MODULE(_core, m) {
  m.doc() = "Compiled trace core: Embree user-geometry Gaussians with exact float64 tests (see _core.cpp).";
  m.attr("EMBREE_VERSION") = RTC_VERSION_STRING;
  py::class_<GaussianScene>(m, "GaussianScene")
      .def(py::init<Arr<double>, Arr<double>, Arr<double>, Arr<double>, double, double, double, bool>(),
           py::arg("means"), py::arg("quats"), py::arg("scales"), py::arg("opacity"), py::arg("k"), py::arg("pad"),
           py::arg("alpha_min") = 0.0, py::arg("morton") = true,
           "Build the BVH of G Gaussians: means (G, 3), quats (G, 4) wxyz, scales (G, 3) > 0, opacity (G,) "
           "float64 (local frame, metres); k sigma; pad (m) the float32 slack of rays against the boxes; "
           "alpha_min > 0: a soft-mode-only scene whose boxes end where the response falls below it; "
           "morton: store the Gaussians in Morton order of their means (False: as given; for benchmarks).")
      .def_property_readonly("alpha_min", &GaussianScene::alpha_min)
      .def_property_readonly("size", &GaussianScene::size)
      .def("bounds", &GaussianScene::bounds, "((3,), (3,)): the padded boxes' lower and upper corners");
  py::class_<MeshScene>(m, "MeshScene")
      .def(py::init<Arr<float>, Arr<int64_t>>(), py::arg("vertices"), py::arg("faces"),
           "Build the BVH of a triangle mesh: vertices (V, 3) float32, faces (F, 3) int64 (local frame).")
      .def_property_readonly("size", &MeshScene::size)
      .def("first_hit", &MeshScene::first_hit, py::arg("o"), py::arg("d"), py::arg("far"), py::arg("t"),
           py::arg("prim"), py::arg("threads") = 0,
           "First hit per ray: o, d (N, 3), far (N,) float32; fills t (N,) float32 (inf: miss) and prim (N,) int64.");
  m.def("set_device_threads", [](int threads) {
    if (g_device_made) return false;
    g_device_threads = std::max(0, threads);
    return true;
  }, py::arg("threads"),
        "The BVH build threads of the process's Embree device; False once the device exists (then unchanged).");
  m.def("trace", &trace, "Trace rays; fills the output arrays; returns (traversals, exact tests, unfinished rays).");
  m.def("voxel_first_hit", &voxel_first_hit, py::arg("o"), py::arg("d"), py::arg("origin"), py::arg("voxel_size"),
        py::arg("lo"), py::arg("dims"), py::arg("keys"), py::arg("order"), py::arg("dist"), py::arg("max_t"),
        py::arg("index"), py::arg("t"), py::arg("threads") = 0,
        "The first voxel each ray enters in a sparse grid (model/voxel_rays.py's traversal); fills index and t.");
  m.def("carve_misses", &carve_misses, py::arg("oc"), py::arg("d"), py::arg("reach"), py::arg("conf"),
        py::arg("origin"), py::arg("voxel_size"), py::arg("step"), py::arg("batch"), py::arg("candidates"),
        py::arg("conf_sum"), py::arg("conf_cnt"), py::arg("hit"), py::arg("threads") = 0,
        "The fusion's carving walk (model/geometry/fusion.py's _misses): sums each candidate voxel's misses.");
}
