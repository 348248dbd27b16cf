// Point features: PCA normals and FPFH.
#pragma once

#include "arrays.hpp"

#include <cstdint>

namespace kernels {

//: Bins per FPFH angle feature, and the feature length.
inline constexpr int FPFH_BINS = 11;
inline constexpr int FPFH_DIMENSION = 3 * FPFH_BINS;
//: What each block of an SPFH sums to (a point with at least one neighbour).
inline constexpr double SPFH_BLOCK_SUM = 100.0;
//: What each block of an FPFH sums to: the point's own SPFH block plus its neighbours' weighted
//: blocks, renormalised to one SPFH block's sum.
inline constexpr double FPFH_BLOCK_SUM = 2.0 * SPFH_BLOCK_SUM;

// PCA normals: for each query, its k nearest tree points within `upper` (cloud units; INF for no
// radius), their covariance (coordinates relative to `centre`, the cloud's centroid, for accuracy)
// and the unit eigenvector of its smallest eigenvalue, sign as it comes (the caller orients it).
// out_counts: the neighbours used; below 3 the normal is left NaN (the caller's fallback).
void knn_normals(CArr2 queries, CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes,
                 int64_t k, double upper, CArr1 centre, Arr2 out_normals, Idx out_counts, int threads);

// The number of tree points within `radius` (cloud units, inclusive) of each query (itself
// included when it is a tree point): out_counts (Q,).
void count_within(CArr2 queries, CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes,
                  double radius, Idx out_counts, int threads);

// FPFH of every point of the tree's cloud within `radius` (cloud units): out (N, 33), rows in the
// cloud's order; normals (N, 3) in that order too. In parallel, each point's neighbours and the
// bins of its pairs with the later points (each pair computed once), counted for that point; then,
// on one thread, the same bins counted for the later points (integer counts, so the order of the
// adds does not matter, and no atomic add: those cost more than the features); in parallel again,
// the SPFHs from the counts, and each point's SPFH plus its neighbours' weighted by 1 / squared
// distance, renormalised per block.
void fpfh(CArr2 normals_, CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes,
          double radius, Arr2 out_, int threads);

}  // namespace kernels
