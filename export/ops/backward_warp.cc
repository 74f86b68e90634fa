// BackwardWarp(image (N,C,H,W), motion (N,2,H,W)) -> warped (N,C,H,W), inside (N,1,H,W)
// attribute mode: int, 0 = bilinear, 1 = nearest, 2 = bicubic
//
// Temporal reprojection (quietframe.model.temporal.backward_warp): output pixel p = (x, y) reads
// `image` at s = (x + motion_x, y + motion_y) in pixel-centre coordinates, with the position
// clamped to the image (border padding); inside = 1 where -0.5 < s_x < W - 0.5 and
// -0.5 < s_y < H - 0.5, else 0 (NaN motion: outside).
//
// The reference is F.grid_sample(padding_mode="border", align_corners=False) on the grid
// g = (2s + 1)/size - 1, and this op does the same float32 operations as PyTorch's CPU kernel,
// so that both pick the same texels with the same weights (bit-identical on an FMA machine for
// bilinear and nearest):
//   i = fma(g + 1, size/2, -0.5), clamped to [0, size - 1] with NaN -> 0;
//   bilinear: x0 = floor(i_x), fx = i_x - x0, weights nw = (1-fy)(1-fx), ne = (1-fy)fx,
//     sw = fy(1-fx), se = fy·fx, out = fma(se_v, se, fma(sw_v, sw, fma(ne_v, ne, nw·nw_v))),
//     where a corner past the last column or row reads 0 (its weight is 0 anyway);
//   nearest: the texel at round-half-to-even(i).
//   bicubic (PyTorch's cubic convolution, A = -0.75): i is not clamped to the image but to
//     [-2, size + 1] with NaN -> -2 (beyond those all four taps are the same border texel, so
//     the result is the reference's up to the rounding of its weights' sum); x0 = floor(i),
//     t = i - x0, taps x0-1 … x0+2, each clamped to [0, size - 1] (border padding), weights
//     (get_cubic_coefficients, evaluated operation by operation)
//       w0 = ((A(t+1) - 5A)(t+1) + 8A)(t+1) - 4A,   w1 = ((A+2)t - (A+3))·t·t + 1,
//       w2 = the same of 1 - t,                      w3 = the same as w0 of 2 - t;
//     row r = fma chain w0·v0 + w1·v1 + w2·v2 + w3·v3 along x, then the same of the 4 rows with
//     the y weights. The reference's compiler contracts its products differently, so this one
//     matches it to float rounding (~1e-7 relative), not bit for bit. Not clamped: it may
//     overshoot the texels' range, like the reference.
// The clamps come before any index is formed, so no motion value (±Inf, NaN, 1e38) can make an
// out-of-bounds read. (Bicubic there reads a border texel where the reference, whose t is then
// NaN, returns NaN.) Image values pass through like the reference's (a non-finite texel in the
// footprint makes the output non-finite).
//
// Parallel over bands of output rows. Each row is done in segments of kSegment pixels: first the
// footprint of every pixel (texel offset, weights, border masks) into stack arrays, then each
// channel plane is read through it, 8 pixels at a time. Where the 8 footprints are consecutive
// texels of one row (smooth motion: the usual case) the corners are plain vector loads, else
// AVX2 gathers (bilinear: of the west/east texel pairs, 8 bytes each, when no footprint touches
// the last column or row; bicubic: pairs likewise when no tap is clamped, else 16 gathers of the
// clamped taps). The op moves far more memory than it computes on, so when every row
// starts on a cache line (W a multiple of 16: 720p, 1080p, 4K) the outputs are written with
// streaming stores of whole lines, which skip reading each line before writing it.
#include <algorithm>
#include <climits>
#include <cmath>
#include <cstdint>
#include <string>

#include "kernel_support.h"
#include "ops.h"
#include "runtime_support.h"
#include "simd.h"

namespace qf {
namespace {

enum class Mode : int64_t { kBilinear = 0, kNearest = 1, kBicubic = 2 };

// Pixels whose footprints are kept at once (bilinear 7 KB, bicubic 17 KB: in L1).
constexpr int64_t kSegment = 256;
constexpr int64_t kLanes = 8;
// Output rows per band at least, for band_count (a band re-reads the footprint rows at its
// edges; the warp is cheap per row, so its bands are thicker than the grid ops').
constexpr int64_t kMinRowsPerBand = 8;

struct WarpJob {
  const float* image;   // (N, C, H, W)
  const float* motion;  // (N, 2, H, W)
  float* warped;        // (N, C, H, W)
  float* inside;        // (N, 1, H, W)
  int64_t C, H, W;
  int64_t bands;
  Mode mode;
  bool stream;  // outputs written with streaming stores (every row starts on a cache line)
};

#if QF_HAVE_AVX2
// Stores 8 floats at `p` (32-byte aligned when streaming).
template <bool kStream>
inline void store8(float* p, __m256 v) {
  if (kStream) {
    _mm256_stream_ps(p, v);
  } else {
    _mm256_storeu_ps(p, v);
  }
}
#endif

// How the 8 pixels 8k..8k+7 of a segment read their texels.
enum Chunk : uint8_t {
  kMasked,       // bilinear: some east column or south row is past the image (those read 0);
                 // bicubic: some tap is clamped (read through `col`, `row`)
  kInterior,     // bilinear: all four corners of every pixel in the image; bicubic: all 16 taps
  kConsecutive,  // offsets o, o + 1, …, o + 7 (and, bilinear/bicubic, interior): vector loads
};

// Footprints of the pixels of one segment. Bilinear: `offset` = y0·W + x0 of the north-west
// texel, the four weights, and the masks (-1 / 0) of the east column (x0 + 1 < W) and the south
// row (y0 + 1 < H). Nearest: `offset` only. Bicubic: `offset` = (y0-1)·W + (x0-1) of the
// north-west tap (meaningful in interior chunks only), the clamped tap columns `col[k]` =
// clamp(x0-1+k) and row offsets `row[k]` = clamp(y0-1+k)·W, and the weights `wx[k]`, `wy[k]`.
struct Footprints {
  alignas(32) int32_t offset[kSegment];
  alignas(32) float nw[kSegment], ne[kSegment], sw[kSegment], se[kSegment];
  alignas(32) int32_t east[kSegment], south[kSegment];
  alignas(32) int32_t col[4][kSegment], row[4][kSegment];
  alignas(32) float wx[4][kSegment], wy[4][kSegment];
  Chunk chunk[kSegment / kLanes];
};

// One axis of the reference's coordinate arithmetic: the clamped source index of position s.
struct Axis {
  float size;        // W or H
  float half_size;   // size/2
  float last;        // size - 1
  float high;        // size - 0.5, the inside bound
  float cubic_high;  // size + 1, bicubic's bound of i

  explicit Axis(int64_t n)
      : size(static_cast<float>(n)),
        half_size(static_cast<float>(n) / 2),
        last(static_cast<float>(n - 1)),
        high(static_cast<float>(n) - 0.5f),
        cubic_high(static_cast<float>(n) + 1.0f) {}

  // g = (2s + 1)/size - 1; i = (g + 1)·size/2 - 0.5 (one fma), not clamped.
  float unnormalized(float s) const {
    const float g = (2.0f * s + 1.0f) / size - 1.0f;
    return std::fma(g + 1.0f, half_size, -0.5f);
  }
  // i clamped to [0, size - 1] with NaN -> 0 (bilinear, nearest).
  float index(float s) const {
    const float i = unnormalized(s);
    const float low = i > 0.0f ? i : 0.0f;  // NaN fails the test: 0
    return low < last ? low : last;
  }
  // i clamped to [-2, size + 1] with NaN -> -2 (bicubic).
  float cubic_index(float s) const {
    const float i = unnormalized(s);
    const float low = i > -2.0f ? i : -2.0f;  // NaN fails the test: -2
    return low < cubic_high ? low : cubic_high;
  }
  bool contains(float s) const { return s > -0.5f && s < high; }
};

// PyTorch's cubic convolution weights (A = -0.75) of the taps -1, 0, 1, 2 at fraction t, each
// operation rounded like get_cubic_coefficients' (the library is built without contraction).
constexpr float kCubicA = -0.75f;
inline float cubic_outer(float x) {  // 1 <= x <= 2
  const float A = kCubicA;
  return ((A * x - 5.0f * A) * x + 8.0f * A) * x - 4.0f * A;
}
inline float cubic_inner(float x) {  // 0 <= x <= 1
  const float A = kCubicA;
  return ((A + 2.0f) * x - (A + 3.0f)) * x * x + 1.0f;
}

#if QF_HAVE_AVX2
struct Axis8 {
  __m256 size, half_size, last, high, cubic_high;
  explicit Axis8(const Axis& a)
      : size(_mm256_set1_ps(a.size)),
        half_size(_mm256_set1_ps(a.half_size)),
        last(_mm256_set1_ps(a.last)),
        high(_mm256_set1_ps(a.high)),
        cubic_high(_mm256_set1_ps(a.cubic_high)) {}

  __m256 unnormalized(__m256 s) const {
    const __m256 one = _mm256_set1_ps(1.0f);
    const __m256 g = _mm256_sub_ps(
        _mm256_div_ps(_mm256_add_ps(_mm256_mul_ps(_mm256_set1_ps(2.0f), s), one), size), one);
    return _mm256_fmadd_ps(_mm256_add_ps(g, one), half_size, _mm256_set1_ps(-0.5f));
  }
  __m256 index(__m256 s) const {
    // max returns its second operand when either is NaN: NaN -> 0.
    return _mm256_min_ps(_mm256_max_ps(unnormalized(s), _mm256_setzero_ps()), last);
  }
  // Axis::cubic_index (NaN -> -2 likewise).
  __m256 cubic_index(__m256 s) const {
    return _mm256_min_ps(_mm256_max_ps(unnormalized(s), _mm256_set1_ps(-2.0f)), cubic_high);
  }
  __m256 contains(__m256 s) const {
    return _mm256_and_ps(_mm256_cmp_ps(s, _mm256_set1_ps(-0.5f), _CMP_GT_OQ),
                         _mm256_cmp_ps(s, high, _CMP_LT_OQ));
  }
};

// 0, 1, …, 7 (a function, not a global: the library runs no AVX2 code when it is loaded).
inline __m256i iota() { return _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7); }

// cubic_outer, cubic_inner of 8 values, operation by operation the same.
inline __m256 cubic_outer8(__m256 x) {
  const __m256 A = _mm256_set1_ps(kCubicA);
  __m256 r = _mm256_sub_ps(_mm256_mul_ps(A, x), _mm256_set1_ps(5.0f * kCubicA));
  r = _mm256_add_ps(_mm256_mul_ps(r, x), _mm256_set1_ps(8.0f * kCubicA));
  return _mm256_sub_ps(_mm256_mul_ps(r, x), _mm256_set1_ps(4.0f * kCubicA));
}
inline __m256 cubic_inner8(__m256 x) {
  const __m256 r = _mm256_sub_ps(_mm256_mul_ps(_mm256_set1_ps(kCubicA + 2.0f), x),
                                 _mm256_set1_ps(kCubicA + 3.0f));
  return _mm256_add_ps(_mm256_mul_ps(_mm256_mul_ps(r, x), x), _mm256_set1_ps(1.0f));
}
#endif

// footprints_scalar of bicubic.
void footprints_bicubic_scalar(const WarpJob& j, const float* mx, const float* my, int64_t y,
                               int64_t x, int64_t begin, int64_t count, float* inside,
                               Footprints& f) {
  const Axis ax(j.W), ay(j.H);
  const int32_t W = static_cast<int32_t>(j.W), H = static_cast<int32_t>(j.H);
  for (int64_t i = begin; i < count; ++i) {
    const float sx = static_cast<float>(x + i) + mx[i];
    const float sy = static_cast<float>(y) + my[i];
    inside[i] = ax.contains(sx) && ay.contains(sy) ? 1.0f : 0.0f;
    const float ix = ax.cubic_index(sx), iy = ay.cubic_index(sy);
    const float x0 = std::floor(ix), y0 = std::floor(iy);
    const float tx = ix - x0, ty = iy - y0;
    f.wx[0][i] = cubic_outer(tx + 1.0f);
    f.wx[1][i] = cubic_inner(tx);
    f.wx[2][i] = cubic_inner(1.0f - tx);
    f.wx[3][i] = cubic_outer(2.0f - tx);
    f.wy[0][i] = cubic_outer(ty + 1.0f);
    f.wy[1][i] = cubic_inner(ty);
    f.wy[2][i] = cubic_inner(1.0f - ty);
    f.wy[3][i] = cubic_outer(2.0f - ty);
    const int32_t x0i = static_cast<int32_t>(x0), y0i = static_cast<int32_t>(y0);  // [-2, n+1]
    for (int32_t k = 0; k < 4; ++k) {
      f.col[k][i] = std::min(std::max(x0i - 1 + k, 0), W - 1);
      f.row[k][i] = std::min(std::max(y0i - 1 + k, 0), H - 1) * W;
    }
  }
}

// Footprints of pixels [x + begin, x + count) of row y (segment positions begin..count), and
// their inside mask (written to `inside`).
void footprints_scalar(const WarpJob& j, const float* mx, const float* my, int64_t y, int64_t x,
                       int64_t begin, int64_t count, float* inside, Footprints& f) {
  const Axis ax(j.W), ay(j.H);
  const int32_t W = static_cast<int32_t>(j.W), H = static_cast<int32_t>(j.H);
  const bool bilinear = j.mode == Mode::kBilinear;
  if (j.mode == Mode::kBicubic) {
    footprints_bicubic_scalar(j, mx, my, y, x, begin, count, inside, f);
    return;
  }
  for (int64_t i = begin; i < count; ++i) {
    const float sx = static_cast<float>(x + i) + mx[i];
    const float sy = static_cast<float>(y) + my[i];
    inside[i] = ax.contains(sx) && ay.contains(sy) ? 1.0f : 0.0f;
    const float ix = ax.index(sx), iy = ay.index(sy);
    if (bilinear) {
      const float x0 = std::floor(ix), y0 = std::floor(iy);
      const float wx = ix - x0, wy = iy - y0;
      const float ex = 1.0f - wx, ey = 1.0f - wy;
      f.nw[i] = ey * ex;
      f.ne[i] = ey * wx;
      f.sw[i] = wy * ex;
      f.se[i] = wy * wx;
      const int32_t x0i = static_cast<int32_t>(x0), y0i = static_cast<int32_t>(y0);
      f.east[i] = x0i + 1 < W ? -1 : 0;
      f.south[i] = y0i + 1 < H ? -1 : 0;
      f.offset[i] = y0i * W + x0i;
    } else {
      f.offset[i] = static_cast<int32_t>(std::nearbyint(iy)) * W +
                    static_cast<int32_t>(std::nearbyint(ix));
    }
  }
}

#if QF_HAVE_AVX2
// The source positions s of pixels x … x+7 of row y (fy = y) and their in-frame mask, written
// to `inside` (both footprint passes start so).
template <bool kStream>
inline void source8(const Axis8& vx, const Axis8& vy, __m256 fy, __m256i lanes, int64_t x,
                    const float* mx, const float* my, float* inside, __m256* sx, __m256* sy) {
  const __m256 px = _mm256_cvtepi32_ps(
      _mm256_add_epi32(_mm256_set1_epi32(static_cast<int32_t>(x)), lanes));
  *sx = _mm256_add_ps(px, _mm256_loadu_ps(mx));
  *sy = _mm256_add_ps(fy, _mm256_loadu_ps(my));
  store8<kStream>(inside, _mm256_and_ps(_mm256_and_ps(vx.contains(*sx), vy.contains(*sy)),
                                        _mm256_set1_ps(1.0f)));
}
#endif

#if QF_HAVE_AVX2
// footprints_bicubic_scalar 8 pixels at a time, from the start of the segment, and the Chunk of
// each 8. Returns the pixels done.
template <bool kStream>
int64_t footprints_bicubic_avx2(const WarpJob& j, const float* mx, const float* my, int64_t y,
                                int64_t x, int64_t count, float* inside, Footprints& f) {
  const Axis ax(j.W), ay(j.H);
  const Axis8 vx(ax), vy(ay);
  const int32_t W = static_cast<int32_t>(j.W), H = static_cast<int32_t>(j.H);
  const __m256 one = _mm256_set1_ps(1.0f), two = _mm256_set1_ps(2.0f);
  const __m256 fy = _mm256_set1_ps(static_cast<float>(y));
  const __m256i width = _mm256_set1_epi32(W), lanes = iota(), zero = _mm256_setzero_si256();
  const __m256i last_x = _mm256_set1_epi32(W - 1), last_y = _mm256_set1_epi32(H - 1);
  // Interior: taps x0-1 … x0+2 in [0, W - 1], i.e. 0 < x0 < W - 2 (and the same of y).
  const __m256i inner_x = _mm256_set1_epi32(W - 2), inner_y = _mm256_set1_epi32(H - 2);
  int64_t i = 0;
  for (; i + kLanes <= count; i += kLanes) {
    __m256 sx, sy;
    source8<kStream>(vx, vy, fy, lanes, x + i, mx + i, my + i, inside + i, &sx, &sy);
    const __m256 ix = vx.cubic_index(sx), iy = vy.cubic_index(sy);
    const __m256 x0 = _mm256_floor_ps(ix), y0 = _mm256_floor_ps(iy);
    const __m256 tx = _mm256_sub_ps(ix, x0), ty = _mm256_sub_ps(iy, y0);
    _mm256_store_ps(f.wx[0] + i, cubic_outer8(_mm256_add_ps(tx, one)));
    _mm256_store_ps(f.wx[1] + i, cubic_inner8(tx));
    _mm256_store_ps(f.wx[2] + i, cubic_inner8(_mm256_sub_ps(one, tx)));
    _mm256_store_ps(f.wx[3] + i, cubic_outer8(_mm256_sub_ps(two, tx)));
    _mm256_store_ps(f.wy[0] + i, cubic_outer8(_mm256_add_ps(ty, one)));
    _mm256_store_ps(f.wy[1] + i, cubic_inner8(ty));
    _mm256_store_ps(f.wy[2] + i, cubic_inner8(_mm256_sub_ps(one, ty)));
    _mm256_store_ps(f.wy[3] + i, cubic_outer8(_mm256_sub_ps(two, ty)));
    const __m256i x0i = _mm256_cvttps_epi32(x0), y0i = _mm256_cvttps_epi32(y0);  // [-2, n+1]
    const __m256i minus1 = _mm256_set1_epi32(-1);
    const __m256i in_x = _mm256_and_si256(_mm256_cmpgt_epi32(x0i, zero),
                                          _mm256_cmpgt_epi32(inner_x, x0i));
    const __m256i in_y = _mm256_and_si256(_mm256_cmpgt_epi32(y0i, zero),
                                          _mm256_cmpgt_epi32(inner_y, y0i));
    const bool interior = _mm256_testc_si256(_mm256_and_si256(in_x, in_y), minus1);
    if (!interior) {  // the clamped taps, read by kMasked chunks only
      for (int32_t k = 0; k < 4; ++k) {
        const __m256i d = _mm256_set1_epi32(k - 1);
        const __m256i cx =
            _mm256_min_epi32(_mm256_max_epi32(_mm256_add_epi32(x0i, d), zero), last_x);
        const __m256i cy =
            _mm256_min_epi32(_mm256_max_epi32(_mm256_add_epi32(y0i, d), zero), last_y);
        _mm256_store_si256(reinterpret_cast<__m256i*>(f.col[k] + i), cx);
        _mm256_store_si256(reinterpret_cast<__m256i*>(f.row[k] + i),
                           _mm256_mullo_epi32(cy, width));
      }
    }
    const __m256i offset = _mm256_add_epi32(
        _mm256_mullo_epi32(_mm256_add_epi32(y0i, minus1), width), _mm256_add_epi32(x0i, minus1));
    _mm256_store_si256(reinterpret_cast<__m256i*>(f.offset + i), offset);
    const __m256i expected =
        _mm256_add_epi32(_mm256_broadcastd_epi32(_mm256_castsi256_si128(offset)), lanes);
    const bool consecutive = _mm256_testc_si256(_mm256_cmpeq_epi32(offset, expected), minus1);
    f.chunk[i / kLanes] = !interior ? kMasked : consecutive ? kConsecutive : kInterior;
  }
  return i;
}

// footprints_scalar 8 pixels at a time, from the start of the segment; also sorts each 8 into a
// Chunk. Returns the pixels done.
template <bool kStream>
int64_t footprints_avx2(const WarpJob& j, const float* mx, const float* my, int64_t y,
                        int64_t x, int64_t count, float* inside, Footprints& f) {
  if (j.mode == Mode::kBicubic) {
    return footprints_bicubic_avx2<kStream>(j, mx, my, y, x, count, inside, f);
  }
  const Axis ax(j.W), ay(j.H);  // vectorised as Axis8
  const int32_t W = static_cast<int32_t>(j.W), H = static_cast<int32_t>(j.H);
  const bool bilinear = j.mode == Mode::kBilinear;
  int64_t i = 0;
  const Axis8 vx(ax), vy(ay);
  const __m256 one = _mm256_set1_ps(1.0f), fy = _mm256_set1_ps(static_cast<float>(y));
  const __m256i width = _mm256_set1_epi32(W), lanes = iota();
  for (; i + kLanes <= count; i += kLanes) {
    __m256 sx, sy;
    source8<kStream>(vx, vy, fy, lanes, x + i, mx + i, my + i, inside + i, &sx, &sy);
    const __m256 ix = vx.index(sx), iy = vy.index(sy);
    __m256i offset;
    bool interior = true;
    if (bilinear) {
      const __m256 x0 = _mm256_floor_ps(ix), y0 = _mm256_floor_ps(iy);
      const __m256 wx = _mm256_sub_ps(ix, x0), wy = _mm256_sub_ps(iy, y0);
      const __m256 ex = _mm256_sub_ps(one, wx), ey = _mm256_sub_ps(one, wy);
      _mm256_store_ps(f.nw + i, _mm256_mul_ps(ey, ex));
      _mm256_store_ps(f.ne + i, _mm256_mul_ps(ey, wx));
      _mm256_store_ps(f.sw + i, _mm256_mul_ps(wy, ex));
      _mm256_store_ps(f.se + i, _mm256_mul_ps(wy, wx));
      const __m256i x0i = _mm256_cvttps_epi32(x0), y0i = _mm256_cvttps_epi32(y0);
      const __m256i east = _mm256_cmpgt_epi32(width, _mm256_add_epi32(x0i, _mm256_set1_epi32(1)));
      const __m256i south =
          _mm256_cmpgt_epi32(_mm256_set1_epi32(H), _mm256_add_epi32(y0i, _mm256_set1_epi32(1)));
      _mm256_store_si256(reinterpret_cast<__m256i*>(f.east + i), east);
      _mm256_store_si256(reinterpret_cast<__m256i*>(f.south + i), south);
      offset = _mm256_add_epi32(_mm256_mullo_epi32(y0i, width), x0i);
      interior = _mm256_testc_si256(_mm256_and_si256(east, south), _mm256_set1_epi32(-1));
    } else {
      const __m256i xi = _mm256_cvttps_epi32(
          _mm256_round_ps(ix, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC));
      const __m256i yi = _mm256_cvttps_epi32(
          _mm256_round_ps(iy, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC));
      offset = _mm256_add_epi32(_mm256_mullo_epi32(yi, width), xi);
    }
    _mm256_store_si256(reinterpret_cast<__m256i*>(f.offset + i), offset);
    const __m256i expected =
        _mm256_add_epi32(_mm256_broadcastd_epi32(_mm256_castsi256_si128(offset)), lanes);
    const bool consecutive =
        _mm256_testc_si256(_mm256_cmpeq_epi32(offset, expected), _mm256_set1_epi32(-1));
    f.chunk[i / kLanes] = !interior ? kMasked : consecutive ? kConsecutive : kInterior;
  }
  return i;
}
#endif

// Footprints of pixels [x, x + count) of row y, and their inside mask (written to `inside`).
template <bool kStream>
void footprints(const WarpJob& j, const float* mx, const float* my, int64_t y, int64_t x,
                int64_t count, float* inside, Footprints& f) {
  int64_t i = 0;
#if QF_HAVE_AVX2
  if (simd_enabled()) i = footprints_avx2<kStream>(j, mx, my, y, x, count, inside, f);
#endif
  footprints_scalar(j, mx, my, y, x, i, count, inside, f);
}

#if QF_HAVE_AVX2
// The texel pairs (p[o], p[o + 1]) at the 8 offsets o of `offset`, as (first, second) vectors:
// two 4-lane gathers of 8-byte elements instead of two 8-lane gathers of 4-byte ones.
inline void gather_pairs(const float* p, __m256i offset, __m256* first, __m256* second) {
  // The gathers read 8 unaligned bytes at p + 4·o: the element type is only the width.
  // (The masked form with every lane on: the plain one leaves its pass-through operand
  // undefined, which GCC reports as an uninitialised read.)
  const double* base = reinterpret_cast<const double*>(p);
  const __m256d zero = _mm256_setzero_pd(), all = _mm256_castsi256_pd(_mm256_set1_epi64x(-1));
  const __m256 lo = _mm256_castpd_ps(
      _mm256_mask_i32gather_pd(zero, base, _mm256_castsi256_si128(offset), all, 4));
  const __m256 hi = _mm256_castpd_ps(
      _mm256_mask_i32gather_pd(zero, base, _mm256_extracti128_si256(offset, 1), all, 4));
  // lo = a0 b0 a1 b1 | a2 b2 a3 b3, hi = a4 b4 … -> a0 a1 a4 a5 | a2 a3 a6 a7 -> a0 … a7
  const __m256 a = _mm256_shuffle_ps(lo, hi, _MM_SHUFFLE(2, 0, 2, 0));
  const __m256 b = _mm256_shuffle_ps(lo, hi, _MM_SHUFFLE(3, 1, 3, 1));
  *first = _mm256_castpd_ps(_mm256_permute4x64_pd(_mm256_castps_pd(a), _MM_SHUFFLE(3, 1, 2, 0)));
  *second =
      _mm256_castpd_ps(_mm256_permute4x64_pd(_mm256_castps_pd(b), _MM_SHUFFLE(3, 1, 2, 0)));
}
#endif

// out[begin..count) = bilinear samples of `plane` (one channel, H·W floats) at the footprints:
// corners past the last column or row read 0.
void sample_bilinear_scalar(const float* plane, int64_t W, const Footprints& f, int64_t begin,
                            int64_t count, float* out) {
  for (int64_t i = begin; i < count; ++i) {
    const float* p = plane + f.offset[i];
    const bool e = f.east[i] != 0, s = f.south[i] != 0;
    const float b = e ? p[1] : 0.0f;
    const float c = s ? p[W] : 0.0f;
    const float d = e && s ? p[W + 1] : 0.0f;
    float r = f.nw[i] * p[0];
    r = std::fma(b, f.ne[i], r);
    r = std::fma(c, f.sw[i], r);
    out[i] = std::fma(d, f.se[i], r);
  }
}

#if QF_HAVE_AVX2
// sample_bilinear_scalar 8 pixels at a time (vector loads, pair gathers or masked gathers by
// Chunk); returns the pixels done.
template <bool kStream>
int64_t sample_bilinear_avx2(const float* plane, int64_t W, const Footprints& f, int64_t count,
                             float* out) {
  int64_t i = 0;
  const __m256 zero = _mm256_setzero_ps();
  const float* east = plane + 1;
  const float* south = plane + W;
  const float* south_east = plane + W + 1;
  for (; i + kLanes <= count; i += kLanes) {
    __m256 a, b, c, d;  // nw, ne, sw, se texels
    const Chunk chunk = f.chunk[i / kLanes];
    if (chunk == kConsecutive) {
      const float* p = plane + f.offset[i];
      a = _mm256_loadu_ps(p);
      b = _mm256_loadu_ps(p + 1);
      c = _mm256_loadu_ps(p + W);
      d = _mm256_loadu_ps(p + W + 1);
    } else if (chunk == kInterior) {
      const __m256i offset = _mm256_load_si256(reinterpret_cast<const __m256i*>(f.offset + i));
      gather_pairs(plane, offset, &a, &b);
      gather_pairs(south, offset, &c, &d);
    } else {
      // Corners past the last column or row are not read (masked lanes of a gather never are)
      // and count as 0, like the reference.
      const __m256i offset = _mm256_load_si256(reinterpret_cast<const __m256i*>(f.offset + i));
      const __m256i e = _mm256_load_si256(reinterpret_cast<const __m256i*>(f.east + i));
      const __m256i s = _mm256_load_si256(reinterpret_cast<const __m256i*>(f.south + i));
      a = _mm256_i32gather_ps(plane, offset, 4);
      b = _mm256_mask_i32gather_ps(zero, east, offset, _mm256_castsi256_ps(e), 4);
      c = _mm256_mask_i32gather_ps(zero, south, offset, _mm256_castsi256_ps(s), 4);
      d = _mm256_mask_i32gather_ps(zero, south_east, offset,
                                   _mm256_castsi256_ps(_mm256_and_si256(e, s)), 4);
    }
    __m256 r = _mm256_mul_ps(_mm256_load_ps(f.nw + i), a);
    r = _mm256_fmadd_ps(b, _mm256_load_ps(f.ne + i), r);
    r = _mm256_fmadd_ps(c, _mm256_load_ps(f.sw + i), r);
    r = _mm256_fmadd_ps(d, _mm256_load_ps(f.se + i), r);
    store8<kStream>(out + i, r);
  }
  return i;
}
#endif

// out[begin..count) = the texels of `plane` at the footprints (nearest).
void sample_nearest_scalar(const float* plane, const Footprints& f, int64_t begin, int64_t count,
                           float* out) {
  for (int64_t i = begin; i < count; ++i) out[i] = plane[f.offset[i]];
}

#if QF_HAVE_AVX2
// sample_nearest_scalar 8 pixels at a time; returns the pixels done.
template <bool kStream>
int64_t sample_nearest_avx2(const float* plane, const Footprints& f, int64_t count, float* out) {
  int64_t i = 0;
  for (; i + kLanes <= count; i += kLanes) {
    const __m256 v =
        f.chunk[i / kLanes] == kConsecutive
            ? _mm256_loadu_ps(plane + f.offset[i])
            : _mm256_i32gather_ps(
                  plane, _mm256_load_si256(reinterpret_cast<const __m256i*>(f.offset + i)), 4);
    store8<kStream>(out + i, v);
  }
  return i;
}
#endif

// out[begin..count) = bicubic samples of `plane` (one channel, H·W floats) at the footprints.
void sample_bicubic_scalar(const float* plane, const Footprints& f, int64_t begin, int64_t count,
                           float* out) {
  for (int64_t i = begin; i < count; ++i) {
    float r = 0.0f;
    for (int k = 0; k < 4; ++k) {
      const float* p = plane + f.row[k][i];
      float v = f.wx[0][i] * p[f.col[0][i]];
      v = std::fma(p[f.col[1][i]], f.wx[1][i], v);
      v = std::fma(p[f.col[2][i]], f.wx[2][i], v);
      v = std::fma(p[f.col[3][i]], f.wx[3][i], v);
      r = k == 0 ? f.wy[0][i] * v : std::fma(v, f.wy[k][i], r);
    }
    out[i] = r;
  }
}

#if QF_HAVE_AVX2
// sample_bicubic_scalar 8 pixels at a time (vector loads, pair gathers or gathers of the clamped
// taps by Chunk); returns the pixels done.
template <bool kStream>
int64_t sample_bicubic_avx2(const float* plane, int64_t W, const Footprints& f, int64_t count,
                            float* out) {
  int64_t i = 0;
  for (; i + kLanes <= count; i += kLanes) {
    const Chunk chunk = f.chunk[i / kLanes];
    const __m256i offset = _mm256_load_si256(reinterpret_cast<const __m256i*>(f.offset + i));
    const __m256 wx0 = _mm256_load_ps(f.wx[0] + i), wx1 = _mm256_load_ps(f.wx[1] + i);
    const __m256 wx2 = _mm256_load_ps(f.wx[2] + i), wx3 = _mm256_load_ps(f.wx[3] + i);
    __m256 r = _mm256_setzero_ps();
    for (int k = 0; k < 4; ++k) {
      __m256 a, b, c, d;  // the taps x0-1 … x0+2 of row y0-1+k
      if (chunk == kConsecutive) {
        const float* p = plane + f.offset[i] + k * W;
        a = _mm256_loadu_ps(p);
        b = _mm256_loadu_ps(p + 1);
        c = _mm256_loadu_ps(p + 2);
        d = _mm256_loadu_ps(p + 3);
      } else if (chunk == kInterior) {
        const float* p = plane + k * W;
        gather_pairs(p, offset, &a, &b);
        gather_pairs(p + 2, offset, &c, &d);
      } else {
        const __m256i row = _mm256_load_si256(reinterpret_cast<const __m256i*>(f.row[k] + i));
        const auto tap = [&](int t) {
          const __m256i col = _mm256_load_si256(reinterpret_cast<const __m256i*>(f.col[t] + i));
          return _mm256_i32gather_ps(plane, _mm256_add_epi32(row, col), 4);
        };
        a = tap(0);
        b = tap(1);
        c = tap(2);
        d = tap(3);
      }
      __m256 v = _mm256_mul_ps(wx0, a);
      v = _mm256_fmadd_ps(b, wx1, v);
      v = _mm256_fmadd_ps(c, wx2, v);
      v = _mm256_fmadd_ps(d, wx3, v);
      const __m256 wy = _mm256_load_ps(f.wy[k] + i);
      r = k == 0 ? _mm256_mul_ps(wy, v) : _mm256_fmadd_ps(v, wy, r);
    }
    store8<kStream>(out + i, r);
  }
  return i;
}
#endif

// out[0..count) = `mode`'s samples of `plane` (one channel, H·W floats) at the footprints: the
// AVX2 path takes what it can, the scalar one the rest.
template <bool kStream>
void sample(Mode mode, const float* plane, int64_t W, const Footprints& f, int64_t count,
            float* out) {
  int64_t i = 0;
#if QF_HAVE_AVX2
  if (simd_enabled()) {
    switch (mode) {
      case Mode::kBilinear: i = sample_bilinear_avx2<kStream>(plane, W, f, count, out); break;
      case Mode::kNearest: i = sample_nearest_avx2<kStream>(plane, f, count, out); break;
      case Mode::kBicubic: i = sample_bicubic_avx2<kStream>(plane, W, f, count, out); break;
    }
  }
#endif
  switch (mode) {
    case Mode::kBilinear: sample_bilinear_scalar(plane, W, f, i, count, out); break;
    case Mode::kNearest: sample_nearest_scalar(plane, f, i, count, out); break;
    case Mode::kBicubic: sample_bicubic_scalar(plane, f, i, count, out); break;
  }
}

// Task: output rows [ya, yb) of image n.
template <bool kStream>
void warp_rows(const WarpJob& j, int64_t task) {
  const int64_t n = task / j.bands, band = task % j.bands;
  const int64_t ya = band_start(band, j.bands, j.H), yb = band_start(band + 1, j.bands, j.H);
  const int64_t plane = j.H * j.W;
  const float* image = j.image + n * j.C * plane;
  float* warped = j.warped + n * j.C * plane;
  Footprints f;
  for (int64_t y = ya; y < yb; ++y) {
    const float* mx = j.motion + (2 * n * j.H + y) * j.W;
    const float* my = mx + plane;
    float* inside = j.inside + (n * j.H + y) * j.W;
    for (int64_t x = 0; x < j.W; x += kSegment) {
      const int64_t count = std::min(kSegment, j.W - x);
      footprints<kStream>(j, mx + x, my + x, y, x, count, inside + x, f);
      const int64_t at = y * j.W + x;
      for (int64_t c = 0; c < j.C; ++c) {
        sample<kStream>(j.mode, image + c * plane, j.W, f, count, warped + c * plane + at);
      }
    }
  }
}

void warp_band(const WarpJob& j, int64_t task) {
#if QF_HAVE_AVX2
  if (j.stream) {
    warp_rows<true>(j, task);
    _mm_sfence();  // the streaming stores are done before the task reports done
    return;
  }
#endif
  warp_rows<false>(j, task);
}

bool line_aligned(const void* p) { return (reinterpret_cast<uintptr_t>(p) & 63) == 0; }

// mode: 0 bilinear, 1 nearest, 2 bicubic.
OrtStatus* read_mode(const ort::Api& api, const char* op, const OrtKernelInfo* info, Mode* out) {
  int64_t mode = -1;
  if (OrtStatus* s = get_int_attribute(api, op, info, "mode", &mode)) return s;
  if (mode != static_cast<int64_t>(Mode::kBilinear) &&
      mode != static_cast<int64_t>(Mode::kNearest) &&
      mode != static_cast<int64_t>(Mode::kBicubic)) {
    return op_error(api, op,
                    "attribute mode must be 0 (bilinear), 1 (nearest) or 2 (bicubic), got " +
                        std::to_string(mode));
  }
  *out = static_cast<Mode>(mode);
  return nullptr;
}

struct BackwardWarp : Kernel<BackwardWarp, Mode, read_mode> {
  static constexpr const char* kName = "BackwardWarp";
  static constexpr const char* kInputNames[] = {"image", "motion"};
  static constexpr size_t kOutputs = 2;  // warped, inside

  OrtStatus* Run(const ort::Api& api, OrtKernelContext* ctx, const FloatInputs<2>& in) const {
    const float* image = in[0].data;
    const float* motion = in[1].data;
    const Shape& is = in[0].shape;
    if (OrtStatus* s = check_image_inputs(api, kName, kInputNames, in, {kAnyChannels, 2})) {
      return s;
    }
    const int64_t N = is[0], C = is[1], H = is[2], W = is[3];
    // Texel offsets inside one plane are int32 (the gathers' index type).
    if (H * W > INT32_MAX - W - 1) {
      return op_error(api, kName, "image planes of more than 2^31 pixels are not supported, got " +
                                      is.str());
    }
    const Shape inside_shape = with_channels(is, 1);
    float* warped = nullptr;
    float* inside = nullptr;
    if (OrtStatus* s = get_float_output(api, kName, ctx, 0, "warped", is, &warped)) return s;
    if (OrtStatus* s = get_float_output(api, kName, ctx, 1, "inside", inside_shape, &inside)) {
      return s;
    }
    const int64_t bands = band_count(H, N, kMinRowsPerBand);
    // Streaming stores need whole, aligned cache lines: rows of a multiple of 16 floats (every
    // segment then is one too) from line-aligned tensors.
    const bool stream = QF_HAVE_AVX2 && simd_enabled() && W % 16 == 0 &&
                        line_aligned(warped) && line_aligned(inside);
    const WarpJob job{image, motion, warped, inside, C, H, W, bands, attributes_, stream};
    auto task = [&job](size_t i) { warp_band(job, static_cast<int64_t>(i)); };
    return run_tasks(api, kName, ctx, N * bands, task);
  }
};

}  // namespace

const OrtCustomOp* backward_warp_op() { return CustomOp<BackwardWarp>::get(); }

}  // namespace qf
