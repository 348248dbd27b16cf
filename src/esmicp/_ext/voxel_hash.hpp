// Voxel hash: exact nearest neighbours within one cell, the tree beyond.
#pragma once

#include "arrays.hpp"
#include "common.hpp"
#include "tree.hpp"

#include <cmath>
#include <cstdint>

namespace kernels {

// A cell key's first slot in a table of 2^(64 - shift) slots (linear probing from there).
inline int64_t hash_slot(int64_t key, int shift) {
    return int64_t((uint64_t(key) * HASH_MULTIPLIER) >> uint64_t(shift));
}

//: Cells holding more distinct points than this are not scanned: the query goes to the tree
//: (exact, logarithmic), so that no dense cell makes the hash quadratic.
inline constexpr int64_t CELL_SCAN_MAX = 256;

// A voxel hash (esmicp.core.voxel_hash.VoxelHash): the target sorted by cell, the table of its
// occupied cells, the grid (low corner, cell edge, dims) and the tree's rank of each target point.
struct Hash {
    const double *sorted_points;
    const int64_t *sorted_index, *rank, *cell_starts, *table_keys, *table_cells, *dims;
    const double *low;
    double cell, inverse_cell, limit;
    int shift;
    int64_t mask;
};

// The Hash over a VoxelHash's arrays.
Hash make_hash(CArr2 sorted_points, CIdx sorted_index, CIdx rank, CIdx cell_starts, CIdx table_keys, CIdx table_cells,
               CArr1 low, double cell, CIdx dims);

// The cell number of a cell key (-1: no point there).
inline int64_t hash_cell(const Hash &h, int64_t key) {
    int64_t slot = hash_slot(key, h.shift);
    while (true) {
        const int64_t stored = h.table_keys[slot];
        if (stored == key) return h.table_cells[slot];
        if (stored == -1) return -1;
        slot = (slot + 1) & h.mask;
    }
}

// Nearest target point to (qx, qy, qz), seeded with target point `warm` (-1: none): the 3 x 3 x 3
// cells around it when `use_hash` (exact within one cell), otherwise (or beyond one cell, or at a
// dense cell) the tree. Returns true when the nearest point is farther than one cell (a miss).
inline bool hash_nearest(const Hash &h, const Tree &t, const int64_t *tree_rank, double qx, double qy, double qz,
                         int64_t warm, bool use_hash, double &distance, int64_t &index) {
    const double *sp = h.sorted_points;
    const int64_t *cs = h.cell_starts, *dims = h.dims;
    const double cell = h.cell, limit = h.limit;
    double best = INF;
    int64_t best_index = -1;
    if (warm >= 0) {
        int64_t k = h.rank[warm];
        double ex = sp[3 * k] - qx, ey = sp[3 * k + 1] - qy, ez = sp[3 * k + 2] - qz;
        best = ex * ex + ey * ey + ez * ez;
        best_index = k;
    }
    bool dense = false;
    if (use_hash) {
        double fx = (qx - h.low[0]) * h.inverse_cell, fy = (qy - h.low[1]) * h.inverse_cell,
               fz = (qz - h.low[2]) * h.inverse_cell;
        // Beyond the grid (or NaN): no cell to scan.
        bool inside = fx > -2.0 && fy > -2.0 && fz > -2.0 && fx < double(dims[0]) + 2.0 &&
                      fy < double(dims[1]) + 2.0 && fz < double(dims[2]) + 2.0;
        if (inside) {
            int64_t cx = int64_t(std::floor(fx)), cy = int64_t(std::floor(fy)), cz = int64_t(std::floor(fz));
            double ox = fx - cx, oy = fy - cy, oz = fz - cz;
            double bound = best > limit ? limit : best;
            for (int dz = -1; dz <= 1 && !dense; ++dz) {
                int64_t z = cz + dz;
                if (z < 0 || z >= dims[2]) continue;
                double gz = dz == 0 ? 0.0 : ((dz < 0 ? oz : 1.0 - oz) * cell);
                for (int dy = -1; dy <= 1 && !dense; ++dy) {
                    int64_t y = cy + dy;
                    if (y < 0 || y >= dims[1]) continue;
                    double gy = dy == 0 ? 0.0 : ((dy < 0 ? oy : 1.0 - oy) * cell);
                    for (int dx = -1; dx <= 1; ++dx) {
                        int64_t x = cx + dx;
                        if (x < 0 || x >= dims[0]) continue;
                        double gx = dx == 0 ? 0.0 : ((dx < 0 ? ox : 1.0 - ox) * cell);
                        if (gx * gx + gy * gy + gz * gz > bound) continue;
                        const int64_t found = hash_cell(h, x + dims[0] * (y + dims[1] * z));
                        if (found < 0) continue;
                        if (cs[found + 1] - cs[found] > CELL_SCAN_MAX) {
                            dense = true;
                            break;
                        }
                        for (int64_t k = cs[found]; k < cs[found + 1]; ++k) {
                            double ex = sp[3 * k] - qx, ey = sp[3 * k + 1] - qy, ez = sp[3 * k + 2] - qz;
                            double squared = ex * ex + ey * ey + ez * ez;
                            if (squared < best) {
                                best = squared;
                                best_index = k;
                                if (squared < bound) bound = squared;
                            }
                        }
                    }
                }
            }
        }
        if (!dense && best <= limit) {
            distance = std::sqrt(best);
            index = h.sorted_index[best_index];
            return false;
        }
    }
    int64_t slot = best_index < 0 ? -1 : tree_rank[h.sorted_index[best_index]];
    nearest(t, qx, qy, qz, best, slot);
    distance = std::sqrt(best);
    index = slot >= 0 ? t.order[slot] : t.count;
    return best > limit;
}

// The table of the occupied cells: table_keys (a power of two long; -1: empty) and table_cells.
void build_table(CIdx cell_keys, Idx table_keys, Idx table_cells);

// The points (M, 3) in cell order: each point's cell key i + dims[0] (j + dims[1] k), with
// (i, j, k) = floor((p - low) / cell) (non-negative: `low` below every point), sorted stably
// (ties in point order: NumPy's stable argsort of the keys, the same permutation). Writes the
// sorted keys, the order (sorted slot -> point), the points in that order and the rank (point ->
// sorted slot).
void cell_order(CArr2 points, CArr1 low, double cell, CIdx dims, Idx out_keys, Idx out_order, Arr2 out_points,
                Idx out_rank);

// hash_nearest for each query mapped by (rotation, translation), seeded with warm[i]; returns the
// number of misses.
int64_t hash_query(CArr2 queries, CArr2 rotation, CArr1 translation, CIdx warm, CIdx rank, CArr2 sorted_points,
                   CIdx sorted_index, CIdx cell_starts, CIdx table_keys, CIdx table_cells, CArr1 low_, double cell,
                   CIdx dims_, CArr2 tree_points, CIdx tree_order, CIdx tree_rank, CIdx tree_starts, CIdx tree_ends,
                   CIdx tree_lefts, CArr2 tree_boxes, bool use_hash, Arr1 out_distances, Idx out_indices,
                   int threads);

// The neighbour graph of a voxel hash's points by sorted position (row p and its entries are rows
// of h.sorted_points), from the 3 x 3 x 3 cells around each point: its k nearest there, and as
// radius the squared distance to the k-th but at most one cell (every point within one cell of p
// is in that block, so every point strictly nearer than the radius is in the list). A point next
// to a dense cell (more than CELL_SCAN_MAX points) gets radius -1: it never certifies.
void hash_graph(const Hash &h, int64_t count, int64_t k, int32_t *neighbours, double *radii, int threads);

}  // namespace kernels
