// Correspondences of the global search: length compatibility, seeds, second-order groups, pose
// scores, descriptor matching.
#pragma once

#include "arrays.hpp"

#include <cstdint>

namespace kernels {

// Length compatibility of K paired points (source[k] <-> target[k], e.g. feature correspondences):
// out[i][j] = 1 when the source length |s_i - s_j| and the target length |t_i - t_j| differ by at
// most `tolerance` (cloud units), else 0; the diagonal is 0. Lengths as SciPy's cdist computes them
// (the same sums, the same square roots), so the entries are those of its two distance matrices;
// float32 for the power iterations that follow. Rows in parallel.
void compatibility(CArr2 source, CArr2 target, double tolerance, F32Arr2 out, int threads);

// The leading eigenvector of a symmetric non-negative (K, K) matrix (the compatibility matrix above)
// by power iteration, into `out` (K,): from the uniform unit vector, each step the product with the
// matrix (its non-zero entries gathered once, row by row, and each row's sum taken in double),
// divided by its norm, at most `iterations` steps, fewer once a step moves no entry by more than
// `tolerance`. The kernels' own threads, never BLAS's. Rows in parallel.
void leading_vector(CF32Arr2 matrix, double tolerance, int64_t iterations, F32Arr1 out, int threads);

// Seeds of the second-order pruning, spread apart: the candidates `order` (K, best first) are
// taken in turn, each kept unless a kept one lies within `spread` of it in both clouds (source
// distance and target distance both below `spread`, as NumPy's norm computes them), until `seeds`
// are kept. Writes the kept candidates to `out` (at least `seeds` long) and returns how many.
int64_t spread_seeds(CIdx order, CArr2 source, CArr2 target, double spread, int64_t seeds, Idx out);

// Groups of the second-order pruning. `compatible` (K, K) is 0/1 and symmetric (compatibility()
// above). For each seed s, the second-order compatibility of candidate j is C[s][j] times the
// number of candidates compatible with both; `partners` (S, size) gets the `size` candidates of
// highest second-order compatibility, highest first, ties to the lower index, then (when fewer
// than `size` are above 0) the candidates at 0 in index order: the first `size` of a stable
// argsort of the negated second-order row. `valid` (S, size) is 1 where the partner's
// second-order compatibility is above 0. Seeds in parallel.
void second_order_partners(CF32Arr2 compatible, CIdx seeds, Idx2 partners, U8Arr2 valid, int threads);

// The second-order matrices of the seeds' groups (S groups of G members): with members m = groups[g]
// and valid[g] (0/1), local[i][j] = C[m_i][m_j] valid[g][i] valid[g][j], and out[g] (row-major
// G x G) = local[i][j] times (local @ local)[i][j], the members compatible with both i and j where
// the two are compatible. Whole numbers of at most G, exact in float32 whatever the order of the
// sums: NumPy's gather, mask and batched product give the same values. Groups in parallel.
void group_second_order(CF32Arr2 compatible, CIdx2 groups, U8Arr2 valid, F32Arr2 out, int threads);

// How many of K paired points (source[k] <-> target[k]) each of S poses maps within `distance`:
// out[c] = #{k : |R_c source[k] + t_c - target[k]| <= distance}. `rotations` (S, 9) row-major,
// `translations` (S, 3). Poses in parallel.
void pair_inlier_counts(CArr2 rotations, CArr2 translations, CArr2 source, CArr2 target, double distance, Idx out,
                        int threads);

// A descriptor matching both ways: rows (R, D) the source descriptors, columns (D, C) the target
// descriptors transposed, float32, with their squared norms. Each squared distance is
// (-2 g + |t|^2) + |s|^2 in float32, clipped at 0, g the dot product (summed over the dimensions
// in order). Per row: the nearest column (the first of equal ones), its squared distance and the
// second smallest (out_row_*). Per column: the two smallest squared distances over the rows
// (column_best (2, C)) and the row of the first (column_index, the first of equal ones). Column
// pieces in parallel; each piece's row minima are merged in column order.
void nearest_descriptors(CF32Arr2 rows_, CF32Arr2 columns_, CF32Arr1 row_squares_, CF32Arr1 column_squares_,
                         Idx out_row_index_, F32Arr1 out_row_best_, F32Arr1 out_row_second_, F32Arr2 column_best_,
                         Idx column_index_, int threads);

}  // namespace kernels
