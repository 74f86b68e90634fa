// Gradients of the affinity kernels (affinity_common.h, docs/affinity-math.md) for training:
// training's C ABI (affinity_train_abi.cc) runs them; quietframe.model.affinity_native calls it.
//
// Per image, with out_p = N_p / D_p (eq. 6 / 8), g = ∂ℓ/∂out and, per pixel,
//   gD_p = g_p / D_p (per channel),  h_p = -Σ_c g_pc out_pc / D_p,
//   G_pq = gD_p · L_q + h_p            (∂ℓ/∂w_pq; G't with O_q' for ω_pq')
// the gradients are
//   ∂ℓ/∂c_p = gD_p · L_p + h_p,        ∂ℓ/∂a_p = -Σ_q G_pq w_pq d²_pq,
//   ∂ℓ/∂L_q = c_q gD_q + Σ_p w_pq gD_p  (p: every pixel whose window holds q),
//   ∂ℓ/∂f_x = Σ_(x,q) (-2 a_x G_xq w_xq)(f_x - f_q) + Σ_(p,x) (-2 a_p G_px w_px)(f_x - f_p),
// and for the temporal term ∂ℓ/∂b_p = -Σ_q' G'_pq' ω_pq' d²_pq', ∂ℓ/∂O_q' = Σ_p ω_pq' gD_p,
// ∂ℓ/∂f_p += Σ_q' (-2 b_p G'_pq' ω_pq')(f_p - PF_q'), ∂ℓ/∂PF_q' = Σ_p (2 b_p G'_pq' ω_pq')(f_p - PF_q').
// The rules of the reference: a, b, c below 0 or NaN count as 0, so their gradient is 0 there;
// a weight counted as 0 (exponent NaN or >= kExpCutoff) has gradient 0; nan_to_num is taken as
// the identity (exact where the result is finite). temporal_on gets no gradient.
//
// Race-free: the scattered terms (∂L_q, ∂f_q, ∂O_q', ∂PF_q') are gathers. Pass 1 runs the forward
// (filter_band, bit-identical to the served op) into scratch and turns it into gD and h; pass 2
// computes every gradient of pixel x alone: for each spatial offset o it forms d = f_x - f_{x+o}
// once and uses it for the pair (x, x+o), where x owns the weight, and the pair (x+o, x), where x
// is the neighbour (the window is symmetric, so x lies in x+o's window). A pixel's gradients
// depend only on its neighbourhood and on which loop (AVX2 or scalar) handles its column:
// bitwise independent of the bands, hence of the thread count.
#pragma once

#include <cstdint>

#include "affinity_common.h"

namespace qf::affinity {

// One backward call: the forward's inputs (`fwd`, whose out/denominator are pass 1's scratch),
// ∂ℓ/∂out and the gradient planes (the temporal ones null for AffinityFilter).
struct GradJob {
  Job fwd;
  const float* grad_out;  // (N, C, H, W)
  float* gD;              // (N, C, H, W) scratch: pass 1 leaves g / D here (fwd.out)
  float* h;               // (N, 1, H, W) scratch: pass 1 leaves h here (fwd.denominator)
  float *gL, *gF, *gA, *gC;  // like radiance, features, bandwidth, centre
  float *gO = nullptr, *gPF = nullptr, *gB = nullptr;  // like prev_output, prev_features, b
};

// The planes of image n for the backward.
struct GradImage {
  Image in;
  const float *G, *gD, *h;  // ∂ℓ/∂out, g / D, h
  float *gL, *gF, *gA, *gC, *gO, *gPF, *gB;

  GradImage(const GradJob& j, int64_t n) : in(j.fwd, n) {
    const int64_t plane = j.fwd.H * j.fwd.W, C = j.fwd.C, D = j.fwd.D;
    G = j.grad_out + n * C * plane;
    gD = j.gD + n * C * plane;
    h = j.h + n * plane;
    gL = j.gL + n * C * plane;
    gF = j.gF + n * D * plane;
    gA = j.gA + n * plane;
    gC = j.gC + n * plane;
    const bool temporal = j.fwd.temporal_radius >= 0;
    gO = temporal ? j.gO + n * C * plane : nullptr;
    gPF = temporal ? j.gPF + n * D * plane : nullptr;
    gB = temporal ? j.gB + n * plane : nullptr;
  }
};

// ---- pass 1: gD and h -----------------------------------------------------------------------

// Pass 1 on one band: the forward into the scratch (out -> gD's planes, ε + Σw -> h's), then per
// pixel gD = g / D and h = -Σ_c g out / D in place.
inline void prepare_band(const GradJob& j, int64_t task) {
  filter_band(j.fwd, task);
  const Job& f = j.fwd;
  const int64_t n = task / f.bands, band = task % f.bands, plane = f.H * f.W;
  const GradImage im(j, n);
  float* gD = const_cast<float*>(im.gD);
  float* h = const_cast<float*>(im.h);
  const int64_t pa = band_start(band, f.bands, f.H) * f.W;
  const int64_t pb = band_start(band + 1, f.bands, f.H) * f.W;
  for (int64_t p = pa; p < pb; ++p) {
    const float denominator = h[p];
    float dot = 0.0f;
    for (int64_t ch = 0; ch < f.C; ++ch) {
      const float g = im.G[ch * plane + p];
      dot += g * gD[ch * plane + p];  // gD holds out here
      gD[ch * plane + p] = g / denominator;
    }
    h[p] = -dot / denominator;
  }
}

// ---- pass 2, scalar reference ---------------------------------------------------------------

// Every gradient of pixels [x0, x1) of row y.
inline void grad_pixels_scalar(const GradJob& j, const GradImage& im, int64_t y, int64_t x0,
                               int64_t x1) {
  const Job& f = j.fwd;
  const Image& in = im.in;
  const int64_t plane = f.H * f.W, C = f.C, D = f.D, r = f.radius, dil = f.dilation;
  for (int64_t x = x0; x < x1; ++x) {
    const int64_t p = y * f.W + x;
    const float a = non_negative(in.A[p]), c = non_negative(in.Cw[p]), hp = im.h[p];
    float* gL = im.gL + p;
    float* gF = im.gF + p;
    float own_dot = hp;  // G_pp = gD_p · L_p + h_p
    for (int64_t ch = 0; ch < C; ++ch) {
      gL[ch * plane] = c * im.gD[ch * plane + p];  // w_pp = c_p
      own_dot += im.gD[ch * plane + p] * in.L[ch * plane + p];
    }
    for (int64_t k = 0; k < D; ++k) gF[k * plane] = 0.0f;
    float ga = 0.0f;
    for_each_tap<1>(y, x, r, dil, true, f.H, f.W, [&](int64_t q, int64_t) {  // eq. 4 + 6
      const float d2 = distance2(in.F, p, in.F, q, D, plane);
      float coef = 0.0f;  // of (f_p - f_q) in ∂ℓ/∂f_p
      const float w_own = weight_of(a * d2);  // w_pq: p owns it
      if (w_own > 0.0f) {
        float G = hp;
        for (int64_t ch = 0; ch < C; ++ch) G += im.gD[ch * plane + p] * in.L[ch * plane + q];
        ga -= G * w_own * d2;
        coef += -2.0f * a * G * w_own;
      }
      const float aq = non_negative(in.A[q]);
      const float w_nb = weight_of(aq * d2);  // w_qp: p is q's neighbour
      if (w_nb > 0.0f) {
        float G = im.h[q];
        for (int64_t ch = 0; ch < C; ++ch) {
          const float gDq = im.gD[ch * plane + q];
          G += gDq * in.L[ch * plane + p];
          gL[ch * plane] += w_nb * gDq;
        }
        coef += -2.0f * aq * G * w_nb;
      }
      if (coef != 0.0f) {
        for (int64_t e = 0; e < D; ++e) {
          gF[e * plane] += coef * (in.F[e * plane + p] - in.F[e * plane + q]);
        }
      }
    });
    im.gA[p] = in.A[p] > 0.0f ? ga : 0.0f;  // a = max(bandwidth, 0), NaN -> 0
    im.gC[p] = in.Cw[p] > 0.0f ? own_dot : 0.0f;
    if (im.gB == nullptr) continue;
    const int64_t rt = f.temporal_radius;
    float* gO = im.gO + p;
    float* gPF = im.gPF + p;
    for (int64_t ch = 0; ch < C; ++ch) gO[ch * plane] = 0.0f;
    for (int64_t k = 0; k < D; ++k) gPF[k * plane] = 0.0f;
    float gb = 0.0f;
    if (in.on > 0.0f) {  // eq. 7 + 8, dilation 1, the centre included
      const float b = non_negative(in.B[p]);
      for_each_tap<1>(y, x, rt, 1, false, f.H, f.W, [&](int64_t q, int64_t) {
        // p owns ω_pq' (f_p against PF_q')
        const float d2 = distance2(in.F, p, in.PF, q, D, plane);
        const float w_own = in.on * weight_of(b * d2);
        if (w_own > 0.0f) {
          float G = hp;
          for (int64_t ch = 0; ch < C; ++ch) G += im.gD[ch * plane + p] * in.O[ch * plane + q];
          gb -= G * w_own * d2;
          const float coef = -2.0f * b * G * w_own;
          for (int64_t e = 0; e < D; ++e) {
            gF[e * plane] += coef * (in.F[e * plane + p] - in.PF[e * plane + q]);
          }
        }
        // p is the neighbour q' of pixel q's window (f_q against PF_p)
        const float d2n = distance2(in.F, q, in.PF, p, D, plane);
        const float bq = non_negative(in.B[q]);
        const float w_nb = in.on * weight_of(bq * d2n);
        if (w_nb > 0.0f) {
          float G = im.h[q];
          for (int64_t ch = 0; ch < C; ++ch) {
            const float gDq = im.gD[ch * plane + q];
            G += gDq * in.O[ch * plane + p];
            gO[ch * plane] += w_nb * gDq;
          }
          const float coef = 2.0f * bq * G * w_nb;
          for (int64_t e = 0; e < D; ++e) {
            gPF[e * plane] += coef * (in.F[e * plane + q] - in.PF[e * plane + p]);
          }
        }
      });
    }
    im.gB[p] = in.B[p] > 0.0f ? gb : 0.0f;
  }
}

// ---- pass 2, AVX2 ---------------------------------------------------------------------------

#if QF_HAVE_AVX2
// v where keep's lanes are set, else 0 (also where v is NaN: a weight counted as 0 must not turn
// an Inf bandwidth or an Inf d² into a NaN gradient).
inline __m256 only(__m256 keep, __m256 v) { return _mm256_and_ps(keep, v); }

inline __m256 positive(__m256 w) { return _mm256_cmp_ps(w, _mm256_setzero_ps(), _CMP_GT_OQ); }

// The spatial gradients of the 8 pixels at (y, x), x + 8 <= W, C = kC, D = kD: grad_pixels_scalar
// with 8 lanes (the same masks and loads as add_window8).
template <int kC, int kD>
inline void grad_spatial8(const GradJob& j, const GradImage& im, int64_t y, int64_t x) {
  const Job& f = j.fwd;
  const Image& in = im.in;
  const int64_t plane = f.H * f.W, p = y * f.W + x, r = f.radius, dil = f.dilation;
  const __m256 zero = _mm256_setzero_ps(), minus2 = _mm256_set1_ps(-2.0f);
  const __m256 a = _mm256_max_ps(_mm256_loadu_ps(in.A + p), zero);  // NaN -> 0
  const __m256 c = _mm256_max_ps(_mm256_loadu_ps(in.Cw + p), zero);
  const __m256 hp = _mm256_loadu_ps(im.h + p);
  __m256 gL[kC], gF[kD];
  __m256 own_dot = hp;
  for (int ch = 0; ch < kC; ++ch) {
    const __m256 gDp = _mm256_loadu_ps(im.gD + ch * plane + p);
    gL[ch] = _mm256_mul_ps(c, gDp);
    own_dot = _mm256_fmadd_ps(gDp, _mm256_loadu_ps(in.L + ch * plane + p), own_dot);
  }
  for (int e = 0; e < kD; ++e) gF[e] = zero;
  __m256 ga = zero;
  for_each_tap8(y, x, r, dil, true, f.H, f.W, [&](int64_t q, bool whole, __m256 mask) {
    __m256 diff[kD];
    __m256 d2 = zero;
    for (int e = 0; e < kD; ++e) {
      diff[e] = _mm256_sub_ps(_mm256_loadu_ps(in.F + e * plane + p),
                              load8(in.F + e * plane, q, whole, mask));
      d2 = _mm256_fmadd_ps(diff[e], diff[e], d2);
    }
    // w_pq, p owns it: G = gD_p · L_q + h_p
    __m256 w_own = weight_of8(_mm256_mul_ps(a, d2));
    if (!whole) w_own = _mm256_and_ps(mask, w_own);
    const __m256 keep_own = positive(w_own);
    __m256 G = hp;
    for (int ch = 0; ch < kC; ++ch) {
      G = _mm256_fmadd_ps(_mm256_loadu_ps(im.gD + ch * plane + p),
                          load8(in.L + ch * plane, q, whole, mask), G);
    }
    const __m256 gw_own = _mm256_mul_ps(G, w_own);
    ga = _mm256_sub_ps(ga, only(keep_own, _mm256_mul_ps(gw_own, d2)));
    __m256 coef = only(keep_own, _mm256_mul_ps(minus2, _mm256_mul_ps(a, gw_own)));
    // w_qp, p is q's neighbour: G = gD_q · L_p + h_q
    const __m256 aq = _mm256_max_ps(load8(in.A, q, whole, mask), zero);
    __m256 w_nb = weight_of8(_mm256_mul_ps(aq, d2));
    if (!whole) w_nb = _mm256_and_ps(mask, w_nb);
    __m256 Gq = load8(im.h, q, whole, mask);
    for (int ch = 0; ch < kC; ++ch) {
      const __m256 gDq = load8(im.gD + ch * plane, q, whole, mask);
      Gq = _mm256_fmadd_ps(gDq, _mm256_loadu_ps(in.L + ch * plane + p), Gq);
      gL[ch] = _mm256_fmadd_ps(w_nb, gDq, gL[ch]);
    }
    const __m256 gw_nb = _mm256_mul_ps(Gq, w_nb);
    coef = _mm256_add_ps(
        coef, only(positive(w_nb), _mm256_mul_ps(minus2, _mm256_mul_ps(aq, gw_nb))));
    for (int e = 0; e < kD; ++e) gF[e] = _mm256_fmadd_ps(coef, diff[e], gF[e]);
  });
  for (int ch = 0; ch < kC; ++ch) _mm256_storeu_ps(im.gL + ch * plane + p, gL[ch]);
  for (int e = 0; e < kD; ++e) _mm256_storeu_ps(im.gF + e * plane + p, gF[e]);
  // a = max(bandwidth, 0): gradient only where bandwidth > 0 (NaN: none)
  const __m256 a_on = _mm256_cmp_ps(_mm256_loadu_ps(in.A + p), zero, _CMP_GT_OQ);
  const __m256 c_on = _mm256_cmp_ps(_mm256_loadu_ps(in.Cw + p), zero, _CMP_GT_OQ);
  _mm256_storeu_ps(im.gA + p, only(a_on, ga));
  _mm256_storeu_ps(im.gC + p, only(c_on, own_dot));
}

// The temporal gradients of the 8 pixels at (y, x): ∂b, ∂O, ∂PF, and the temporal part of ∂f
// added to what grad_spatial8 stored.
template <int kC, int kD>
inline void grad_temporal8(const GradJob& j, const GradImage& im, int64_t y, int64_t x) {
  const Job& f = j.fwd;
  const Image& in = im.in;
  const int64_t plane = f.H * f.W, p = y * f.W + x, rt = f.temporal_radius;
  const __m256 zero = _mm256_setzero_ps(), minus2 = _mm256_set1_ps(-2.0f);
  const __m256 two = _mm256_set1_ps(2.0f), on = _mm256_set1_ps(in.on);
  const __m256 b = _mm256_max_ps(_mm256_loadu_ps(in.B + p), zero);
  const __m256 hp = _mm256_loadu_ps(im.h + p);
  __m256 gO[kC], gPF[kD], gF[kD];
  for (int ch = 0; ch < kC; ++ch) gO[ch] = zero;
  for (int e = 0; e < kD; ++e) gPF[e] = gF[e] = zero;
  __m256 gb = zero;
  for_each_tap8(y, x, rt, 1, false, f.H, f.W, [&](int64_t q, bool whole, __m256 mask) {
    {  // ω_pq', p owns it: f_p against PF_q'
      __m256 diff[kD];
      __m256 d2 = zero;
      for (int e = 0; e < kD; ++e) {
        diff[e] = _mm256_sub_ps(_mm256_loadu_ps(in.F + e * plane + p),
                                load8(in.PF + e * plane, q, whole, mask));
        d2 = _mm256_fmadd_ps(diff[e], diff[e], d2);
      }
      __m256 w = _mm256_mul_ps(on, weight_of8(_mm256_mul_ps(b, d2)));
      if (!whole) w = _mm256_and_ps(mask, w);
      const __m256 keep = positive(w);
      __m256 G = hp;
      for (int ch = 0; ch < kC; ++ch) {
        G = _mm256_fmadd_ps(_mm256_loadu_ps(im.gD + ch * plane + p),
                            load8(in.O + ch * plane, q, whole, mask), G);
      }
      const __m256 gw = _mm256_mul_ps(G, w);
      gb = _mm256_sub_ps(gb, only(keep, _mm256_mul_ps(gw, d2)));
      const __m256 coef = only(keep, _mm256_mul_ps(minus2, _mm256_mul_ps(b, gw)));
      for (int e = 0; e < kD; ++e) gF[e] = _mm256_fmadd_ps(coef, diff[e], gF[e]);
    }
    {  // p is the neighbour q' of pixel q's window: f_q against PF_p
      __m256 diff[kD];
      __m256 d2 = zero;
      for (int e = 0; e < kD; ++e) {
        diff[e] = _mm256_sub_ps(load8(in.F + e * plane, q, whole, mask),
                                _mm256_loadu_ps(in.PF + e * plane + p));
        d2 = _mm256_fmadd_ps(diff[e], diff[e], d2);
      }
      const __m256 bq = _mm256_max_ps(load8(in.B, q, whole, mask), zero);
      __m256 w = _mm256_mul_ps(on, weight_of8(_mm256_mul_ps(bq, d2)));
      if (!whole) w = _mm256_and_ps(mask, w);
      __m256 G = load8(im.h, q, whole, mask);
      for (int ch = 0; ch < kC; ++ch) {
        const __m256 gDq = load8(im.gD + ch * plane, q, whole, mask);
        G = _mm256_fmadd_ps(gDq, _mm256_loadu_ps(in.O + ch * plane + p), G);
        gO[ch] = _mm256_fmadd_ps(w, gDq, gO[ch]);
      }
      const __m256 coef =
          only(positive(w), _mm256_mul_ps(two, _mm256_mul_ps(bq, _mm256_mul_ps(G, w))));
      for (int e = 0; e < kD; ++e) gPF[e] = _mm256_fmadd_ps(coef, diff[e], gPF[e]);
    }
  });
  for (int ch = 0; ch < kC; ++ch) _mm256_storeu_ps(im.gO + ch * plane + p, gO[ch]);
  for (int e = 0; e < kD; ++e) {
    _mm256_storeu_ps(im.gPF + e * plane + p, gPF[e]);
    float* at = im.gF + e * plane + p;
    _mm256_storeu_ps(at, _mm256_add_ps(_mm256_loadu_ps(at), gF[e]));
  }
  const __m256 b_on = _mm256_cmp_ps(_mm256_loadu_ps(in.B + p), zero, _CMP_GT_OQ);
  _mm256_storeu_ps(im.gB + p, only(b_on, gb));
}

// Whole groups of 8 pixels of row y. Returns the pixels done.
template <int kC, int kD>
inline int64_t grad_row_avx2(const GradJob& j, const GradImage& im, int64_t y) {
  const Job& f = j.fwd;
  const int64_t plane = f.H * f.W;
  int64_t x = 0;
  for (; x + 8 <= f.W; x += 8) {
    grad_spatial8<kC, kD>(j, im, y, x);
    if (im.gB == nullptr) continue;
    if (im.in.on > 0.0f) {
      grad_temporal8<kC, kD>(j, im, y, x);
    } else {  // ω = 0: no temporal gradient
      const int64_t p = y * f.W + x;
      for (int ch = 0; ch < kC; ++ch) _mm256_storeu_ps(im.gO + ch * plane + p, _mm256_setzero_ps());
      for (int e = 0; e < kD; ++e) _mm256_storeu_ps(im.gPF + e * plane + p, _mm256_setzero_ps());
      _mm256_storeu_ps(im.gB + p, _mm256_setzero_ps());
    }
  }
  return x;
}
#endif

// Pass 2 on row y of image n.
inline void grad_row(const GradJob& j, const GradImage& im, int64_t y) {
  int64_t x = 0;
#if QF_HAVE_AVX2
  // the model's radiance (C = 3) and the paper's feature count (d = 8) in registers
  if (simd_enabled() && j.fwd.C == 3 && j.fwd.D == 8) x = grad_row_avx2<3, 8>(j, im, y);
#endif
  grad_pixels_scalar(j, im, y, x, j.fwd.W);
}

// Pass 2 on one band of image task / bands.
inline void grad_band(const GradJob& j, int64_t task) {
  const Job& f = j.fwd;
  const int64_t n = task / f.bands, band = task % f.bands;
  const GradImage im(j, n);
  const int64_t ya = band_start(band, f.bands, f.H), yb = band_start(band + 1, f.bands, f.H);
  for (int64_t y = ya; y < yb; ++y) grad_row(j, im, y);
}

}  // namespace qf::affinity
