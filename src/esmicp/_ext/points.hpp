// Passes over a cloud's points: coincident points, a rigid transform.
#pragma once

#include "arrays.hpp"

#include <cstdint>

namespace kernels {

// Coincident points: one pass with a hash table of exact coordinates (-0.0 counts as 0.0).
// Marks first[i] = 1 for the first occurrence of each distinct point, 0 for a repeat; returns
// (repeats, index of the most repeated point, its number of occurrences).
struct Coincident {
    int64_t repeats, most, most_count;
};
Coincident coincident(CArr2 points_, U8Arr1 first_);

// The voxel grid of a cloud: each point's cell floor((p - low) / voxel) (per axis, in double, as
// NumPy computes it), the occupied cells numbered in lexicographic order of their integer
// coordinates (x-major), owner[i] the number of point i's cell, sums[c] the sum of its points'
// coordinates in point order and counts[c] their number (sums and counts at least N long).
// Returns the number of cells; -1 when a cell coordinate reaches 2^62 (too fine a voxel).
int64_t voxel_cells(CArr2 points, CArr1 low, double voxel, Idx owner, Arr2 sums, Idx counts);

// The k nearest points of each query (out_indices (Q, k), nearest first, indices into points)
// among the points of the 27 cells of edge `cell` (corner at `low`) around the query's own,
// found without a tree; out_exact[q] 1 when they are the k nearest of the whole cloud (the k-th
// within a cell of the query, so nothing farther out could be nearer), else 0 (fewer found, the
// k-th beyond a cell, or a query off the grid: ask a tree).
void knn_in_cells(CArr2 points, CArr2 queries, CArr1 low, double cell, Idx2 out_indices, U8Arr1 out_exact,
                  int threads);

// The number of cells of voxel_cells (the same grid), without the owners, sums or counts; -1 as there.
int64_t voxel_count(CArr2 points, CArr1 low, double voxel);

// The sum of each column of points (N, 3) into out (3,), row after row from the first: NumPy's
// sum(axis=0) of a C-contiguous (N, 3) float64 array adds in that order, so the sums are its own
// to the last bit, without its inner loop of three values per row.
void column_sums(CArr2 points, Arr1 out);

// The scatter matrix sum_i u_i u_i^T of u_i = (p_i - centre) / scale (out (3, 3), symmetric), in
// one pass over the points (no centred copy), summed by blocks of points.
void centred_scatter(CArr2 points, CArr1 centre, double scale, Arr2 out);

// points @ R^T + t into out (N, 3), on `threads` threads (NumPy would call BLAS, whose own
// threads then compete with the kernels').
void transform_points(CArr2 points, CArr2 rotation, CArr1 translation, Arr2 out_, int threads);

}  // namespace kernels
