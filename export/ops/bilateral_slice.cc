// BilateralSlice(grid (N,C,D,GH,GW), weight (N,1,D,GH,GW), guide (N,1,H,W)) -> image (N,C,H,W)
//
// Supplement §5.2, eq. 20–23 with the [qf] mask: m(cell) = 1[weight(cell) > 0],
// μ = Σ t·grid·m, η = Σ t·m over the 8 cells of a pixel, out = μ/η where η > 0 else 0
// (docs/grid-math.md).
//
// Parallel over bands of pixel rows (cut where the first y-cell changes). A task copies the
// cells its pixels read into [z][gx][P] scratch holding (grid·m, m) for two grid rows, so that a
// pixel reads its two x-neighbour cells with one load per (y, z) corner. Cells are copied in
// blocks of 8 columns, and only the blocks some pixel reads: with a smooth guide most range
// cells of a column are never read, and most of the grid is never brought in from memory.
#include <algorithm>
#include <climits>
#include <cstdint>
#include <cstring>
#include <utility>
#include <vector>

#include "grid_common.h"
#include "kernel_support.h"
#include "ops.h"
#include "runtime_support.h"
#include "simd.h"

namespace qf {
namespace {

using grid::AxisTaps;

using grid::kBlock;  // grid columns per copied block
constexpr int64_t kPrefetchLevels = 2;  // range cells ahead that copy_blocks prefetches

struct SliceJob {
  const float* grid;    // (N, C, D, GH, GW)
  const float* weight;  // (N, 1, D, GH, GW)
  const float* guide;   // (N, 1, H, W)
  float* out;           // (N, C, H, W)
  int64_t C, H, W, D, GH, GW;
  const grid::RangeAxis* range;
  const AxisTaps* xs;
  const AxisTaps* ys;
  int64_t bands;
  bool fast;  // C == 3 on an AVX2 build

  int64_t cell_values() const { return fast ? 4 : C + 1; }  // P: C values·m, then m
  int64_t blocks() const { return (GW + kBlock - 1) / kBlock; }
};

// A grid row in scratch. For each block of columns, the range cells [low, high] have been
// copied (none when low > high).
struct RowBuffer {
  float* cells;  // [z][gx][P]
  int32_t* low;  // [block]
  int32_t* high;
  int64_t row = -1;  // the grid row held, -1 for none
};

struct SliceScratch {
  RowBuffer rows[2];
  int32_t* low;       // [block]: range cells read by the current pixel row
  int32_t* high;
  int32_t* new_low;   // [block]: working space of ensure_row
  int32_t* new_high;
  grid::RowTaps taps;  // of the current pixel row
  float* sums;        // [x][P]: μ then η

  SliceScratch(grid::Carver& carver, const SliceJob& j) {
    const int64_t P = j.cell_values();
    const auto W = static_cast<size_t>(j.W), B = static_cast<size_t>(j.blocks());
    for (RowBuffer& r : rows) {
      r.cells = carver.take<float>(static_cast<size_t>(j.D * j.GW * P));
      r.low = carver.take<int32_t>(B);
      r.high = carver.take<int32_t>(B);
    }
    low = carver.take<int32_t>(B);
    high = carver.take<int32_t>(B);
    new_low = carver.take<int32_t>(B);
    new_high = carver.take<int32_t>(B);
    taps.zfirst = carver.take<int32_t>(W);
    taps.offset = carver.take<int32_t>(W);
    taps.tz0 = carver.take<float>(W);
    taps.tz1 = carver.take<float>(W);
    sums = carver.take<float>(W * P);
  }
};

// Cells [begin, end) of range cell z of grid row v: `grid` and `weight` at their column 0,
// `cells` the range cell's [gx][P] scratch. Writes (grid·m, m) with m = 1[weight > 0]; a cell
// that is masked out, or holds a non-finite value, contributes 0 (never NaN from 0·Inf).
void copy_cells_scalar(const SliceJob& j, const float* grid, const float* weight, int64_t begin,
                       int64_t end, float* cells) {
  const int64_t P = j.cell_values();
  const int64_t channel = j.D * j.GH * j.GW;  // from one grid channel to the next
  for (int64_t gx = begin; gx < end; ++gx) {
    float* cell = cells + gx * P;
    const bool m = weight[gx] > 0.0f;  // false for NaN
    for (int64_t c = 0; c < j.C; ++c) {
      cell[c] = m ? grid::finite_or_zero(grid[c * channel + gx]) : 0.0f;
    }
    for (int64_t k = j.C; k < P; ++k) cell[k] = m ? 1.0f : 0.0f;
  }
}

#if QF_HAVE_AVX2
// copy_cells_scalar for 4-value cells (C = 3), 8 columns at a time; returns where it stopped.
int64_t copy_cells_avx2(const SliceJob& j, int64_t z, const float* grid, const float* weight,
                        int64_t begin, int64_t end, float* cells) {
  const int64_t channel = j.D * j.GH * j.GW;
  const __m256 one = _mm256_set1_ps(1.0f);
  // A new row is copied range cell after range cell: ask for the same columns of the next
  // but one now (one core alone does not keep enough reads in flight to fill the memory bus).
  const int64_t ahead = z + kPrefetchLevels < j.D ? kPrefetchLevels * j.GH * j.GW : 0;
  int64_t gx = begin;
  for (; gx + kBlock <= end; gx += kBlock) {
    if (ahead != 0) {
      for (int c = 0; c < 3; ++c) grid::prefetch(grid + c * channel + ahead + gx);
      grid::prefetch(weight + ahead + gx);
    }
    const __m256 m =
        _mm256_cmp_ps(_mm256_loadu_ps(weight + gx), _mm256_setzero_ps(), _CMP_GT_OQ);
    __m256 t[4];
    for (int c = 0; c < 3; ++c) {
      t[c] = _mm256_and_ps(m, grid::finite_or_zero(_mm256_loadu_ps(grid + c * channel + gx)));
    }
    t[3] = _mm256_and_ps(m, one);
    grid::store_cells_4x8(cells + 4 * gx, t);
  }
  return gx;
}
#endif

// Copies blocks [b0, b1) of range cell z of grid row v (image n) into `row` (see
// copy_cells_scalar).
void copy_blocks(const SliceJob& j, int64_t n, int64_t v, int64_t z, int64_t b0, int64_t b1,
                 float* row) {
  const int64_t start = b0 * kBlock, end = std::min(b1 * kBlock, j.GW);
  const float* grid = j.grid + ((n * j.C * j.D + z) * j.GH + v) * j.GW;  // channel 0
  const float* weight = j.weight + ((n * j.D + z) * j.GH + v) * j.GW;
  float* cells = row + z * j.GW * j.cell_values();
  int64_t gx = start;
#if QF_HAVE_AVX2
  if (j.fast) gx = copy_cells_avx2(j, z, grid, weight, start, end, cells);
#endif
  copy_cells_scalar(j, grid, weight, gx, end, cells);
}

// Makes `buffer` hold grid row v with at least the range cells the current pixel row reads
// (s.low/s.high). The copied range of a block only grows, as one interval, and becomes the whole
// column once more than half of it is read (a noisy guide reads everything anyway). A new row is
// copied range cell by range cell, along the rows of the grid planes: the order memory streams
// best in; later rows of pixels usually add a few cells to a few blocks.
void ensure_row(const SliceJob& j, SliceScratch& s, int64_t n, int64_t v, RowBuffer& buffer) {
  const int64_t B = j.blocks();
  const bool fresh = buffer.row != v;
  if (fresh) {
    for (int64_t b = 0; b < B; ++b) {
      buffer.low[b] = INT32_MAX;
      buffer.high[b] = -1;
    }
    buffer.row = v;
  }
  const auto top = static_cast<int32_t>(j.D - 1);
  int32_t first = INT32_MAX, last = -1;
  for (int64_t b = 0; b < B; ++b) {
    int32_t low = buffer.low[b], high = buffer.high[b];
    if (s.low[b] <= s.high[b] && (s.low[b] < low || s.high[b] > high)) {
      low = std::min(low, s.low[b]);
      high = std::max(high, s.high[b]);
      if (2 * (high - low + 1) > j.D) low = 0, high = top;
      first = std::min(first, low);
      last = std::max(last, high);
    }
    s.new_low[b] = low;
    s.new_high[b] = high;
  }
  if (first > last) return;  // nothing missing
  if (fresh) {
    for (int64_t z = first; z <= last; ++z) {
      for (int64_t b = 0; b < B;) {  // runs of blocks that need range cell z
        if (z < s.new_low[b] || z > s.new_high[b]) {
          ++b;
          continue;
        }
        int64_t e = b + 1;
        while (e < B && z >= s.new_low[e] && z <= s.new_high[e]) ++e;
        copy_blocks(j, n, v, z, b, e, buffer.cells);
        b = e;
      }
    }
  } else {
    for (int64_t b = 0; b < B; ++b) {
      const bool had = buffer.low[b] <= buffer.high[b];
      const int64_t below = had ? buffer.low[b] - 1 : s.new_high[b];  // copy [new_low, below]
      for (int64_t z = s.new_low[b]; z <= below; ++z) {
        copy_blocks(j, n, v, z, b, b + 1, buffer.cells);
      }
      for (int64_t z = had ? buffer.high[b] + 1 : s.new_high[b] + 1; z <= s.new_high[b]; ++z) {
        copy_blocks(j, n, v, z, b, b + 1, buffer.cells);
      }
    }
  }
  std::swap(buffer.low, s.new_low);
  std::swap(buffer.high, s.new_high);
}

// μ and η of one pixel row from grid rows `lo` (its first y-cell, weight ty0) and `hi` (ty1),
// into s.sums.
void gather_row_scalar(const SliceJob& j, const SliceScratch& s, float ty0, float ty1,
                       const float* lo, const float* hi) {
  const AxisTaps& xs = *j.xs;
  const int64_t P = j.cell_values();
  const int64_t zstride = j.GW * P;
  const int32_t* offset = s.taps.offset;
  const float* tz0 = s.taps.tz0;
  const float* tz1 = s.taps.tz1;
  for (int64_t x = 0; x < j.W; ++x) {
    float* sums = s.sums + x * P;
    for (int64_t k = 0; k < P; ++k) sums[k] = 0.0f;
    const float tx[2] = {xs.w0[x], xs.w1[x]};
    const float ty[2] = {ty0, ty1};
    const float tz[2] = {tz0[x], tz1[x]};
    for (int dy = 0; dy < 2; ++dy) {
      for (int dz = 0; dz < 2; ++dz) {
        const float* cell = (dy == 0 ? lo : hi) + offset[x] + dz * zstride;
        for (int dx = 0; dx < 2; ++dx, cell += P) {
          const float t = tz[dz] * (ty[dy] * tx[dx]);  // t(p, cell) = tent_x · tent_y · tent_z
          for (int64_t k = 0; k < P; ++k) sums[k] += t * cell[k];
        }
      }
    }
  }
}

#if QF_HAVE_AVX2
// gather_row_scalar for 4-value cells (C = 3): both x-neighbour cells of a (y, z) corner in one
// register.
void gather_row_avx2(const SliceJob& j, const SliceScratch& s, float ty0, float ty1,
                     const float* lo, const float* hi) {
  const AxisTaps& xs = *j.xs;
  const int64_t zstride = j.GW * 4;
  const int32_t* offset = s.taps.offset;
  const float* tz0 = s.taps.tz0;
  const float* tz1 = s.taps.tz1;
  const __m256 y0 = _mm256_set1_ps(ty0), y1 = _mm256_set1_ps(ty1);
  const float* xpair = xs.pair.data();
  float* sums = s.sums;
  const int64_t W = j.W;
  for (int64_t x = 0; x < W; ++x) {
    const float* a = lo + offset[x];
    const float* b = hi + offset[x];
    const __m256 z0 = _mm256_broadcast_ss(tz0 + x), z1 = _mm256_broadcast_ss(tz1 + x);
    // Both x-neighbour cells at once: lanes 0–3 the first, 4–7 the second.
    const __m256 near = _mm256_fmadd_ps(z1, _mm256_loadu_ps(a + zstride),
                                        _mm256_mul_ps(z0, _mm256_loadu_ps(a)));
    const __m256 far = _mm256_fmadd_ps(z1, _mm256_loadu_ps(b + zstride),
                                       _mm256_mul_ps(z0, _mm256_loadu_ps(b)));
    __m256 acc = _mm256_fmadd_ps(y1, far, _mm256_mul_ps(y0, near));
    acc = _mm256_mul_ps(acc, _mm256_loadu_ps(xpair + 8 * x));  // · (tx0, tx1)
    _mm_store_ps(sums + 4 * x,
                 _mm_add_ps(_mm256_castps256_ps128(acc), _mm256_extractf128_ps(acc, 1)));
  }
}
#endif

void gather_row(const SliceJob& j, const SliceScratch& s, float ty0, float ty1, const float* lo,
                const float* hi) {
#if QF_HAVE_AVX2
  if (j.fast) return gather_row_avx2(j, s, ty0, ty1, lo, hi);
#endif
  gather_row_scalar(j, s, ty0, ty1, lo, hi);
}

// out = μ/η where η > 0 else 0 (as μ · (1/η), like the reference) for pixels [begin, W) of a
// row, `out` at its channel-0 value.
void write_row_scalar(const SliceJob& j, const SliceScratch& s, int64_t begin, float* out) {
  const int64_t P = j.cell_values();
  const int64_t plane = j.H * j.W;
  for (int64_t x = begin; x < j.W; ++x) {
    const float* sums = s.sums + x * P;
    const float eta = sums[j.C];
    const float inverse = eta > 0.0f ? 1.0f / eta : 0.0f;
    for (int64_t c = 0; c < j.C; ++c) out[c * plane + x] = sums[c] * inverse;
  }
}

#if QF_HAVE_AVX2
// write_row_scalar for 4-value cells (C = 3), 8 pixels at a time; returns the pixels done.
int64_t write_row_avx2(const SliceJob& j, const SliceScratch& s, float* out) {
  const int64_t plane = j.H * j.W;
  const __m256 zero = _mm256_setzero_ps();
  int64_t x = 0;
  for (; x + 8 <= j.W; x += 8) {
    __m256 t[4];
    grid::transpose_cells_4x8(s.sums + 4 * x, t);
    // 1/η where η > 0, else 0 (the division's Inf/NaN lanes are masked away)
    const __m256 inverse = _mm256_and_ps(_mm256_cmp_ps(t[3], zero, _CMP_GT_OQ),
                                         _mm256_div_ps(_mm256_set1_ps(1.0f), t[3]));
    for (int c = 0; c < 3; ++c) {
      _mm256_storeu_ps(out + c * plane + x, _mm256_mul_ps(t[c], inverse));
    }
  }
  return x;
}
#endif

// Pixel row y of image n from s.sums.
void write_row(const SliceJob& j, const SliceScratch& s, int64_t n, int64_t y) {
  float* out = j.out + n * j.C * j.H * j.W + y * j.W;  // channel 0
  int64_t x = 0;
#if QF_HAVE_AVX2
  if (j.fast) x = write_row_avx2(j, s, out);
#endif
  write_row_scalar(j, s, x, out);
}

// Task: the pixel rows of image n whose first y-cell is in [va, vb).
void slice_band(const SliceJob& j, int64_t task) {
  const grid::Band band = grid::task_band(task, j.bands, j.GH);
  const int64_t n = band.n, va = band.va, vb = band.vb;
  grid::Carver carver = grid::scratch_carver<SliceScratch>(j);
  SliceScratch s(carver, j);
  const AxisTaps& xs = *j.xs;
  const AxisTaps& ys = *j.ys;
  for (int64_t v = va; v < vb; ++v) {
    RowBuffer* lo = &s.rows[0];
    RowBuffer* hi = &s.rows[1];
    if (lo->row != v && hi->row == v) std::swap(lo, hi);
    for (int64_t y = ys.begin[v]; y < ys.begin[v + 1]; ++y) {
      grid::row_taps(j.guide + (n * j.H + y) * j.W, j.W, *j.range, xs.offset.data(),
                     j.GW * j.cell_values(), s.taps);
      grid::block_ranges(xs, s.taps.zfirst, static_cast<int32_t>(j.D - 1), s.low, s.high);
      ensure_row(j, s, n, v, *lo);
      ensure_row(j, s, n, v + 1, *hi);  // exists: a first y-cell is at most GH - 2
      gather_row(j, s, ys.w0[y], ys.w1[y], lo->cells, hi->cells);
      write_row(j, s, n, y);
    }
  }
}

struct BilateralSlice : Kernel<BilateralSlice, grid::Attributes, grid::read_attributes> {
  static constexpr const char* kName = "BilateralSlice";
  static constexpr const char* kInputNames[] = {"grid", "weight", "guide"};
  static constexpr size_t kOutputs = 1;  // image

  OrtStatus* Run(const ort::Api& api, OrtKernelContext* ctx, const FloatInputs<3>& in) const {
    const float* grid = in[0].data;
    const float* weight = in[1].data;
    const float* guide = in[2].data;
    const Shape &gs = in[0].shape, &ws = in[1].shape, &us = in[2].shape;
    if (us.rank != 4 || us[0] < 1 || us[1] != 1 || us[2] < 1 || us[3] < 1) {
      return op_error(api, kName, "guide must be (N, 1, H, W) with N, H, W >= 1, got " +
                                      us.str());
    }
    const int64_t N = us[0], H = us[2], W = us[3];
    const int64_t D = attributes_.depth;
    const int64_t GH = grid::spatial_cells(H, attributes_.sigma_s);
    const int64_t GW = grid::spatial_cells(W, attributes_.sigma_s);
    const std::string cells = std::to_string(D) + ", " + std::to_string(GH) + ", " +
                              std::to_string(GW) + ")";
    const std::string because = " for a " + std::to_string(H) + "x" + std::to_string(W) +
                                " guide with sigma_s=" + std::to_string(attributes_.sigma_s) +
                                ", grid_depth=" + std::to_string(D);
    if (gs.rank != 5 || gs[0] != N || gs[1] < 1 || gs[2] != D || gs[3] != GH || gs[4] != GW) {
      return op_error(api, kName, "grid must be (" + std::to_string(N) + ", C, " + cells +
                                      because + ", got " + gs.str());
    }
    const int64_t C = gs[1];
    if (ws.rank != 5 || ws[0] != N || ws[1] != 1 || ws[2] != D || ws[3] != GH || ws[4] != GW) {
      return op_error(api, kName, "weight must be (" + std::to_string(N) + ", 1, " + cells +
                                      because + ", got " + ws.str());
    }
    const bool fast = QF_HAVE_AVX2 && C == 3 && simd_enabled();
    if (D * GW * (fast ? 4 : C + 1) > INT32_MAX) {
      return op_error(api, kName, "a grid row of " + gs.str() + " is too large");
    }
    Shape out_shape;
    out_shape.rank = 4;
    out_shape.dims = {N, C, H, W};
    float* out = nullptr;
    if (OrtStatus* s = get_float_output(api, kName, ctx, 0, "image", out_shape, &out)) return s;

    AxisTaps xs, ys;
    xs.build(W, attributes_.sigma_s, GW, fast ? 4 : C + 1);
    ys.build(H, attributes_.sigma_s, GH);
    const grid::RangeAxis range(attributes_.sigma_r, D);
    const SliceJob job{grid, weight, guide, out, C, H, W, D, GH, GW, &range, &xs, &ys,
                       band_count(GH, N, grid::kMinRowsPerBand), fast};
    auto task = [&job](size_t i) { slice_band(job, static_cast<int64_t>(i)); };
    return run_tasks(api, kName, ctx, N * job.bands, task, "out of memory for scratch buffers");
  }
};

}  // namespace

const OrtCustomOp* bilateral_slice_op() { return CustomOp<BilateralSlice>::get(); }

}  // namespace qf
