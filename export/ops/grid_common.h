// Bilateral-grid coordinates shared by BilateralSplat and BilateralSlice, exactly as
// docs/grid-math.md (Meng et al. 2020, supplement §5, with the [qf] changes), plus the small
// building blocks of the fast paths: per-axis tap tables, per-thread scratch memory, AVX2 helpers.
//
// Storage order inside the ops (not the tensors'): a grid row `v` is kept as [z][gx][P] with the
// P = C + 1 values of one cell (C channels, then β or the mask) next to each other, so that the
// two x-neighbour cells a pixel touches are 2P contiguous floats: for C = 3 one AVX register.
// Everything is float32 and computed operation by operation like quietframe.model.grid, so the
// tent weights are the same floats on both sides (the spatial ones come from double there).
#pragma once

#include <algorithm>
#include <climits>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstdio>
#include <cstring>
#include <new>
#include <string>
#include <vector>

#include "kernel_support.h"
#include "runtime_support.h"
#include "simd.h"

namespace qf::grid {

constexpr double kTentEpsilon = 1e-7;  // supplement eq. 5
constexpr float kGuideLevels = 255.0f;  // the guide in [0, 1] spans 256 levels

// tent(d) = max(1 - sqrt(d² + ε), 0)  (supplement eq. 4–5)
inline float tent(float d) {
  const float t = 1.0f - std::sqrt(d * d + static_cast<float>(kTentEpsilon));
  return t > 0.0f ? t : 0.0f;
}
inline double tent(double d) {
  const double t = 1.0 - std::sqrt(d * d + kTentEpsilon);
  return t > 0.0 ? t : 0.0;
}

// cells(n, σs) = floor((n - 0.5)/σs - 0.5) + 3 = (2n - 1 - σs) // (2σs) + 3 (floor division)
inline int64_t spatial_cells(int64_t pixels, int64_t sigma_s) {
  const int64_t num = 2 * pixels - 1 - sigma_s;
  const int64_t den = 2 * sigma_s;
  int64_t q = num / den;
  if (num % den != 0 && num < 0) --q;
  return q + 3;
}

// D = floor(255/σr - 0.5) + 3
inline int64_t range_cells(float sigma_r) {
  return static_cast<int64_t>(std::floor(255.0 / static_cast<double>(sigma_r) - 0.5)) + 3;
}

// A coordinate c touches cells u0 = floor(c - 0.5) and u0 + 1 (centres at u + 0.5), stored at
// index u + 1. Writes the storage index of the first cell and the two tent weights. The index
// is clamped to [0, last_first] so that rounding can never address a cell past the grid (the
// weight of a clamped-away cell is 0 anyway).
inline void taps(float c, int32_t last_first, int32_t* first, float* w0, float* w1) {
  int32_t i = static_cast<int32_t>(std::floor(c - 0.5f)) + 1;
  i = i < 0 ? 0 : (i > last_first ? last_first : i);
  const float u = static_cast<float>(i - 1);
  *first = i;
  *w0 = tent(c - (u + 0.5f));
  *w1 = tent(c - (u + 1.5f));
}

// [qf] image values that are NaN or ±Inf count as 0.
inline float finite_or_zero(float v) {
  uint32_t bits;
  std::memcpy(&bits, &v, sizeof bits);
  return (bits & 0x7f800000u) == 0x7f800000u ? 0.0f : v;
}

// The range axis: cz = 255·g/σr. When σr is a power of two, multiplying by 1/σr is exact (the
// same float as the division) and much cheaper.
struct RangeAxis {
  float sigma_r;
  float inverse;
  bool exact_inverse;
  int32_t last_first;  // D - 2

  RangeAxis(float sigma_r_, int64_t depth)
      : sigma_r(sigma_r_), inverse(1.0f / sigma_r_), last_first(static_cast<int32_t>(depth - 2)) {
    int exponent = 0;
    exact_inverse = std::frexp(sigma_r, &exponent) == 0.5f;
  }
};

// Writes output streams piece by piece, each piece continuing the previous one of its stream
// (here: the rows of one grid plane, one after the other), with streaming stores of whole cache
// lines. Output that is read again only much later then skips the cache and the read of every
// line before it is written; the part line at the end of a piece waits in `pending` until the
// next piece completes it, because a line written in parts by streaming stores is slow.
class LineWriter {
 public:
  static constexpr int64_t kLine = 16;  // floats per 64-byte cache line

  struct Pending {
    alignas(64) float data[kLine];
    float* line = nullptr;  // where the line starts, null for none
    int64_t count = 0;      // floats of it in data
  };

  explicit LineWriter(Pending* pending, int64_t streams) : pending_(pending), streams_(streams) {
    for (int64_t i = 0; i < streams_; ++i) pending_[i] = Pending{};
  }

  void write(int64_t stream, float* dst, const float* src, int64_t count) {
    Pending& p = pending_[stream];
    int64_t i = 0;
    if (p.line != nullptr && p.line + p.count == dst) {
      for (; i < count && p.count < kLine; ++i) p.data[p.count++] = src[i];
      if (p.count < kLine) return;
      store_line(p.line, p.data);
      p.line = nullptr;
    } else {
      flush(p);  // (not a continuation: never the case for rows written in order)
      for (; i < count && (reinterpret_cast<uintptr_t>(dst + i) & 63) != 0; ++i) dst[i] = src[i];
    }
    for (; i + kLine <= count; i += kLine) store_line(dst + i, src + i);
    if (i < count) {
      p.line = dst + i;
      p.count = count - i;
      std::memcpy(p.data, src + i, sizeof(float) * p.count);
    }
  }

  // Writes the part lines still pending with ordinary stores, and orders the streaming stores
  // before whatever this thread does next (such as reporting the task done).
  void finish() {
    for (int64_t i = 0; i < streams_; ++i) flush(pending_[i]);
#if QF_HAVE_AVX2
    _mm_sfence();
#endif
  }

 private:
  static void flush(Pending& p) {
    if (p.line != nullptr) std::memcpy(p.line, p.data, sizeof(float) * p.count);
    p.line = nullptr;
  }

  static void store_line(float* dst, const float* src) {  // dst: 64-byte aligned
#if QF_HAVE_AVX2
    _mm256_stream_ps(dst, _mm256_loadu_ps(src));
    _mm256_stream_ps(dst + 8, _mm256_loadu_ps(src + 8));
#else
    std::memcpy(dst, src, sizeof(float) * kLine);
#endif
  }

  Pending* pending_;
  int64_t streams_;
};

// A hint to bring the line of `address` into the cache (never faults, any address).
inline void prefetch(const void* address) {
#if defined(__GNUC__)
  __builtin_prefetch(address, 0, 3);
#else
  (void)address;
#endif
}

#if QF_HAVE_AVX2
// 8 cells of 4 values (32 contiguous floats) -> 4 vectors, value k of cells 0..7 in out[k].
inline void transpose_cells_4x8(const float* cells, __m256 out[4]) {
  const __m256 r0 = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(cells + 0)),
                                         _mm_loadu_ps(cells + 16), 1);
  const __m256 r1 = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(cells + 4)),
                                         _mm_loadu_ps(cells + 20), 1);
  const __m256 r2 = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(cells + 8)),
                                         _mm_loadu_ps(cells + 24), 1);
  const __m256 r3 = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(cells + 12)),
                                         _mm_loadu_ps(cells + 28), 1);
  const __m256 t0 = _mm256_unpacklo_ps(r0, r1);  // a0 a1 b0 b1 | a4 a5 b4 b5
  const __m256 t1 = _mm256_unpackhi_ps(r0, r1);  // c0 c1 d0 d1 | c4 c5 d4 d5
  const __m256 t2 = _mm256_unpacklo_ps(r2, r3);  // a2 a3 b2 b3 | a6 a7 b6 b7
  const __m256 t3 = _mm256_unpackhi_ps(r2, r3);  // c2 c3 d2 d3 | c6 c7 d6 d7
  out[0] = _mm256_shuffle_ps(t0, t2, 0x44);      // a0 a1 a2 a3 | a4 a5 a6 a7
  out[1] = _mm256_shuffle_ps(t0, t2, 0xEE);
  out[2] = _mm256_shuffle_ps(t1, t3, 0x44);
  out[3] = _mm256_shuffle_ps(t1, t3, 0xEE);
}

// The inverse: 4 vectors (value k of cells 0..7) -> 8 cells of 4 values.
inline void store_cells_4x8(float* cells, const __m256 in[4]) {
  const __m256 t0 = _mm256_unpacklo_ps(in[0], in[1]);  // a0 b0 a1 b1 | a4 b4 a5 b5
  const __m256 t1 = _mm256_unpackhi_ps(in[0], in[1]);  // a2 b2 a3 b3 | a6 b6 a7 b7
  const __m256 t2 = _mm256_unpacklo_ps(in[2], in[3]);  // c0 d0 c1 d1 | ...
  const __m256 t3 = _mm256_unpackhi_ps(in[2], in[3]);
  const __m256 c04 = _mm256_shuffle_ps(t0, t2, 0x44);  // cell 0 | cell 4
  const __m256 c15 = _mm256_shuffle_ps(t0, t2, 0xEE);  // cell 1 | cell 5
  const __m256 c26 = _mm256_shuffle_ps(t1, t3, 0x44);  // cell 2 | cell 6
  const __m256 c37 = _mm256_shuffle_ps(t1, t3, 0xEE);  // cell 3 | cell 7
  _mm256_storeu_ps(cells + 0, _mm256_permute2f128_ps(c04, c15, 0x20));
  _mm256_storeu_ps(cells + 8, _mm256_permute2f128_ps(c26, c37, 0x20));
  _mm256_storeu_ps(cells + 16, _mm256_permute2f128_ps(c04, c15, 0x31));
  _mm256_storeu_ps(cells + 24, _mm256_permute2f128_ps(c26, c37, 0x31));
}

// Lanes that are NaN or ±Inf set to 0.
inline __m256 finite_or_zero(__m256 v) {
  const __m256 exponent = _mm256_castsi256_ps(_mm256_set1_epi32(0x7f800000));
  const __m256 inf_or_nan = _mm256_cmp_ps(_mm256_and_ps(v, exponent), exponent, _CMP_EQ_OQ);
  return _mm256_andnot_ps(inf_or_nan, v);
}
#endif

// Range taps of one pixel row: for pixel x, zfirst[x] = its first range cell, tz0[x] and tz1[x]
// the tents of it and the next, and offset[x] = (zfirst · GW + first column) · P, the index of
// its first cell in a [z][gx][P] grid row.
struct RowTaps {
  int32_t* zfirst;
  int32_t* offset;
  float* tz0;
  float* tz1;
};

#if QF_HAVE_AVX2
// tent() of 8 lanes with the same operations, so the same floats.
inline __m256 tent8(__m256 d) {
  const __m256 root = _mm256_sqrt_ps(
      _mm256_add_ps(_mm256_mul_ps(d, d), _mm256_set1_ps(static_cast<float>(kTentEpsilon))));
  return _mm256_max_ps(_mm256_sub_ps(_mm256_set1_ps(1.0f), root), _mm256_setzero_ps());
}
#endif

// Fills `out` for pixels [begin, end) of a row with guide values `guide`; `xoffset[x]` = first
// column of pixel x times P, `plane` = GW·P (the offset from one range cell to the next).
inline void row_taps_scalar(const float* guide, int64_t begin, int64_t end,
                            const RangeAxis& range, const int32_t* xoffset, int64_t plane,
                            const RowTaps& out) {
  const bool exact_inverse = range.exact_inverse;
  for (int64_t x = begin; x < end; ++x) {
    // [qf] NaN counts as 0 (it fails `g > 0`), then clamp to [0, 1]; the guide is not biased.
    const float g = guide[x] > 0.0f ? (guide[x] < 1.0f ? guide[x] : 1.0f) : 0.0f;
    const float c = exact_inverse ? (kGuideLevels * g) * range.inverse
                                  : (kGuideLevels * g) / range.sigma_r;
    taps(c, range.last_first, &out.zfirst[x], &out.tz0[x], &out.tz1[x]);
    out.offset[x] = static_cast<int32_t>(out.zfirst[x] * plane + xoffset[x]);
  }
}

#if QF_HAVE_AVX2
// row_taps_scalar for pixels [0, count) 8 at a time, the same floats; returns the pixels done
// (the rest of the row is left to the scalar loop).
inline int64_t row_taps_avx2(const float* guide, int64_t count, const RangeAxis& range,
                             const int32_t* xoffset, int64_t plane, const RowTaps& out) {
  int64_t x = 0;
  const bool exact_inverse = range.exact_inverse;
  const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f);
  const __m256 levels = _mm256_set1_ps(kGuideLevels), half = _mm256_set1_ps(0.5f);
  const __m256 sigma_r = _mm256_set1_ps(range.sigma_r), inverse = _mm256_set1_ps(range.inverse);
  const __m256i last = _mm256_set1_epi32(range.last_first);
  const __m256i stride = _mm256_set1_epi32(static_cast<int32_t>(plane));
  for (; x + 8 <= count; x += 8) {
    // [qf] NaN counts as 0 (max returns its second operand), then clamp to [0, 1].
    const __m256 g = _mm256_min_ps(_mm256_max_ps(_mm256_loadu_ps(guide + x), zero), one);
    const __m256 scaled = _mm256_mul_ps(levels, g);
    const __m256 c = exact_inverse ? _mm256_mul_ps(scaled, inverse)
                                   : _mm256_div_ps(scaled, sigma_r);
    // first = floor(c - 0.5) + 1, at least 0 as c >= 0; u + 0.5 and u + 1.5 of the scalar
    // taps() are the same floats as first - 0.5 and first + 0.5.
    const __m256i first = _mm256_min_epi32(
        _mm256_add_epi32(_mm256_cvttps_epi32(_mm256_floor_ps(_mm256_sub_ps(c, half))),
                         _mm256_set1_epi32(1)),
        last);
    const __m256 f = _mm256_cvtepi32_ps(first);
    _mm256_storeu_ps(out.tz0 + x, tent8(_mm256_sub_ps(c, _mm256_sub_ps(f, half))));
    _mm256_storeu_ps(out.tz1 + x, tent8(_mm256_sub_ps(c, _mm256_add_ps(f, half))));
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(out.zfirst + x), first);
    const __m256i columns = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(xoffset + x));
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(out.offset + x),
                        _mm256_add_epi32(_mm256_mullo_epi32(first, stride), columns));
  }
  return x;
}
#endif

// The taps of pixels [0, count) of a row (see row_taps_scalar).
inline void row_taps(const float* guide, int64_t count, const RangeAxis& range,
                     const int32_t* xoffset, int64_t plane, const RowTaps& out) {
  int64_t x = 0;
#if QF_HAVE_AVX2
  if (simd_enabled()) x = row_taps_avx2(guide, count, range, xoffset, plane, out);
#endif
  row_taps_scalar(guide, x, count, range, xoffset, plane, out);
}

constexpr int64_t kBlock = 8;  // grid columns per block: 8 cells, one AVX register per value

// Taps of every pixel along one spatial axis (computed once per call). `pair` holds
// (w0, w0, w0, w0, w1, w1, w1, w1) per pixel for the 4-value cells of the AVX2 path.
struct AxisTaps {
  std::vector<int32_t> first, offset;  // offset = first · P, the index of the cell in its row
  std::vector<float> w0, w1, pair;
  // begin[u]..begin[u+1]: the pixels whose first cell is u (u in [0, cells)); pixels are sorted
  // by first cell because the coordinate grows with the pixel index.
  std::vector<int64_t> begin;
  // Cells in blocks of kBlock: block b (cells [kBlock·b, kBlock·b + kBlock)) is touched by the
  // pixels [touching[2b], touching[2b + 1]) (first cell in [kBlock·b - 1, kBlock·b + kBlock - 1]).
  std::vector<int64_t> touching;

  void build(int64_t pixels, int64_t sigma_s, int64_t cells, int64_t cell_values = 1) {
    first.resize(pixels);
    offset.resize(pixels);
    w0.resize(pixels);
    w1.resize(pixels);
    pair.resize(pixels * 8);
    begin.assign(cells + 1, pixels);
    for (int64_t p = pixels - 1; p >= 0; --p) {
      // u0 = floor(cx - 0.5), cx = (p + 0.5)/σs, in exact integer form; the weights in double
      // (they do not depend on the data, so rounding to float is their only error).
      const int64_t num = 2 * p + 1 - sigma_s, den = 2 * sigma_s;
      const int64_t u0 = num / den - ((num % den != 0 && num < 0) ? 1 : 0);
      const double c = (static_cast<double>(p) + 0.5) / static_cast<double>(sigma_s);
      first[p] = static_cast<int32_t>(std::clamp<int64_t>(u0 + 1, 0, cells - 2));
      const double u = static_cast<double>(first[p] - 1);
      w0[p] = static_cast<float>(tent(c - (u + 0.5)));
      w1[p] = static_cast<float>(tent(c - (u + 1.5)));
      for (int k = 0; k < 4; ++k) {
        pair[p * 8 + k] = w0[p];
        pair[p * 8 + 4 + k] = w1[p];
      }
      offset[p] = static_cast<int32_t>(first[p] * cell_values);
      begin[first[p]] = p;
    }
    for (int64_t u = cells - 1; u >= 0; --u) begin[u] = std::min(begin[u], begin[u + 1]);
    const int64_t blocks = (cells + kBlock - 1) / kBlock;
    touching.resize(2 * blocks);
    for (int64_t b = 0; b < blocks; ++b) {
      touching[2 * b] = begin[std::max<int64_t>(b * kBlock - 1, 0)];
      touching[2 * b + 1] = begin[std::min((b + 1) * kBlock, cells)];
    }
  }
};

// The range cells [low[b], high[b]] that one pixel row touches in each block b of columns: a
// pixel touches its first range cell and the next (min/max over the block's pixels, vectorised).
inline void block_ranges(const AxisTaps& xs, const int32_t* zfirst, int32_t top, int32_t* low,
                         int32_t* high) {
  const int64_t blocks = static_cast<int64_t>(xs.touching.size() / 2);
  for (int64_t b = 0; b < blocks; ++b) {
    int32_t lo = INT32_MAX, hi = -1;
    for (int64_t x = xs.touching[2 * b]; x < xs.touching[2 * b + 1]; ++x) {
      lo = std::min(lo, zfirst[x]);
      hi = std::max(hi, zfirst[x]);
    }
    low[b] = lo;
    high[b] = std::min(hi + 1, top);
  }
}

// Grid rows per band at least (a band re-reads the pixel rows or grid row at its edge), for
// qf::band_count. The results do not depend on the cut: every cell sums its pixels in the same
// order, every pixel reads the same cells.
constexpr int64_t kMinRowsPerBand = 4;

// ---- per-thread scratch memory ------------------------------------------------------------------

// Grows to the largest request and is kept by its thread for the next call: the hot loops never
// allocate, and pool threads reuse warm memory across frames.
class Scratch {
 public:
  Scratch() = default;
  Scratch(const Scratch&) = delete;
  Scratch& operator=(const Scratch&) = delete;
  ~Scratch() { std::free(data_); }

  // Returns at least `bytes` bytes, 64-byte aligned (contents unspecified).
  char* get(size_t bytes) {
    if (bytes > capacity_) {
      std::free(data_);
      capacity_ = (bytes + 4095) & ~size_t{4095};
      data_ = static_cast<char*>(std::aligned_alloc(64, capacity_));
      if (data_ == nullptr) {
        capacity_ = 0;
        throw std::bad_alloc();
      }
    }
    return data_;
  }

 private:
  char* data_ = nullptr;
  size_t capacity_ = 0;
};

inline Scratch& thread_scratch() {
  thread_local Scratch scratch;
  return scratch;
}

// Carves typed, 64-byte aligned arrays out of one block. Run once with base == nullptr to
// measure, then with the block.
class Carver {
 public:
  explicit Carver(char* base) : base_(base) {}
  template <class T>
  T* take(size_t count) {
    used_ = (used_ + 63) & ~size_t{63};
    T* p = base_ ? reinterpret_cast<T*>(base_ + used_) : nullptr;
    used_ += count * sizeof(T);
    return p;
  }
  size_t used() const { return used_ + 64; }

 private:
  char* base_;
  size_t used_ = 0;
};

// One task of a banded grid op: image n, grid rows [va, vb) of `rows`, the tasks being
// (image, band) pairs, `bands` per image.
struct Band {
  int64_t n, va, vb;
};
inline Band task_band(int64_t task, int64_t bands, int64_t rows) {
  const int64_t band = task % bands;
  return {task / bands, band_start(band, bands, rows), band_start(band + 1, bands, rows)};
}

// A carver on this thread's scratch, sized for one S (S(carver, job) lays out its arrays):
// measured by a layout on a carver without a block first.
template <class S, class Job>
inline Carver scratch_carver(const Job& j) {
  Carver measure(nullptr);
  S{measure, j};
  return Carver(thread_scratch().get(measure.used()));
}

// ---- attributes shared by both ops --------------------------------------------------------------

constexpr int64_t kMaxSigmaS = 65536;
constexpr int64_t kMaxRangeCells = 65536;

struct Attributes {
  int64_t sigma_s = 0;  // spatial sampling rate, pixels per cell
  float sigma_r = 0;    // range sampling rate, guide levels (of 256) per cell
  int64_t depth = 0;    // D, range cells
};

// Reads and validates sigma_s, sigma_r and grid_depth, once per kernel.
inline OrtStatus* read_attributes(const ort::Api& api, const char* op, const OrtKernelInfo* info,
                                  Attributes* out) {
  if (OrtStatus* s = get_int_attribute(api, op, info, "sigma_s", &out->sigma_s)) return s;
  if (OrtStatus* s = get_float_attribute(api, op, info, "sigma_r", &out->sigma_r)) return s;
  if (OrtStatus* s = get_int_attribute(api, op, info, "grid_depth", &out->depth)) return s;
  if (out->sigma_s < 1 || out->sigma_s > kMaxSigmaS) {
    return op_error(api, op,
                    "attribute sigma_s must be an integer in [1, " + std::to_string(kMaxSigmaS) +
                        "], got " + std::to_string(out->sigma_s));
  }
  // At most kMaxRangeCells range cells, which also keeps 255/σr far from overflowing.
  const double min_sigma_r = 255.0 / (static_cast<double>(kMaxRangeCells) - 2.5);
  if (!(std::isfinite(out->sigma_r) && out->sigma_r >= min_sigma_r)) {
    return op_error(api, op,
                    "attribute sigma_r must be a finite number >= " + format_float(min_sigma_r) +
                        ", got " + format_float(out->sigma_r));
  }
  const int64_t expected = range_cells(out->sigma_r);
  if (out->depth != expected) {
    return op_error(api, op,
                    "attribute grid_depth=" + std::to_string(out->depth) +
                        " does not match sigma_r=" + format_float(out->sigma_r) +
                        ": floor(255/sigma_r - 0.5) + 3 = " + std::to_string(expected));
  }
  return nullptr;
}

}  // namespace qf::grid
