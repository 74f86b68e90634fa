// The affinity kernels of Işık et al. 2021 (eq. 4, 6, 7, 8) shared by AffinityFilter and
// AffinityTemporalFilter, exactly as quietframe.model.affinity_kernels (docs/affinity-math.md):
//
//   w_pq = c_p if q = p, else exp(-a_p ||f_p - f_q||²)      q = p + dilation·(i, j), |i|,|j| <= r
//   ω_pq' = on_n · exp(-b_p ||f_p - Wf_q'||²)                q' = p + (i, j), |i|,|j| <= r_t
//   out_p = (Σ_q w_pq L_q + Σ_q' ω_pq' WO_q') / (ε + Σ_q w_pq + Σ_q' ω_pq')
//
// with neighbours outside the image skipped, a, b, c, on below 0 or NaN counted as 0, a weight
// whose exponent a·d² is NaN or >= kExpCutoff counted as 0, and the result mapped like
// torch.nan_to_num (NaN -> 0, ±Inf -> ±FLT_MAX). The sums run in the reference's order: the
// centre, the spatial offsets row by row, then the temporal ones.
//
// A pixel's result depends only on its own neighbourhood and on which loop (AVX2 or scalar)
// handles its column, never on the bands: results are bitwise independent of the thread count.
// The AVX2 loop handles 8 pixels of a row at once (NCHW planes make 8 neighbours at the same
// offset one load), masking lanes whose neighbour falls off the left or right edge.
#pragma once

#include <algorithm>
#include <cfloat>
#include <climits>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <string>

#include "kernel_support.h"
#include "runtime_support.h"
#include "simd.h"

namespace qf::affinity {

constexpr int64_t kMaxKernelSize = 31;
constexpr int64_t kMaxDilation = 65536;
constexpr float kDefaultEpsilon = 1e-10f;  // ε of eq. 6 and 8
// exp(-t) for t >= 87 is below 1.7e-38, at the bottom of the normal floats: such a weight counts
// as 0 (torch gives a value below 1.7e-38 there, which no sum can tell apart).
constexpr float kExpCutoff = 87.0f;
// Pixel rows per band at least, for band_count: a row costs k² taps per pixel, so thin bands
// already pay.
constexpr int64_t kMinRowsPerBand = 2;

struct Attributes {
  int64_t dilation = 1;
  float epsilon = kDefaultEpsilon;
};

// dilation (int, required, 1..kMaxDilation) and epsilon (float, optional, finite and >= 0).
inline OrtStatus* read_attributes(const ort::Api& api, const char* op, const OrtKernelInfo* info,
                                  Attributes* out) {
  if (OrtStatus* s = get_int_attribute(api, op, info, "dilation", &out->dilation)) return s;
  if (out->dilation < 1 || out->dilation > kMaxDilation) {
    return op_error(api, op, "attribute dilation must be an integer in [1, " +
                                 std::to_string(kMaxDilation) + "], got " +
                                 std::to_string(out->dilation));
  }
  float epsilon = kDefaultEpsilon;
  if (OrtStatus* s = api.KernelInfoGetAttribute_float(info, "epsilon", &epsilon)) {
    api.ReleaseStatus(s);  // absent: the paper's 1e-10
    epsilon = kDefaultEpsilon;
  }
  if (!(std::isfinite(epsilon) && epsilon >= 0.0f)) {
    return op_error(api, op, "attribute epsilon must be a finite number >= 0, got " +
                                 format_float(epsilon));
  }
  out->epsilon = epsilon;
  return nullptr;
}

// Radius of a kernel-size input: odd, 1..kMaxKernelSize.
inline OrtStatus* kernel_radius(const ort::Api& api, const char* op, const char* name,
                                int64_t size, int64_t* radius) {
  if (size < 1 || size > kMaxKernelSize || size % 2 == 0) {
    return op_error(api, op, std::string(name) + " must be odd and in [1, " +
                                 std::to_string(kMaxKernelSize) + "], got " +
                                 std::to_string(size));
  }
  *radius = (size - 1) / 2;
  return nullptr;
}

// One call's tensors and settings. The temporal pointers are null for AffinityFilter.
struct Job {
  const float* radiance;  // (N, C, H, W)
  const float* features;  // (N, D, H, W)
  const float* bandwidth;  // (N, 1, H, W)
  const float* center;     // (N, 1, H, W)
  const float* prev_output = nullptr;         // (N, C, H, W)
  const float* prev_features = nullptr;       // (N, D, H, W)
  const float* temporal_bandwidth = nullptr;  // (N, 1, H, W)
  const float* temporal_on = nullptr;         // (N)
  float* out;                                 // (N, C, H, W)
  // (N, 1, H, W): ε + Σ weights, the denominator of eq. 6 / 8, for training's backward
  // (affinity_backward.h); null when serving.
  float* denominator = nullptr;
  int64_t C = 0, D = 0, H = 0, W = 0;
  int64_t radius = 0, dilation = 1, temporal_radius = -1;  // -1: no temporal kernel
  float epsilon = kDefaultEpsilon;
  int64_t bands = 1;
};

// The planes of image n.
struct Image {
  const float *L, *F, *A, *Cw;  // radiance, features, bandwidth, centre
  const float *O, *PF, *B;      // previous output, previous features, temporal bandwidth
  float on;                     // temporal_on, sanitised; 0: no temporal term
  float* out;
  float* den;                   // ε + Σ weights, or null (Job::denominator)

  Image(const Job& j, int64_t n) {
    const int64_t plane = j.H * j.W;
    L = j.radiance + n * j.C * plane;
    F = j.features + n * j.D * plane;
    A = j.bandwidth + n * plane;
    Cw = j.center + n * plane;
    const bool temporal = j.temporal_radius >= 0;
    O = temporal ? j.prev_output + n * j.C * plane : nullptr;
    PF = temporal ? j.prev_features + n * j.D * plane : nullptr;
    B = temporal ? j.temporal_bandwidth + n * plane : nullptr;
    on = temporal && j.temporal_on[n] > 0.0f ? j.temporal_on[n] : 0.0f;  // NaN -> 0
    out = j.out + n * j.C * plane;
    den = j.denominator ? j.denominator + n * plane : nullptr;
  }
};

// a, b, c, on: values below 0 and NaN count as 0.
inline float non_negative(float v) { return v > 0.0f ? v : 0.0f; }

// exp(-t), and 0 where t >= kExpCutoff or t is NaN.
inline float weight_of(float t) { return t < kExpCutoff ? std::exp(-t) : 0.0f; }

// torch.nan_to_num: NaN -> 0, ±Inf -> ±FLT_MAX.
inline float finite_result(float v) {
  if (v != v) return 0.0f;
  return v > FLT_MAX ? FLT_MAX : (v < -FLT_MAX ? -FLT_MAX : v);
}

// ---- windows ------------------------------------------------------------------------------------

// The window of the kLanes pixels from (y, x) on in a row: calls tap(q, xq) for each tap
// (yq, xq) = (y + i·step, x + k·step), -r <= i, k <= r, row by row (the sums' order), with q its
// index in the H×W plane, whose row is inside the image and whose kLanes columns from xq on reach
// into it; the centre is left out if `skip_centre`.
template <int kLanes, class Tap>
inline void for_each_tap(int64_t y, int64_t x, int64_t r, int64_t step, bool skip_centre,
                         int64_t H, int64_t W, const Tap& tap) {
  for (int64_t i = -r; i <= r; ++i) {
    const int64_t yq = y + i * step;
    if (yq < 0 || yq >= H) continue;
    for (int64_t k = -r; k <= r; ++k) {
      const int64_t xq = x + k * step;
      if ((skip_centre && i == 0 && k == 0) || xq + kLanes <= 0 || xq >= W) continue;
      tap(yq * W + xq, xq);
    }
  }
}

// ||a_p - b_q||² over the D feature planes of a and b (`plane` floats apart).
inline float distance2(const float* a, int64_t p, const float* b, int64_t q, int64_t D,
                       int64_t plane) {
  float d2 = 0.0f;
  for (int64_t e = 0; e < D; ++e) {
    const float diff = a[e * plane + p] - b[e * plane + q];
    d2 += diff * diff;
  }
  return d2;
}

// ---- scalar reference ---------------------------------------------------------------------------

// Pixels [x0, x1) of row y: the numerators are summed in the output planes themselves.
inline void filter_pixels_scalar(const Job& j, const Image& im, int64_t y, int64_t x0,
                                 int64_t x1) {
  const int64_t plane = j.H * j.W, r = j.radius, dil = j.dilation;
  for (int64_t x = x0; x < x1; ++x) {
    const int64_t p = y * j.W + x;
    float* out = im.out + p;
    const float a = non_negative(im.A[p]), c = non_negative(im.Cw[p]);
    for (int64_t ch = 0; ch < j.C; ++ch) {
      out[ch * plane] = c * im.L[ch * plane + p];  // w_pp = c_p
    }
    float den = c;
    for_each_tap<1>(y, x, r, dil, true, j.H, j.W, [&](int64_t q, int64_t) {  // eq. 4 + 6
      const float w = weight_of(a * distance2(im.F, p, im.F, q, j.D, plane));
      for (int64_t ch = 0; ch < j.C; ++ch) out[ch * plane] += w * im.L[ch * plane + q];
      den += w;
    });
    if (im.on > 0.0f) {  // eq. 7 + 8, dilation 1, the centre included
      const float b = non_negative(im.B[p]);
      const int64_t rt = j.temporal_radius;
      for_each_tap<1>(y, x, rt, 1, false, j.H, j.W, [&](int64_t q, int64_t) {
        const float w = im.on * weight_of(b * distance2(im.F, p, im.PF, q, j.D, plane));
        for (int64_t ch = 0; ch < j.C; ++ch) out[ch * plane] += w * im.O[ch * plane + q];
        den += w;
      });
    }
    const float denominator = j.epsilon + den;
    for (int64_t ch = 0; ch < j.C; ++ch) {
      out[ch * plane] = finite_result(out[ch * plane] / denominator);
    }
    if (im.den != nullptr) im.den[p] = denominator;
  }
}

// ---- AVX2 ---------------------------------------------------------------------------------------

#if QF_HAVE_AVX2
// weight_of on 8 lanes: exp(-t) = 2^-m · e^-u with m = round(t·log2 e), |u| <= ln2/2, e^-u by
// its degree-7 Taylor polynomial (truncation below 6e-9 relative, under float rounding). Lanes
// with t >= kExpCutoff or NaN are masked to 0 at the end, whatever the arithmetic made of them.
inline __m256 weight_of8(__m256 t) {
  const __m256 keep = _mm256_cmp_ps(t, _mm256_set1_ps(kExpCutoff), _CMP_LT_OQ);  // NaN: false
  const __m256 m = _mm256_round_ps(_mm256_mul_ps(t, _mm256_set1_ps(1.44269504088896341f)),
                                   _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  // u = t - m·ln2 with ln2 in two parts, so that u keeps its low bits
  __m256 u = _mm256_fnmadd_ps(m, _mm256_set1_ps(0.693359375f), t);
  u = _mm256_fnmadd_ps(m, _mm256_set1_ps(-2.12194440e-4f), u);
  __m256 e = _mm256_set1_ps(-1.0f / 5040.0f);  // Σ (-u)^k / k!
  e = _mm256_fmadd_ps(e, u, _mm256_set1_ps(1.0f / 720.0f));
  e = _mm256_fmadd_ps(e, u, _mm256_set1_ps(-1.0f / 120.0f));
  e = _mm256_fmadd_ps(e, u, _mm256_set1_ps(1.0f / 24.0f));
  e = _mm256_fmadd_ps(e, u, _mm256_set1_ps(-1.0f / 6.0f));
  e = _mm256_fmadd_ps(e, u, _mm256_set1_ps(0.5f));
  e = _mm256_fmadd_ps(e, u, _mm256_set1_ps(-1.0f));
  e = _mm256_fmadd_ps(e, u, _mm256_set1_ps(1.0f));
  // 2^-m for m in [0, 126] (t < 87): the exponent field 127 - m
  const __m256i bits =
      _mm256_slli_epi32(_mm256_sub_epi32(_mm256_set1_epi32(127), _mm256_cvtps_epi32(m)), 23);
  return _mm256_and_ps(keep, _mm256_mul_ps(e, _mm256_castsi256_ps(bits)));
}

// finite_result on 8 lanes.
inline __m256 finite_result8(__m256 v) {
  const __m256 number = _mm256_cmp_ps(v, v, _CMP_ORD_Q);
  const __m256 clamped = _mm256_min_ps(_mm256_max_ps(v, _mm256_set1_ps(-FLT_MAX)),
                                       _mm256_set1_ps(FLT_MAX));
  return _mm256_and_ps(number, clamped);
}

// Lanes l with 0 <= x + l < W.
inline __m256 lanes_inside(int64_t x, int64_t W) {
  const __m256i index = _mm256_add_epi32(_mm256_set1_epi32(static_cast<int32_t>(x)),
                                         _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
  const __m256i low = _mm256_cmpgt_epi32(index, _mm256_set1_epi32(-1));
  const __m256i high = _mm256_cmpgt_epi32(_mm256_set1_epi32(static_cast<int32_t>(W)), index);
  return _mm256_castsi256_ps(_mm256_and_si256(low, high));
}

// 8 floats at base + offset; lanes outside `mask` read 0 and are never touched.
inline __m256 load8(const float* base, int64_t offset, bool whole, __m256 mask) {
  // (the address of a masked load may lie before the plane: only its unmasked lanes are read)
  const float* at = reinterpret_cast<const float*>(reinterpret_cast<uintptr_t>(base) +
                                                   static_cast<uintptr_t>(offset) * sizeof(float));
  return whole ? _mm256_loadu_ps(at) : _mm256_maskload_ps(at, _mm256_castps_si256(mask));
}

// for_each_tap for the 8 pixels at (y, x): tap(q, whole, mask), q that of lane 0; whole: every
// lane's tap is inside the image, else `mask` holds the lanes whose tap is.
template <class Tap>
inline void for_each_tap8(int64_t y, int64_t x, int64_t r, int64_t step, bool skip_centre,
                          int64_t H, int64_t W, const Tap& tap) {
  for_each_tap<8>(y, x, r, step, skip_centre, H, W, [&](int64_t q, int64_t xq) {
    const bool whole = xq >= 0 && xq + 8 <= W;
    tap(q, whole, whole ? _mm256_setzero_ps() : lanes_inside(xq, W));
  });
}

// Adds the taps of one window (the spatial one: `features`/`values` = F/L, skipping the centre;
// the temporal one: PF/O with dilation 1 and the weights times `scale`) for the 8 pixels at
// (y, x) and channels [c0, c0 + G) to num[] and den. kD > 0: D = kD, the pixels' own features
// stay in registers; kD = 0: any D, read from the plane at each tap.
template <int G, int kD, bool kTemporal>
inline void add_window8(const Job& j, const Image& im, int64_t y, int64_t x, int64_t c0,
                        __m256 bandwidth, __m256 scale, __m256* num, __m256& den) {
  const int64_t plane = j.H * j.W, p = y * j.W + x;
  const int64_t D = kD > 0 ? kD : j.D;
  __m256 own[kD > 0 ? kD : 1];
  if constexpr (kD > 0) {
    for (int f = 0; f < kD; ++f) own[f] = _mm256_loadu_ps(im.F + f * plane + p);
  }
  const int64_t r = kTemporal ? j.temporal_radius : j.radius;
  const int64_t dil = kTemporal ? 1 : j.dilation;
  const float* neighbours = kTemporal ? im.PF : im.F;
  const float* values = kTemporal ? im.O : im.L;
  for_each_tap8(y, x, r, dil, !kTemporal, j.H, j.W, [&](int64_t q, bool whole, __m256 mask) {
    __m256 d2 = _mm256_setzero_ps();
    for (int64_t f = 0; f < D; ++f) {
      __m256 fp;
      if constexpr (kD > 0) {
        fp = own[f];
      } else {
        fp = _mm256_loadu_ps(im.F + f * plane + p);
      }
      const __m256 diff = _mm256_sub_ps(fp, load8(neighbours + f * plane, q, whole, mask));
      d2 = _mm256_fmadd_ps(diff, diff, d2);
    }
    __m256 w = weight_of8(_mm256_mul_ps(bandwidth, d2));
    if (kTemporal) w = _mm256_mul_ps(scale, w);
    if (!whole) w = _mm256_and_ps(mask, w);
    for (int g = 0; g < G; ++g) {
      num[g] = _mm256_fmadd_ps(w, load8(values + (c0 + g) * plane, q, whole, mask), num[g]);
    }
    den = _mm256_add_ps(den, w);
  });
}

// filter_pixels_scalar for the 8 pixels at (y, x), x + 8 <= W, channels [c0, c0 + G).
template <int G, int kD>
inline void filter_chunk_avx2(const Job& j, const Image& im, int64_t y, int64_t x, int64_t c0) {
  const int64_t plane = j.H * j.W, p = y * j.W + x;
  const __m256 zero = _mm256_setzero_ps();
  // max(v, 0) returns its second operand for NaN: NaN -> 0 like non_negative()
  const __m256 a = _mm256_max_ps(_mm256_loadu_ps(im.A + p), zero);
  const __m256 c = _mm256_max_ps(_mm256_loadu_ps(im.Cw + p), zero);
  __m256 num[G];
  for (int g = 0; g < G; ++g) {
    num[g] = _mm256_mul_ps(c, _mm256_loadu_ps(im.L + (c0 + g) * plane + p));  // w_pp = c_p
  }
  __m256 den = c;
  add_window8<G, kD, false>(j, im, y, x, c0, a, zero, num, den);
  if (im.on > 0.0f) {
    const __m256 b = _mm256_max_ps(_mm256_loadu_ps(im.B + p), zero);
    add_window8<G, kD, true>(j, im, y, x, c0, b, _mm256_set1_ps(im.on), num, den);
  }
  const __m256 denominator = _mm256_add_ps(_mm256_set1_ps(j.epsilon), den);
  for (int g = 0; g < G; ++g) {
    _mm256_storeu_ps(im.out + (c0 + g) * plane + p,
                     finite_result8(_mm256_div_ps(num[g], denominator)));
  }
  if (im.den != nullptr && c0 == 0) _mm256_storeu_ps(im.den + p, denominator);
}

// Whole groups of 8 pixels of row y, every channel (in groups of up to 4, which keeps the
// numerators in registers; the weights are recomputed per group). Returns the pixels done.
template <int kD>
inline int64_t filter_row_avx2(const Job& j, const Image& im, int64_t y) {
  int64_t x = 0;
  for (; x + 8 <= j.W; x += 8) {
    for (int64_t c0 = 0; c0 < j.C; c0 += 4) {
      switch (std::min<int64_t>(j.C - c0, 4)) {
        case 1: filter_chunk_avx2<1, kD>(j, im, y, x, c0); break;
        case 2: filter_chunk_avx2<2, kD>(j, im, y, x, c0); break;
        case 3: filter_chunk_avx2<3, kD>(j, im, y, x, c0); break;
        default: filter_chunk_avx2<4, kD>(j, im, y, x, c0); break;
      }
    }
  }
  return x;
}
#endif

// Row y of image n.
inline void filter_row(const Job& j, const Image& im, int64_t y) {
  int64_t x = 0;
#if QF_HAVE_AVX2
  // d = 8, the paper's feature count, with the pixel's own features in registers
  if (simd_enabled()) {
    x = j.D == 8 ? filter_row_avx2<8>(j, im, y) : filter_row_avx2<0>(j, im, y);
  }
#endif
  filter_pixels_scalar(j, im, y, x, j.W);
}

// Task: the rows of one band of image task / bands.
inline void filter_band(const Job& j, int64_t task) {
  const int64_t n = task / j.bands, band = task % j.bands;
  const Image im(j, n);
  const int64_t ya = band_start(band, j.bands, j.H), yb = band_start(band + 1, j.bands, j.H);
  for (int64_t y = ya; y < yb; ++y) filter_row(j, im, y);
}

// ---- inputs -------------------------------------------------------------------------------------

// "(N, k, H, W)" with N, H, W from `like` and k given.
inline std::string nchw(const Shape& like, const std::string& channels) {
  return "(" + std::to_string(like[0]) + ", " + channels + ", " + std::to_string(like[2]) +
         ", " + std::to_string(like[3]) + ")";
}

inline bool same_nhw(const Shape& s, const Shape& like, int64_t channels) {
  return s.rank == 4 && s[0] == like[0] && s[1] == channels && s[2] == like[2] &&
         s[3] == like[3];
}

// Checks radiance, features, bandwidth, centre (inputs 0–3, as read) and puts them in `j`.
inline OrtStatus* read_spatial_inputs(const ort::Api& api, const char* op,
                                      const FloatInput* in, Job* j) {
  j->radiance = in[0].data;
  j->features = in[1].data;
  j->bandwidth = in[2].data;
  j->center = in[3].data;
  const Shape &r = in[0].shape, &f = in[1].shape, &bs = in[2].shape, &cs = in[3].shape;
  if (OrtStatus* s = check_planes(api, op, "radiance", r)) return s;
  if (r[2] * r[3] > INT32_MAX - 16) {
    return op_error(api, op, "images of more than 2^31 pixels are not supported, got " + r.str());
  }
  if (f.rank != 4 || f[1] < 1 || !same_nhw(f, r, f[1])) {
    return op_error(api, op, "features must be " + nchw(r, "D") + " like the radiance, got " +
                                 f.str());
  }
  if (!same_nhw(bs, r, 1)) {
    return op_error(api, op, "bandwidth must be " + nchw(r, "1") + ", got " + bs.str());
  }
  if (!same_nhw(cs, r, 1)) {
    return op_error(api, op, "center must be " + nchw(r, "1") + ", got " + cs.str());
  }
  j->C = r[1];
  j->D = f[1];
  j->H = r[2];
  j->W = r[3];
  return nullptr;
}

// Allocates the output like the radiance and runs the bands.
inline OrtStatus* run(const ort::Api& api, const char* op, OrtKernelContext* ctx, Job* j,
                      const Shape& radiance_shape) {
  if (OrtStatus* s = get_float_output(api, op, ctx, 0, "output", radiance_shape, &j->out)) {
    return s;
  }
  const int64_t N = radiance_shape[0];
  j->bands = band_count(j->H, N, kMinRowsPerBand);
  const Job& job = *j;
  auto task = [&job](size_t i) { filter_band(job, static_cast<int64_t>(i)); };
  return run_tasks(api, op, ctx, N * job.bands, task);
}

}  // namespace qf::affinity
