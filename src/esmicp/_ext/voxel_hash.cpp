// Voxel hash (voxel_hash.hpp): its table, the nearest-neighbour queries, its neighbour graph.
#include "voxel_hash.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <vector>

namespace kernels {

void build_table(CIdx cell_keys, Idx table_keys, Idx table_cells) {
    const int64_t size = int64_t(table_keys.shape(0));
    int bits = 0;
    while ((int64_t(1) << bits) < size) ++bits;
    const int shift = 64 - bits;
    const int64_t mask = size - 1;
    int64_t *tk = table_keys.data(), *tc = table_cells.data();
    const int64_t *ck = cell_keys.data();
    for (int64_t s = 0; s < size; ++s) tk[s] = -1;
    for (int64_t cell = 0; cell < int64_t(cell_keys.shape(0)); ++cell) {
        int64_t slot = hash_slot(ck[cell], shift);
        while (tk[slot] != -1) slot = (slot + 1) & mask;
        tk[slot] = ck[cell];
        tc[slot] = cell;
    }
}

void cell_order(CArr2 points_, CArr1 low_, double cell, CIdx dims_, Idx out_keys, Idx out_order, Arr2 out_points,
                Idx out_rank) {
    const int64_t count = int64_t(points_.shape(0));
    if (points_.shape(1) != 3 || low_.shape(0) != 3 || dims_.shape(0) != 3 || int64_t(out_keys.shape(0)) != count ||
        int64_t(out_order.shape(0)) != count || int64_t(out_points.shape(0)) != count || out_points.shape(1) != 3 ||
        int64_t(out_rank.shape(0)) != count)
        throw std::invalid_argument("cell_order: points (M, 3), low and dims (3,), outputs of M rows");
    const double *p = points_.data(), *low = low_.data();
    const int64_t *dims = dims_.data();
    int64_t *keys = out_keys.data(), *order = out_order.data(), *rank = out_rank.data();
    double *sorted = out_points.data();
    GilReleased release;
    const size_t size = static_cast<size_t>(count);
    std::vector<int64_t> key(size), swap_key(size), swap_order(size);
    int64_t largest = 0;
    for (int64_t n = 0; n < count; ++n) {
        int64_t ijk[3];
        for (int a = 0; a < 3; ++a) ijk[a] = int64_t(std::floor((p[3 * n + a] - low[a]) / cell));
        key[size_t(n)] = ijk[0] + dims[0] * (ijk[1] + dims[1] * ijk[2]);
        largest = std::max(largest, key[size_t(n)]);
        order[n] = n;
    }
    // Least significant digit first, 16 bits a pass, each pass stable: the order of a stable sort.
    int64_t *from_key = key.data(), *from_order = order, *to_key = swap_key.data(), *to_order = swap_order.data();
    std::vector<int64_t> counts(size_t(1) << 16);
    for (int shift = 0; shift < 64 && (largest >> shift) > 0; shift += 16) {
        std::fill(counts.begin(), counts.end(), int64_t(0));
        for (int64_t n = 0; n < count; ++n) ++counts[size_t((from_key[n] >> shift) & 0xFFFF)];
        int64_t total = 0;
        for (auto &value : counts) {
            const int64_t here = value;
            value = total;
            total += here;
        }
        for (int64_t n = 0; n < count; ++n) {
            const int64_t slot = counts[size_t((from_key[n] >> shift) & 0xFFFF)]++;
            to_key[slot] = from_key[n];
            to_order[slot] = from_order[n];
        }
        std::swap(from_key, to_key);
        std::swap(from_order, to_order);
    }
    for (int64_t n = 0; n < count; ++n) {
        keys[n] = from_key[n];
        order[n] = from_order[n];
        rank[from_order[n]] = n;
        for (int a = 0; a < 3; ++a) sorted[3 * n + a] = p[3 * from_order[n] + a];
    }
}

Hash make_hash(CArr2 sorted_points, CIdx sorted_index, CIdx rank, CIdx cell_starts, CIdx table_keys, CIdx table_cells,
               CArr1 low, double cell, CIdx dims) {
    const int64_t size = int64_t(table_keys.shape(0));
    int bits = 0;
    while ((int64_t(1) << bits) < size) ++bits;
    return Hash{sorted_points.data(), sorted_index.data(), rank.data(), cell_starts.data(), table_keys.data(),
                table_cells.data(), dims.data(), low.data(), cell, 1.0 / cell, cell * cell, 64 - bits, size - 1};
}

int64_t hash_query(CArr2 queries, CArr2 rotation, CArr1 translation, CIdx warm, CIdx rank, CArr2 sorted_points,
                   CIdx sorted_index, CIdx cell_starts, CIdx table_keys, CIdx table_cells, CArr1 low_, double cell,
                   CIdx dims_, CArr2 tree_points, CIdx tree_order, CIdx tree_rank, CIdx tree_starts, CIdx tree_ends,
                   CIdx tree_lefts, CArr2 tree_boxes, bool use_hash, Arr1 out_distances, Idx out_indices,
                   int threads) {
    Tree t{tree_points.data(), tree_order.data(), tree_starts.data(), tree_ends.data(), tree_lefts.data(),
           tree_boxes.data(), int64_t(tree_points.shape(0))};
    const Hash h = make_hash(sorted_points, sorted_index, rank, cell_starts, table_keys, table_cells, low_, cell, dims_);
    const int64_t count = int64_t(queries.shape(0));
    const double *q = queries.data(), *r = rotation.data(), *tr = translation.data();
    const int64_t *w = warm.data(), *trank = tree_rank.data();
    double *od = out_distances.data();
    int64_t *oi = out_indices.data();
    const int64_t pieces = piece_count(count, QUERY_PIECE);
    std::vector<int64_t> misses(pieces, 0);
    if (count < PARALLEL_QUERY_MIN) threads = 1;
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        int64_t end = std::min(count, (piece + 1) * QUERY_PIECE);
        int64_t piece_misses = 0;
        for (int64_t i = piece * QUERY_PIECE; i < end; ++i) {
            double qx, qy, qz;
            mapped(q, i, r, tr, qx, qy, qz);
            piece_misses += hash_nearest(h, t, trank, qx, qy, qz, w[i], use_hash, od[i], oi[i]);
        }
        misses[piece] = piece_misses;
    });
    int64_t total = 0;
    for (int64_t m : misses) total += m;
    return total;
}

void hash_graph(const Hash &h, int64_t count, int64_t k, int32_t *neighbours, double *radii, int threads) {
    const double *sp = h.sorted_points;
    const int64_t *cs = h.cell_starts, *dims = h.dims;
    const double cell = h.cell;
    // Below one cell by a margin for the rounding of the cell coordinates.
    const double reach = h.limit * (1.0 - 1e-6);
    parallel_pieces(piece_count(count, QUERY_PIECE), threads, [&](int64_t piece) {
        double best[GRAPH_K_MAX];
        int64_t slots[GRAPH_K_MAX];
        const int64_t end = std::min(count, (piece + 1) * QUERY_PIECE);
        for (int64_t p = piece * QUERY_PIECE; p < end; ++p) {
            const double qx = sp[3 * p], qy = sp[3 * p + 1], qz = sp[3 * p + 2];
            std::fill(best, best + k, INF);
            std::fill(slots, slots + k, p);
            const double fx = (qx - h.low[0]) * h.inverse_cell, fy = (qy - h.low[1]) * h.inverse_cell,
                         fz = (qz - h.low[2]) * h.inverse_cell;
            const int64_t cx = int64_t(std::floor(fx)), cy = int64_t(std::floor(fy)), cz = int64_t(std::floor(fz));
            const double ox = fx - cx, oy = fy - cy, oz = fz - cz;
            bool dense = false;
            // The point's own cell first: its near points bound the rest of the block early.
            for (int cube = 0; cube < 27 && !dense; ++cube) {
                const int offset = cube == 0 ? 13 : (cube <= 13 ? cube - 1 : cube);
                const int dx = offset % 3 - 1, dy = offset / 3 % 3 - 1, dz = offset / 9 - 1;
                const int64_t x = cx + dx, y = cy + dy, z = cz + dz;
                if (x < 0 || x >= dims[0] || y < 0 || y >= dims[1] || z < 0 || z >= dims[2]) continue;
                const double gx = dx == 0 ? 0.0 : ((dx < 0 ? ox : 1.0 - ox) * cell);
                const double gy = dy == 0 ? 0.0 : ((dy < 0 ? oy : 1.0 - oy) * cell);
                const double gz = dz == 0 ? 0.0 : ((dz < 0 ? oz : 1.0 - oz) * cell);
                if (gx * gx + gy * gy + gz * gz > std::min(best[k - 1], h.limit)) continue;
                const int64_t found = hash_cell(h, x + dims[0] * (y + dims[1] * z));
                if (found < 0) continue;
                if (cs[found + 1] - cs[found] > CELL_SCAN_MAX) {
                    dense = true;
                    break;
                }
                for (int64_t c = cs[found]; c < cs[found + 1]; ++c) {
                    const double ex = sp[3 * c] - qx, ey = sp[3 * c + 1] - qy, ez = sp[3 * c + 2] - qz;
                    keep_nearer(best, slots, k, ex * ex + ey * ey + ez * ez, c);
                }
            }
            for (int64_t j = 0; j < k; ++j) neighbours[k * p + j] = int32_t(slots[j]);
            radii[p] = dense ? -1.0 : std::min(best[k - 1], reach);
        }
    });
}

}  // namespace kernels
