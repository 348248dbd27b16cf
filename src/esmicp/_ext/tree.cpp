// KD-tree (tree.hpp): its build, the nearest and k-nearest queries, the neighbour graph.
#include "tree.hpp"

#include <stdexcept>
#include <vector>

namespace kernels {
namespace {

// Three-way quickselect of order[start:end] by coordinates (runs of equal values: linear).
void select_nth(int64_t *order, const double *coordinates, int64_t start, int64_t end, int64_t nth) {
    int64_t low = start, high = end - 1;
    while (high > low) {
        double a = coordinates[order[low]], b = coordinates[order[(low + high) / 2]], c = coordinates[order[high]];
        double pivot = std::max(std::min(a, b), std::min(std::max(a, b), c));
        int64_t less = low, i = low, greater = high;
        while (i <= greater) {
            double value = coordinates[order[i]];
            if (value < pivot) {
                std::swap(order[less], order[i]);
                ++less;
                ++i;
            } else if (value > pivot) {
                std::swap(order[greater], order[i]);
                --greater;
            } else {
                ++i;
            }
        }
        if (nth < less) high = less - 1;
        else if (nth > greater) low = greater + 1;
        else return;
    }
}

// Nodes of the subtree over `count` points (split at floor(count / 2) while above the leaf size).
int64_t subtree_nodes(int64_t count, int64_t leaf_size) {
    if (count <= leaf_size) return 1;
    return 1 + subtree_nodes(count / 2, leaf_size) + subtree_nodes(count - count / 2, leaf_size);
}

// One node of the build: its box, and when it holds more than `leaf_size` points its split (the
// median along the box's longest axis) into children numbered `left` and `left + 1`. True when
// split.
bool build_node(int64_t node, int64_t left, int64_t count, int64_t leaf_size, const double *columns, int64_t *ord,
                int64_t *st, int64_t *en, int64_t *lf, double *bx) {
    const int64_t start = st[node], end = en[node];
    // The node's box, its three axes in one pass over the node's points.
    double low[3] = {INF, INF, INF}, high[3] = {-INF, -INF, -INF};
    const double *xs = columns, *ys = xs + count, *zs = ys + count;
    for (int64_t k = start; k < end; ++k) {
        const int64_t point = ord[k];
        const double value[3] = {xs[point], ys[point], zs[point]};
        for (int a = 0; a < 3; ++a) {
            low[a] = std::min(low[a], value[a]);
            high[a] = std::max(high[a], value[a]);
        }
    }
    for (int a = 0; a < 3; ++a) {
        bx[6 * node + a] = low[a];
        bx[6 * node + 3 + a] = high[a];
    }
    if (end - start <= leaf_size) return false;
    int axis = 0;
    for (int c = 1; c < 3; ++c)
        if (bx[6 * node + 3 + c] - bx[6 * node + c] > bx[6 * node + 3 + axis] - bx[6 * node + axis]) axis = c;
    const int64_t middle = (start + end) / 2;
    select_nth(ord, columns + axis * count, start, end, middle);
    lf[node] = left;
    st[left] = start;
    en[left] = middle;
    st[left + 1] = middle;
    en[left + 1] = end;
    return true;
}

// The build of `root` and every node below it, depth first, the right child before the left, the
// children numbered from `nodes` on in that order.
void build_below(int64_t root, int64_t nodes, int64_t count, int64_t leaf_size, const double *columns, int64_t *ord,
                 int64_t *st, int64_t *en, int64_t *lf, double *bx) {
    std::vector<int64_t> stack{root};
    while (!stack.empty()) {
        const int64_t node = stack.back();
        stack.pop_back();
        if (!build_node(node, nodes, count, leaf_size, columns, ord, st, en, lf, bx)) continue;
        stack.push_back(nodes);
        stack.push_back(nodes + 1);
        nodes += 2;
    }
}

}  // namespace

int64_t build_tree(CArr2 points, int64_t leaf_size, Arr2 tree_points, Idx order, Idx starts, Idx ends, Idx lefts,
                   Arr2 boxes, int threads) {
    const int64_t count = int64_t(points.shape(0));
    const double *p = points.data();
    int64_t *ord = order.data();
    int64_t *st = starts.data(), *en = ends.data(), *lf = lefts.data();
    double *bx = boxes.data();
    const int64_t capacity = int64_t(starts.shape(0));
    if (count < PARALLEL_BUILD_MIN) threads = 1;
    if (threads <= 0) threads = int(std::max(1u, std::thread::hardware_concurrency()));
    std::vector<double> columns(3 * count);
    // The top levels split in turn; below them, each subtree is built on its own (parallel_pieces),
    // its nodes numbered from where the depth-first build of the whole tree numbers them: a
    // subtree's node count depends only on its point count, so every array is the same whatever
    // the number of threads.
    struct Subtree {
        int64_t node, first;
    };
    std::vector<Subtree> subtrees;
    int64_t nodes = 1;
    {
        GilReleased release;
        for (int64_t k = 0; k < count; ++k) {
            ord[k] = k;
            for (int a = 0; a < 3; ++a) columns[a * count + k] = p[3 * k + a];
        }
        std::fill(lf, lf + capacity, int64_t(-1));
        st[0] = 0;
        en[0] = count;
        int depth = 0;
        while ((int64_t(1) << depth) < int64_t(BUILD_SUBTREES_PER_THREAD) * threads) ++depth;
        if (threads <= 1) depth = 0;
        // (node, depth), depth first, the right child before the left, as build_below visits them.
        std::vector<std::pair<int64_t, int>> stack{{0, 0}};
        while (!stack.empty()) {
            auto [node, level] = stack.back();
            stack.pop_back();
            const int64_t size = en[node] - st[node];
            if (level == depth || size <= leaf_size) {
                subtrees.push_back({node, nodes});
                nodes += subtree_nodes(size, leaf_size) - 1;
                continue;
            }
            const int64_t left = nodes;
            build_node(node, left, count, leaf_size, columns.data(), ord, st, en, lf, bx);
            nodes += 2;
            stack.push_back({left, level + 1});
            stack.push_back({left + 1, level + 1});
        }
    }
    if (nodes > capacity) throw std::invalid_argument("build_tree: more nodes than the arrays hold");
    parallel_pieces(int64_t(subtrees.size()), threads, [&](int64_t piece) {
        const Subtree &subtree = subtrees[size_t(piece)];
        build_below(subtree.node, subtree.first, count, leaf_size, columns.data(), ord, st, en, lf, bx);
    });
    {
        GilReleased release;
        double *tp = tree_points.data();
        for (int64_t k = 0; k < count; ++k)
            for (int a = 0; a < 3; ++a) tp[3 * k + a] = p[3 * ord[k] + a];
    }
    return nodes;
}

void tree_query(CArr2 queries, CArr2 rotation, CArr1 translation, CIdx warm, CIdx rank, CArr2 tree_points,
                CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes, Arr1 out_distances, Idx out_indices,
                int threads) {
    Tree t{tree_points.data(), order.data(), starts.data(), ends.data(), lefts.data(), boxes.data(),
           int64_t(tree_points.shape(0))};
    const int64_t count = int64_t(queries.shape(0));
    const double *q = queries.data(), *r = rotation.data(), *tr = translation.data();
    const int64_t *w = warm.data(), *rk = rank.data();
    double *od = out_distances.data();
    int64_t *oi = out_indices.data();
    if (count < PARALLEL_QUERY_MIN) threads = 1;
    parallel_pieces(piece_count(count, QUERY_PIECE), threads, [&](int64_t piece) {
        int64_t end = std::min(count, (piece + 1) * QUERY_PIECE);
        for (int64_t i = piece * QUERY_PIECE; i < end; ++i) {
            double x, y, z;
            mapped(q, i, r, tr, x, y, z);
            tree_nearest(t, rk, x, y, z, w[i], od[i], oi[i]);
        }
    });
}

void tree_within(CArr2 points, CArr2 rotations, CArr2 translations, double bound, Arr2 out_distances,
                 CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes, int threads) {
    Tree t{tree_points.data(), order.data(), starts.data(), ends.data(), lefts.data(), boxes.data(),
           int64_t(tree_points.shape(0))};
    const int64_t n = int64_t(points.shape(0)), maps = int64_t(rotations.shape(0));
    if (points.shape(1) != 3 || rotations.shape(1) != 9 || translations.shape(0) != size_t(maps) ||
        translations.shape(1) != 3 || out_distances.shape(0) != size_t(maps) || out_distances.shape(1) != size_t(n))
        throw std::invalid_argument("tree_within: points (n, 3), rotations (K, 9), translations (K, 3), distances (K, n)");
    if (!(bound >= 0.0)) throw std::invalid_argument("tree_within: the bound must be a distance >= 0");
    // Squared distances strictly below this start: every point within the bound (sqrt rounds to it).
    const double start = bound * bound * (1.0 + 1e-12);
    const int64_t count = maps * n;
    const double *q = points.data(), *r = rotations.data(), *tr = translations.data();
    double *od = out_distances.data();
    if (count < PARALLEL_QUERY_MIN) threads = 1;
    parallel_pieces(piece_count(count, QUERY_PIECE), threads, [&](int64_t piece) {
        int64_t end = std::min(count, (piece + 1) * QUERY_PIECE);
        for (int64_t j = piece * QUERY_PIECE; j < end; ++j) {
            const int64_t k = j / n, i = j % n;
            double x, y, z;
            mapped(q, i, r + 9 * k, tr + 3 * k, x, y, z);
            double best = start;
            int64_t slot = -1;
            if (t.count > 0) nearest(t, x, y, z, best, slot);
            od[j] = slot >= 0 ? std::sqrt(best) : INF;
        }
    });
}

void nearest_k(const Tree &t, int64_t node, double x, double y, double z, int64_t k, double *best, int64_t *slots) {
    const int64_t left = t.lefts[node];
    if (left >= 0) {
        const double bounds[2] = {box_distance(t.boxes + 6 * left, x, y, z),
                                  box_distance(t.boxes + 6 * (left + 1), x, y, z)};
        const int first = bounds[1] < bounds[0] ? 1 : 0;
        for (int child : {first, 1 - first})
            if (bounds[child] < best[k - 1]) nearest_k(t, left + child, x, y, z, k, best, slots);
        return;
    }
    for (int64_t s = t.starts[node]; s < t.ends[node]; ++s) {
        const double ex = t.points[3 * s] - x, ey = t.points[3 * s + 1] - y, ez = t.points[3 * s + 2] - z;
        keep_nearer(best, slots, k, ex * ex + ey * ey + ez * ez, s);
    }
}

void neighbour_graph(CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes,
                     Idx2 out_neighbours, Arr1 out_radii, int threads) {
    Tree t{tree_points.data(), order.data(), starts.data(), ends.data(), lefts.data(), boxes.data(),
           int64_t(tree_points.shape(0))};
    const int64_t k = int64_t(out_neighbours.shape(1));
    if (k < 1 || k > GRAPH_K_MAX || k > t.count || int64_t(out_neighbours.shape(0)) != t.count ||
        int64_t(out_radii.shape(0)) != t.count)
        throw std::invalid_argument("neighbour_graph: out_neighbours (M, k) with 1 <= k <= min(M, 64), out_radii (M,)");
    int64_t *neighbours = out_neighbours.data();
    double *radii = out_radii.data();
    each_k_nearest(t, t.points, t.count, k, threads, 0, [&](int64_t s, const double *best, const int64_t *slots) {
        const int64_t i = t.order[s];
        for (int64_t j = 0; j < k; ++j) neighbours[k * i + j] = t.order[slots[j]];
        radii[i] = best[k - 1];
    });
}

void tree_knn(CArr2 queries, CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes,
              Arr2 out_distances, Idx2 out_indices, int threads) {
    Tree t{tree_points.data(), order.data(), starts.data(), ends.data(), lefts.data(), boxes.data(),
           int64_t(tree_points.shape(0))};
    const int64_t count = int64_t(queries.shape(0)), k = int64_t(out_indices.shape(1));
    if (queries.shape(1) != 3 || k < 1 || k > GRAPH_K_MAX || k > t.count || int64_t(out_indices.shape(0)) != count ||
        int64_t(out_distances.shape(0)) != count || int64_t(out_distances.shape(1)) != k)
        throw std::invalid_argument("tree_knn: queries (Q, 3), out_distances and out_indices (Q, k), 1 <= k <= min(M, 64)");
    double *distances = out_distances.data();
    int64_t *indices = out_indices.data();
    each_k_nearest(t, queries.data(), count, k, threads, PARALLEL_QUERY_MIN,
                   [&](int64_t i, const double *best, const int64_t *slots) {
        for (int64_t j = 0; j < k; ++j) {
            distances[k * i + j] = std::sqrt(best[j]);
            indices[k * i + j] = slots[j] >= 0 ? t.order[slots[j]] : t.count;
        }
    });
}

}  // namespace kernels
