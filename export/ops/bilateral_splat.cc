// BilateralSplat(image (N,C,H,W), guide (N,1,H,W)) -> grid (N,C,D,GH,GW), weight (N,1,D,GH,GW)
//
// Supplement §5.1, eq. 2, 6–8: α[c, cell] = Σ_p t(p, cell)·image[c, p],
// β[cell] = Σ_p t(p, cell), grid = α/β where β > 0 else 0, weight = β (docs/grid-math.md).
//
// Parallel over bands of grid rows: a task owns its rows outright and gathers every pixel row
// that touches them, so no two tasks write the same cell. It walks its pixel rows in order while
// holding only two grid rows (the current row and the next) in [z][gx][P] scratch, which stays in
// L2; a finished row is normalised and streamed to the output tensors in whole cache lines
// (grid::LineWriter), range cells that no pixel of the row touched as plain zeros.
#include <algorithm>
#include <climits>
#include <cstdint>
#include <cstring>
#include <utility>

#include "grid_common.h"
#include "kernel_support.h"
#include "ops.h"
#include "runtime_support.h"
#include "simd.h"

namespace qf {
namespace {

using grid::AxisTaps;

// Independent stretches of a pixel row scattered in lockstep (see scatter_row).
constexpr int64_t kStreams = 4;

struct SplatJob {
  const float* image;  // (N, C, H, W)
  const float* guide;  // (N, 1, H, W)
  float* grid;         // (N, C, D, GH, GW)
  float* weight;       // (N, 1, D, GH, GW)
  int64_t C, H, W, D, GH, GW;
  const grid::RangeAxis* range;
  const AxisTaps* xs;
  const AxisTaps* ys;
  int64_t bands;
  bool fast;  // C == 3 on an AVX2 build: 4-value cells, one register per cell pair

  int64_t cell_values() const { return fast ? 4 : C + 1; }  // P: C values, then β
};

// One task's working memory.
struct SplatScratch {
  float* rows[2];       // grid rows [z][gx][P]
  float* values;        // one pixel row [x][P]: sanitised values, then 1
  grid::RowTaps taps;   // and its taps
  float* staging;       // one range cell of a finished grid row, [C + 1][GW]
  float* zeros;         // GW zeros
  grid::LineWriter::Pending* pending;  // one per output plane

  SplatScratch(grid::Carver& carver, const SplatJob& j) {
    const size_t row = static_cast<size_t>(j.D * j.GW * j.cell_values());
    const auto W = static_cast<size_t>(j.W);
    rows[0] = carver.take<float>(row);
    rows[1] = carver.take<float>(row);
    values = carver.take<float>(W * j.cell_values());
    taps.zfirst = carver.take<int32_t>(W);
    taps.offset = carver.take<int32_t>(W);
    taps.tz0 = carver.take<float>(W);
    taps.tz1 = carver.take<float>(W);
    staging = carver.take<float>(static_cast<size_t>((j.C + 1) * j.GW));
    zeros = carver.take<float>(static_cast<size_t>(j.GW));
    pending = carver.take<grid::LineWriter::Pending>(static_cast<size_t>((j.C + 1) * j.D));
  }
};

// Pixels [begin, end) of a row (`image` at its channel-0 value) as [x][P] cells: the values, with
// non-finite ones counted as 0, then 1.
void prepare_values_scalar(const SplatJob& j, const float* image, int64_t begin, int64_t end,
                           float* values) {
  const int64_t plane = j.H * j.W;
  const int64_t P = j.cell_values();
  for (int64_t x = begin; x < end; ++x) {
    float* cell = values + x * P;
    for (int64_t c = 0; c < j.C; ++c) cell[c] = grid::finite_or_zero(image[c * plane + x]);
    for (int64_t k = j.C; k < P; ++k) cell[k] = 1.0f;
  }
}

#if QF_HAVE_AVX2
// prepare_values_scalar for 4-value cells (C = 3), 8 pixels at a time; returns the pixels done.
int64_t prepare_values_avx2(const SplatJob& j, const float* image, float* values) {
  const int64_t plane = j.H * j.W;
  const __m256 one = _mm256_set1_ps(1.0f);
  int64_t x = 0;
  for (; x + 8 <= j.W; x += 8) {
    const __m256 v[4] = {grid::finite_or_zero(_mm256_loadu_ps(image + x)),
                         grid::finite_or_zero(_mm256_loadu_ps(image + plane + x)),
                         grid::finite_or_zero(_mm256_loadu_ps(image + 2 * plane + x)), one};
    grid::store_cells_4x8(values + 4 * x, v);
  }
  return x;
}
#endif

// Pixel row y of image n as [x][P] cells, and its taps.
void prepare_row(const SplatJob& j, int64_t n, int64_t y, const SplatScratch& s) {
  const int64_t plane = j.H * j.W;
  const float* image = j.image + n * j.C * plane + y * j.W;
  const int64_t P = j.cell_values();
  int64_t x = 0;
#if QF_HAVE_AVX2
  if (j.fast) x = prepare_values_avx2(j, image, s.values);
#endif
  prepare_values_scalar(j, image, x, j.W, s.values);
  grid::row_taps(j.guide + n * plane + y * j.W, j.W, *j.range, j.xs->offset.data(), j.GW * P,
                 s.taps);
}

// Adds the prepared pixel row to grid row `lo` (its first y-cell) and/or `hi` (the second); a
// null row belongs to another task.
template <bool kLo, bool kHi>
void scatter_row_scalar(const SplatJob& j, const SplatScratch& s, float ty0, float ty1,
                        float* lo, float* hi) {
  const AxisTaps& xs = *j.xs;
  const int64_t P = j.cell_values();
  const int64_t zstride = j.GW * P;  // from a cell to the next range cell
  const int32_t* offset = s.taps.offset;
  const float* tz0 = s.taps.tz0;
  const float* tz1 = s.taps.tz1;
  for (int64_t x = 0; x < j.W; ++x) {
    const float* v = s.values + x * P;
    const float tx[2] = {xs.w0[x], xs.w1[x]};
    const float ty[2] = {ty0, ty1};
    const float tz[2] = {tz0[x], tz1[x]};
    for (int dy = 0; dy < 2; ++dy) {
      if ((dy == 0 && !kLo) || (dy == 1 && !kHi)) continue;
      for (int dz = 0; dz < 2; ++dz) {
        float* cell = (dy == 0 ? lo : hi) + offset[x] + dz * zstride;
        for (int dx = 0; dx < 2; ++dx, cell += P) {
          const float t = tz[dz] * (ty[dy] * tx[dx]);  // t(p, cell) = tent_x · tent_y · tent_z
          for (int64_t k = 0; k < P; ++k) cell[k] += t * v[k];
        }
      }
    }
  }
}

#if QF_HAVE_AVX2
// scatter_row_scalar for 4-value cells (C = 3): a pixel adds to both x-neighbour cells with one
// register per (y, z) corner.
template <bool kLo, bool kHi>
void scatter_row_avx2(const SplatJob& j, const SplatScratch& s, float ty0, float ty1, float* lo,
                      float* hi) {
  const AxisTaps& xs = *j.xs;
  const int64_t zstride = j.GW * 4;  // from a cell to the next range cell
  const int32_t* offset = s.taps.offset;
  const float* tz0 = s.taps.tz0;
  const float* tz1 = s.taps.tz1;
  const __m256 y0 = _mm256_set1_ps(ty0), y1 = _mm256_set1_ps(ty1);
  const float* values = s.values;
  const float* xpair = xs.pair.data();
  auto add_pixel = [=](int64_t x) {
    // (tx0·v, tx1·v) for the two x-neighbour cells, v = (c0, c1, c2, 1)
    const __m256 pair =
        _mm256_mul_ps(_mm256_broadcast_ps(reinterpret_cast<const __m128*>(values + 4 * x)),
                      _mm256_loadu_ps(xpair + 8 * x));
    const __m256 z0 = _mm256_broadcast_ss(tz0 + x), z1 = _mm256_broadcast_ss(tz1 + x);
    const int32_t first = offset[x];
    // the row's y weight times the pair into two range cells of `rows` (lo or hi)
    auto add = [&](float* rows, __m256 y) {
      const __m256 p = _mm256_mul_ps(y, pair);
      float* a = rows + first;
      float* b = a + zstride;
      _mm256_storeu_ps(a, _mm256_fmadd_ps(z0, p, _mm256_loadu_ps(a)));
      _mm256_storeu_ps(b, _mm256_fmadd_ps(z1, p, _mm256_loadu_ps(b)));
    };
    if (kLo) add(lo, y0);
    if (kHi) add(hi, y1);
  };
  // Neighbouring pixels mostly hit the same cells, and each add must wait for the previous
  // one's store: walk kStreams far-apart stretches of the row in lockstep so that that
  // many independent chains overlap.
  const int64_t W = j.W, stretch = W / kStreams;
  for (int64_t i = 0; i < stretch; ++i) {
    for (int64_t k = 0; k < kStreams; ++k) add_pixel(k * stretch + i);
  }
  for (int64_t x = kStreams * stretch; x < W; ++x) add_pixel(x);
}
#endif

template <bool kLo, bool kHi>
void scatter_row(const SplatJob& j, const SplatScratch& s, float ty0, float ty1, float* lo,
                 float* hi) {
#if QF_HAVE_AVX2
  if (j.fast) return scatter_row_avx2<kLo, kHi>(j, s, ty0, ty1, lo, hi);
#endif
  scatter_row_scalar<kLo, kHi>(j, s, ty0, ty1, lo, hi);
}

// A grid row in scratch, [z][gx][P], and the range cells [low, high] that pixels have touched
// (all others are still 0).
struct RowBuffer {
  float* cells;
  int32_t low = INT32_MAX;
  int32_t high = -1;

  void touch(int32_t first, int32_t last) {
    low = std::min(low, first);
    high = std::max(high, last + 1);  // a pixel touches its first range cell and the next
  }
  void clear() {
    low = INT32_MAX;
    high = -1;
  }
};

// Cells [begin, GW) of one range cell of a finished grid row (`cells`, [gx][P]) to `staging`
// ([C + 1][GW]): grid = α/β where β > 0 else 0 (as α · (1/β), like the reference), then β;
// the cells are left zeroed.
void normalise_cells_scalar(const SplatJob& j, float* cells, int64_t begin, float* staging) {
  const int64_t P = j.cell_values();
  float* beta_row = staging + j.C * j.GW;
  for (int64_t gx = begin; gx < j.GW; ++gx) {
    float* cell = cells + gx * P;
    const float beta = cell[j.C];
    const float inverse = beta > 0.0f ? 1.0f / beta : 0.0f;
    for (int64_t c = 0; c < j.C; ++c) staging[c * j.GW + gx] = cell[c] * inverse;
    beta_row[gx] = beta;
    std::memset(cell, 0, sizeof(float) * P);
  }
}

#if QF_HAVE_AVX2
// normalise_cells_scalar for 4-value cells (C = 3), 8 cells at a time; returns the cells done.
int64_t normalise_cells_avx2(const SplatJob& j, float* cells, float* staging) {
  const int64_t GW = j.GW;
  float* beta_row = staging + 3 * GW;
  const __m256 zero = _mm256_setzero_ps();
  int64_t gx = 0;
  for (; gx + 8 <= GW; gx += 8) {
    __m256 t[4];
    grid::transpose_cells_4x8(cells + 4 * gx, t);
    const __m256 filled = _mm256_cmp_ps(t[3], zero, _CMP_GT_OQ);
    for (int k = 0; k < 4; ++k) _mm256_storeu_ps(cells + 4 * gx + 8 * k, zero);
    if (_mm256_movemask_ps(filled) == 0) {  // 8 empty cells, the usual case: no division
      for (int c = 0; c < 4; ++c) _mm256_storeu_ps(staging + c * GW + gx, zero);
      continue;
    }
    // 1/β where β > 0, else 0 (the division's Inf/NaN lanes are masked away)
    const __m256 inverse = _mm256_and_ps(filled, _mm256_div_ps(_mm256_set1_ps(1.0f), t[3]));
    for (int c = 0; c < 3; ++c) {
      _mm256_storeu_ps(staging + c * GW + gx, _mm256_mul_ps(t[c], inverse));
    }
    _mm256_storeu_ps(beta_row + gx, t[3]);
  }
  return gx;
}
#endif

// grid = α/β where β > 0 else 0 (as α · (1/β), like the reference), weight = β, for grid row
// v; leaves the scratch row zeroed. Each range cell's values go through `staging` ([C + 1][GW]:
// the C grid channels, then β) to `out`, whose streams are the (C + 1)·D planes; untouched range
// cells are written from `zeros` (GW floats).
void finish_row(const SplatJob& j, int64_t n, int64_t v, RowBuffer& row, float* staging,
                const float* zeros, grid::LineWriter& out) {
  const int64_t P = j.cell_values();
  const int64_t channel = j.D * j.GH * j.GW;  // from one channel of the grid to the next
  float* beta_row = staging + j.C * j.GW;
  for (int64_t z = 0; z < j.D; ++z) {
    float* grid = j.grid + ((n * j.C * j.D + z) * j.GH + v) * j.GW;  // channel 0
    float* weight = j.weight + ((n * j.D + z) * j.GH + v) * j.GW;
    if (z < row.low || z > row.high) {
      for (int64_t c = 0; c < j.C; ++c) out.write(c * j.D + z, grid + c * channel, zeros, j.GW);
      out.write(j.C * j.D + z, weight, zeros, j.GW);
      continue;
    }
    float* cells = row.cells + z * j.GW * P;
    int64_t gx = 0;
#if QF_HAVE_AVX2
    if (j.fast) gx = normalise_cells_avx2(j, cells, staging);
#endif
    normalise_cells_scalar(j, cells, gx, staging);
    for (int64_t c = 0; c < j.C; ++c) {
      out.write(c * j.D + z, grid + c * channel, staging + c * j.GW, j.GW);
    }
    out.write(j.C * j.D + z, weight, beta_row, j.GW);
  }
  row.clear();
}

// Task: grid rows [va, vb) of image n.
void splat_band(const SplatJob& j, int64_t task) {
  const grid::Band band = grid::task_band(task, j.bands, j.GH);
  const int64_t n = band.n, va = band.va, vb = band.vb;
  grid::Carver carver = grid::scratch_carver<SplatScratch>(j);
  const SplatScratch s(carver, j);
  const size_t row_bytes = sizeof(float) * j.D * j.GW * j.cell_values();
  std::memset(s.rows[0], 0, row_bytes);
  std::memset(s.rows[1], 0, row_bytes);
  std::memset(s.zeros, 0, sizeof(float) * j.GW);
  const AxisTaps& ys = *j.ys;
  grid::LineWriter out(s.pending, (j.C + 1) * j.D);
  RowBuffer cur, next;  // grid rows v and v + 1
  cur.cells = s.rows[0];
  next.cells = s.rows[1];
  auto row_range = [&](int32_t* first, int32_t* last) {  // range cells of the prepared row
    *first = INT32_MAX;
    *last = -1;
    for (int64_t x = 0; x < j.W; ++x) {
      *first = std::min(*first, s.taps.zfirst[x]);
      *last = std::max(*last, s.taps.zfirst[x]);
    }
  };
  int32_t first, last;
  if (va > 0) {  // pixel rows whose second y-cell is va
    for (int64_t y = ys.begin[va - 1]; y < ys.begin[va]; ++y) {
      prepare_row(j, n, y, s);
      row_range(&first, &last);
      cur.touch(first, last);
      scatter_row<false, true>(j, s, ys.w0[y], ys.w1[y], nullptr, cur.cells);
    }
  }
  for (int64_t v = va; v < vb; ++v) {
    for (int64_t y = ys.begin[v]; y < ys.begin[v + 1]; ++y) {
      prepare_row(j, n, y, s);
      row_range(&first, &last);
      cur.touch(first, last);
      if (v + 1 < vb) {
        next.touch(first, last);
        scatter_row<true, true>(j, s, ys.w0[y], ys.w1[y], cur.cells, next.cells);
      } else {  // row v + 1 belongs to the next band
        scatter_row<true, false>(j, s, ys.w0[y], ys.w1[y], cur.cells, nullptr);
      }
    }
    finish_row(j, n, v, cur, s.staging, s.zeros, out);
    std::swap(cur, next);
  }
  out.finish();
}

struct BilateralSplat : Kernel<BilateralSplat, grid::Attributes, grid::read_attributes> {
  static constexpr const char* kName = "BilateralSplat";
  static constexpr const char* kInputNames[] = {"image", "guide"};
  static constexpr size_t kOutputs = 2;  // grid, weight

  OrtStatus* Run(const ort::Api& api, OrtKernelContext* ctx, const FloatInputs<2>& in) const {
    const float* image = in[0].data;
    const float* guide = in[1].data;
    const Shape& is = in[0].shape;
    if (OrtStatus* s = check_image_inputs(api, kName, kInputNames, in, {kAnyChannels, 1})) {
      return s;
    }
    const int64_t N = is[0], C = is[1], H = is[2], W = is[3];
    const int64_t D = attributes_.depth;
    const int64_t GH = grid::spatial_cells(H, attributes_.sigma_s);
    const int64_t GW = grid::spatial_cells(W, attributes_.sigma_s);
    Shape grid_shape, weight_shape;
    grid_shape.rank = weight_shape.rank = 5;
    grid_shape.dims = {N, C, D, GH, GW};
    weight_shape.dims = {N, 1, D, GH, GW};
    float* grid_data = nullptr;
    float* weight_data = nullptr;
    if (OrtStatus* s = get_float_output(api, kName, ctx, 0, "grid", grid_shape, &grid_data)) {
      return s;
    }
    if (OrtStatus* s =
            get_float_output(api, kName, ctx, 1, "weight", weight_shape, &weight_data)) {
      return s;
    }

    const bool fast = QF_HAVE_AVX2 && C == 3 && simd_enabled();
    if (D * GW * (fast ? 4 : C + 1) > INT32_MAX) {
      return op_error(api, kName, "a grid row of " + grid_shape.str() + " is too large");
    }
    AxisTaps xs, ys;
    xs.build(W, attributes_.sigma_s, GW, fast ? 4 : C + 1);
    ys.build(H, attributes_.sigma_s, GH);
    const grid::RangeAxis range(attributes_.sigma_r, D);
    const SplatJob job{image, guide, grid_data, weight_data, C, H, W, D, GH, GW, &range,
                       &xs, &ys, band_count(GH, N, grid::kMinRowsPerBand), fast};
    auto task = [&job](size_t i) { splat_band(job, static_cast<int64_t>(i)); };
    return run_tasks(api, kName, ctx, N * job.bands, task, "out of memory for scratch buffers");
  }
};

}  // namespace

const OrtCustomOp* bilateral_splat_op() { return CustomOp<BilateralSplat>::get(); }

}  // namespace qf
