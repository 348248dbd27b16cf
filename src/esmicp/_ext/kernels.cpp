// Compiled kernels of esmicp: the KD-tree, the voxel hash and the pair moments.
//
// Threads: a small pool of std::thread per call (no persistent runtime, so a fork() after a call
// is safe), sized by the caller's `threads`. The GIL is released during the work; the calling
// thread checks for signals every few milliseconds (PyErr_CheckSignals with the GIL taken back),
// and a pending Ctrl-C stops every thread at its next piece and raises KeyboardInterrupt.
// Work is cut into pieces of fixed size (independent of the thread count), and partial sums are
// added in piece order: results are bitwise the same whatever the number of threads.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <pthread.h>
#include <stdexcept>
#include <limits>
#include <mutex>
#include <thread>
#include <type_traits>
#include <vector>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace nb = nanobind;

using CArr2 = nb::ndarray<const double, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using CArr1 = nb::ndarray<const double, nb::ndim<1>, nb::c_contig, nb::device::cpu>;
using Arr1 = nb::ndarray<double, nb::ndim<1>, nb::c_contig, nb::device::cpu>;
using Arr2 = nb::ndarray<double, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using CIdx = nb::ndarray<const int64_t, nb::ndim<1>, nb::c_contig, nb::device::cpu>;
using Idx = nb::ndarray<int64_t, nb::ndim<1>, nb::c_contig, nb::device::cpu>;
using Idx2 = nb::ndarray<int64_t, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using CIdx2 = nb::ndarray<const int64_t, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using F32Arr2 = nb::ndarray<float, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using CF32Arr2 = nb::ndarray<const float, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using CF32Arr1 = nb::ndarray<const float, nb::ndim<1>, nb::c_contig, nb::device::cpu>;
using F32Arr1 = nb::ndarray<float, nb::ndim<1>, nb::c_contig, nb::device::cpu>;

namespace {

constexpr int STACK = 96;
constexpr double INF = std::numeric_limits<double>::infinity();
constexpr uint64_t HASH_MULTIPLIER = 0x9E3779B97F4A7C15ULL;

// ---------------------------------------------------------------------------------------------
// Parallel loop over pieces [0, pieces), interruptible.
template <class F>
void parallel_pieces(int64_t pieces, int threads, F &&work) {
    if (pieces <= 0) return;
    unsigned hw = std::max(1u, std::thread::hardware_concurrency());
    if (threads <= 0) threads = int(hw);
    threads = int(std::min<int64_t>(threads, pieces));
    std::atomic<int64_t> next{0};
    std::atomic<bool> cancel{false};
    bool interrupted = false;
    {
        nb::gil_scoped_release release;
        auto runner = [&]() {
            while (!cancel.load(std::memory_order_relaxed)) {
                int64_t piece = next.fetch_add(1);
                if (piece >= pieces) break;
                work(piece);
            }
        };
        std::vector<std::thread> pool;
        pool.reserve(threads - 1);
        for (int t = 1; t < threads; ++t) pool.emplace_back(runner);
        auto last_check = std::chrono::steady_clock::now();
        while (!cancel.load(std::memory_order_relaxed)) {
            int64_t piece = next.fetch_add(1);
            if (piece >= pieces) break;
            work(piece);
            auto now = std::chrono::steady_clock::now();
            if (now - last_check > std::chrono::milliseconds(5)) {
                last_check = now;
                nb::gil_scoped_acquire acquire;
                if (PyErr_CheckSignals() != 0) {
                    interrupted = true;
                    cancel.store(true);
                }
            }
        }
        for (auto &thread : pool) thread.join();
    }
    if (interrupted) throw nb::python_error();
}

// ---------------------------------------------------------------------------------------------
// Persistent helper threads for the short calls of the local loop (Index::step below
// POOLED_STEP_MAX points): starting a std::thread per call costs more than half the work of
// 1,000 queries, so these threads are started once and wait between calls, spinning for
// POOL_SPIN (the Python between two iterations takes less), then sleeping on a condition
// variable (no CPU used while idle). fork(): the child forgets the pool (its threads do not
// exist there) and starts its own on first use. Same contract as parallel_pieces (every piece
// once, results independent of the threads), without signal checks: a call is under a
// millisecond, the loop around it sees Ctrl-C.
constexpr auto POOL_SPIN = std::chrono::microseconds(200);

//: Below this many source points, Index::step runs both its passes (queries, moments) on the
//: persistent helper threads (a call of that size lasts a few milliseconds at most: the loop
//: around it sees Ctrl-C in time).
constexpr int64_t POOLED_STEP_MAX = 32768;

struct Pool {
    std::mutex mutex;
    std::condition_variable wake;
    std::atomic<uint64_t> generation{0};  // bumped for each job
    std::atomic<int> active{0};           // helpers inside the current job
    // The job (read under the mutex): its pieces, the shared counter, the work.
    bool open = false;
    int seats = 0;  // helpers that may still join
    int64_t pieces = 0;
    std::atomic<int64_t> *next = nullptr;
    void (*call)(void *, int64_t) = nullptr;
    void *context = nullptr;
    int size = 0;

    void helper() {
        uint64_t seen = 0;
        for (;;) {
            auto start = std::chrono::steady_clock::now();
            while (generation.load(std::memory_order_acquire) == seen) {
                if (std::chrono::steady_clock::now() - start > POOL_SPIN) {
                    std::unique_lock<std::mutex> lock(mutex);
                    wake.wait(lock, [&] { return generation.load(std::memory_order_acquire) != seen; });
                    break;
                }
                std::this_thread::yield();
            }
            int64_t total;
            std::atomic<int64_t> *counter;
            void (*work)(void *, int64_t);
            void *data;
            {
                std::lock_guard<std::mutex> lock(mutex);
                seen = generation.load(std::memory_order_acquire);
                if (!open || seats == 0) continue;
                --seats;
                active.fetch_add(1, std::memory_order_acq_rel);
                total = pieces, counter = next, work = call, data = context;
            }
            for (int64_t piece = counter->fetch_add(1); piece < total; piece = counter->fetch_add(1)) work(data, piece);
            active.fetch_sub(1, std::memory_order_acq_rel);
        }
    }
};

Pool *the_pool = nullptr;
std::mutex pool_start;

void forget_pool_in_child() { the_pool = nullptr; }  // leaked: its threads and locks are the parent's

Pool &pool_of(int helpers) {
    std::lock_guard<std::mutex> lock(pool_start);
    static bool registered = (pthread_atfork(nullptr, nullptr, forget_pool_in_child), true);
    (void)registered;
    if (the_pool == nullptr) the_pool = new Pool();
    while (the_pool->size < helpers) {
        Pool *pool = the_pool;
        std::thread([pool] { pool->helper(); }).detach();
        ++the_pool->size;
    }
    return *the_pool;
}

// Releases the GIL for its lifetime when the calling thread holds it (a kernel called from Python),
// and does nothing when it does not (a kernel called from a helper thread or a released region).
struct ReleaseIfHeld {
    PyThreadState *state = nullptr;
    ReleaseIfHeld() {
        if (PyGILState_Check()) state = PyEval_SaveThread();
    }
    ~ReleaseIfHeld() {
        if (state != nullptr) PyEval_RestoreThread(state);
    }
    ReleaseIfHeld(const ReleaseIfHeld &) = delete;
    ReleaseIfHeld &operator=(const ReleaseIfHeld &) = delete;
};

template <class F>
void pooled_pieces(int64_t pieces, int threads, F &&work) {
    if (pieces <= 0) return;
    unsigned hw = std::max(1u, std::thread::hardware_concurrency());
    if (threads <= 0) threads = int(hw);
    threads = int(std::min<int64_t>(threads, pieces));
    // The GIL is released on every path, one thread included: several Python threads each running
    // a registration on one thread (register_many's thread pool, workers=1) then run in parallel.
    ReleaseIfHeld release;
    if (threads <= 1) {
        for (int64_t piece = 0; piece < pieces; ++piece) work(piece);
        return;
    }
    Pool &pool = pool_of(threads - 1);
    std::atomic<int64_t> next{0};
    {
        std::lock_guard<std::mutex> lock(pool.mutex);
        pool.open = true;
        pool.seats = threads - 1;
        pool.pieces = pieces;
        pool.next = &next;
        pool.call = [](void *data, int64_t piece) { (*static_cast<std::remove_reference_t<F> *>(data))(piece); };
        pool.context = static_cast<void *>(&work);
        pool.generation.fetch_add(1, std::memory_order_acq_rel);
    }
    pool.wake.notify_all();
    for (int64_t piece = next.fetch_add(1); piece < pieces; piece = next.fetch_add(1)) work(piece);
    {
        std::lock_guard<std::mutex> lock(pool.mutex);
        pool.open = false;  // no helper joins from here on
    }
    while (pool.active.load(std::memory_order_acquire) != 0) std::this_thread::yield();
}

inline int64_t piece_count(int64_t count, int64_t size) { return (count + size - 1) / size; }

// ---------------------------------------------------------------------------------------------
// KD-tree.
struct Tree {
    const double *points;  // (M, 3) in tree order
    const int64_t *order;  // tree slot -> target index
    const int64_t *starts, *ends, *lefts;
    const double *boxes;  // (nodes, 6): low xyz, high xyz
    int64_t count;
};

inline double box_distance(const double *box, double x, double y, double z) {
    double total = 0.0, gap;
    const double q[3] = {x, y, z};
    for (int a = 0; a < 3; ++a) {
        gap = box[a] - q[a];
        if (gap > 0.0) {
            total += gap * gap;
        } else {
            gap = q[a] - box[3 + a];
            if (gap > 0.0) total += gap * gap;
        }
    }
    return total;
}

inline void nearest(const Tree &t, double x, double y, double z, double &best, int64_t &best_slot) {
    int64_t stack_nodes[STACK];
    double stack_bounds[STACK];
    stack_nodes[0] = 0;
    stack_bounds[0] = box_distance(t.boxes, x, y, z);
    int depth = 1;
    while (depth > 0) {
        --depth;
        int64_t node = stack_nodes[depth];
        if (stack_bounds[depth] >= best) continue;
        int64_t left = t.lefts[node];
        if (left < 0) {
            for (int64_t k = t.starts[node]; k < t.ends[node]; ++k) {
                double ex = t.points[3 * k] - x, ey = t.points[3 * k + 1] - y, ez = t.points[3 * k + 2] - z;
                double squared = ex * ex + ey * ey + ez * ez;
                if (squared < best) {
                    best = squared;
                    best_slot = k;
                }
            }
            continue;
        }
        double near_bound = box_distance(t.boxes + 6 * left, x, y, z);
        double far_bound = box_distance(t.boxes + 6 * (left + 1), x, y, z);
        int64_t near_node = left, far_node = left + 1;
        if (far_bound < near_bound) {
            std::swap(near_node, far_node);
            std::swap(near_bound, far_bound);
        }
        if (far_bound < best) {
            stack_nodes[depth] = far_node;
            stack_bounds[depth] = far_bound;
            ++depth;
        }
        if (near_bound < best) {
            stack_nodes[depth] = near_node;
            stack_bounds[depth] = near_bound;
            ++depth;
        }
    }
}

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

// Builds the tree into the caller's arrays (capacity nodes); returns the number of nodes.
int64_t build_tree(CArr2 points, int64_t leaf_size, Arr2 tree_points, Idx order, Idx starts, Idx ends, Idx lefts,
                   Arr2 boxes) {
    const int64_t count = int64_t(points.shape(0));
    const double *p = points.data();
    int64_t *ord = order.data();
    int64_t *st = starts.data(), *en = ends.data(), *lf = lefts.data();
    double *bx = boxes.data();
    const int64_t capacity = int64_t(starts.shape(0));
    int64_t nodes = 1;
    {
        nb::gil_scoped_release release;
        std::vector<double> columns(3 * count);
        for (int64_t k = 0; k < count; ++k) {
            ord[k] = k;
            for (int a = 0; a < 3; ++a) columns[a * count + k] = p[3 * k + a];
        }
        for (int64_t n = 0; n < capacity; ++n) lf[n] = -1;
        std::vector<int64_t> stack;
        stack.push_back(0);
        st[0] = 0;
        en[0] = count;
        while (!stack.empty()) {
            int64_t node = stack.back();
            stack.pop_back();
            int64_t start = st[node], end = en[node];
            for (int a = 0; a < 3; ++a) {
                double low = INF, high = -INF;
                for (int64_t k = start; k < end; ++k) {
                    double value = columns[a * count + ord[k]];
                    low = std::min(low, value);
                    high = std::max(high, value);
                }
                bx[6 * node + a] = low;
                bx[6 * node + 3 + a] = high;
            }
            if (end - start <= leaf_size) continue;
            int axis = 0;
            for (int c = 1; c < 3; ++c)
                if (bx[6 * node + 3 + c] - bx[6 * node + c] > bx[6 * node + 3 + axis] - bx[6 * node + axis]) axis = c;
            int64_t middle = (start + end) / 2;
            select_nth(ord, columns.data() + axis * count, start, end, middle);
            int64_t left = nodes;
            nodes += 2;
            lf[node] = left;
            st[left] = start;
            en[left] = middle;
            st[left + 1] = middle;
            en[left + 1] = end;
            stack.push_back(left);
            stack.push_back(left + 1);
        }
        double *tp = tree_points.data();
        for (int64_t k = 0; k < count; ++k)
            for (int a = 0; a < 3; ++a) tp[3 * k + a] = p[3 * ord[k] + a];
    }
    return nodes;
}

inline void mapped(const double *q, int64_t i, const double *r, const double *t, double &x, double &y, double &z) {
    const double a = q[3 * i], b = q[3 * i + 1], c = q[3 * i + 2];
    x = r[0] * a + r[1] * b + r[2] * c + t[0];
    y = r[3] * a + r[4] * b + r[5] * c + t[1];
    z = r[6] * a + r[7] * b + r[8] * c + t[2];
}

constexpr int64_t QUERY_PIECE = 256;

//: Queries of fewer points than this run on the calling thread alone.
constexpr int64_t PARALLEL_QUERY_MIN = 2048;

// Nearest point of the tree to (x, y, z), seeded with the target point `warm` (-1: none): its
// distance and target index (t.count when the tree is empty of candidates).
inline void tree_nearest(const Tree &t, const int64_t *tree_rank, double x, double y, double z, int64_t warm,
                         double &distance, int64_t &index) {
    double best = INF;
    int64_t slot = -1;
    if (warm >= 0) {
        slot = tree_rank[warm];
        double ex = t.points[3 * slot] - x, ey = t.points[3 * slot + 1] - y, ez = t.points[3 * slot + 2] - z;
        best = ex * ex + ey * ey + ez * ez;
    }
    nearest(t, x, y, z, best, slot);
    distance = std::sqrt(best);
    index = slot >= 0 ? t.order[slot] : t.count;
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

// ---------------------------------------------------------------------------------------------
// Voxel hash.
inline int64_t hash_slot(int64_t key, int shift) {
    return int64_t((uint64_t(key) * HASH_MULTIPLIER) >> uint64_t(shift));
}

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

//: Cells holding more distinct points than this are not scanned: the query goes to the tree
//: (exact, logarithmic), so that no dense cell makes the hash quadratic.
constexpr int64_t CELL_SCAN_MAX = 256;

// Insert (squared, slot) into the k best so far (best ascending, slots alongside), if it is nearer
// than the k-th: the k-nearest searches of the tree and of the voxel hash share it.
inline void keep_nearer(double *best, int64_t *slots, int64_t k, double squared, int64_t slot) {
    if (squared >= best[k - 1]) return;
    int64_t j = k - 1;
    for (; j > 0 && best[j - 1] > squared; --j) {
        best[j] = best[j - 1];
        slots[j] = slots[j - 1];
    }
    best[j] = squared;
    slots[j] = slot;
}

struct Hash {
    const double *sorted_points;
    const int64_t *sorted_index, *rank, *cell_starts, *table_keys, *table_cells, *dims;
    const double *low;
    double cell, inverse_cell, limit;
    int shift;
    int64_t mask;
};

Hash make_hash(CArr2 sorted_points, CIdx sorted_index, CIdx rank, CIdx cell_starts, CIdx table_keys, CIdx table_cells,
               CArr1 low, double cell, CIdx dims) {
    const int64_t size = int64_t(table_keys.shape(0));
    int bits = 0;
    while ((int64_t(1) << bits) < size) ++bits;
    return Hash{sorted_points.data(), sorted_index.data(), rank.data(), cell_starts.data(), table_keys.data(),
                table_cells.data(), dims.data(), low.data(), cell, 1.0 / cell, cell * cell, 64 - bits, size - 1};
}

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

// ---------------------------------------------------------------------------------------------
// Neighbour graphs.
// k near points of every point (itself among them) and a squared radius: every point strictly
// nearer than that to a point is in its list (the k nearest and the distance to the k-th, for the
// global search's graph by target index; see hash_graph for the step's, by hash order).
template <class I>
struct NeighbourGraph {
    const I *neighbours;  // (M, k) point numbers
    const double *radii;  // (M,) squared radii
    int64_t k;
};

//: Descent steps along the graph before a query goes to the tree.
constexpr int GRAPH_DESCENT_MAX = 8;

// The certified walk from a warm start p (best: squared distance from (x, y, z) to p, `points` the
// coordinates the graph's numbers refer to): moves p to a nearer member of its list while there
// is one; when p's list holds none nearer and 2 |q - p| is within p's radius, every point nearer
// to q than p (within 2 |q - p| of p) is in that list, so p is the exact nearest: returns true.
// Otherwise (no certificate within GRAPH_DESCENT_MAX steps) false, with p and best the nearest
// point met, a seed for an exact search.
template <class I>
inline bool graph_descent(const NeighbourGraph<I> &graph, const double *points, double x, double y, double z,
                          int64_t &p, double &best) {
    for (int step = 0; step < GRAPH_DESCENT_MAX; ++step) {
        const I *list = graph.neighbours + graph.k * p;
        int64_t next = -1;
        for (int64_t j = 0; j < graph.k; ++j) {
            const int64_t c = int64_t(list[j]);
            const double ex = points[3 * c] - x, ey = points[3 * c + 1] - y, ez = points[3 * c + 2] - z;
            const double candidate = ex * ex + ey * ey + ez * ez;
            if (candidate < best) {
                best = candidate;
                next = c;
            }
        }
        if (next < 0) return 4.0 * best * (1.0 + 1e-9) <= graph.radii[p];
        p = next;
    }
    return false;
}

//: Most neighbours per point of a neighbour graph.
constexpr int64_t GRAPH_K_MAX = 64;

// The neighbour graph of a voxel hash's points by sorted position (row p and its entries are rows
// of h.sorted_points), from the 3 x 3 x 3 cells around each point: its k nearest there, and as
// radius the squared distance to the k-th but at most one cell (every point within one cell of p
// is in that block, so every point strictly nearer than the radius is in the list). A point next
// to a dense cell (more than CELL_SCAN_MAX points) gets radius -1: it never certifies.
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

// ---------------------------------------------------------------------------------------------
// Pair moments.
constexpr int64_t SUM_PIECE = 4096;

// The 17 moments of the pairs (R x_i + t, target[indices[i]]) with weights
// exp(-(d_i^2 - shift) * scale) (1 where scale is 0): sum w, sum w^2, the weighted centroids and
// the weighted cross-covariance (see esmicp.core.moments.pair_moments). `pooled`: on the
// persistent helper threads (Index::step below POOLED_STEP_MAX points), else threads per call.
void moments_of_pairs(const double *s, int64_t count, const double *r, const double *tr, const double *tg,
                      const int64_t *ix, const double *d, double scale, double shift, double *o, int threads,
                      bool pooled) {
    double sref[3], tref[3];
    for (int a = 0; a < 3; ++a) {
        sref[a] = r[3 * a] * s[0] + r[3 * a + 1] * s[1] + r[3 * a + 2] * s[2] + tr[a];
        tref[a] = tg[3 * ix[0] + a];
    }
    const int64_t pieces = piece_count(count, SUM_PIECE);
    std::vector<double> partial(17 * pieces, 0.0);
    auto moments = [&](int64_t piece) {
        double w0 = 0, w1 = 0, ax = 0, ay = 0, az = 0, bx = 0, by = 0, bz = 0;
        double c[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
        int64_t end = std::min(count, (piece + 1) * SUM_PIECE);
        for (int64_t i = piece * SUM_PIECE; i < end; ++i) {
            double w = scale > 0.0 ? std::exp(-(d[i] * d[i] - shift) * scale) : 1.0;
            double sx, sy, sz;
            mapped(s, i, r, tr, sx, sy, sz);
            sx -= sref[0];
            sy -= sref[1];
            sz -= sref[2];
            int64_t j = ix[i];
            double tx = tg[3 * j] - tref[0], ty = tg[3 * j + 1] - tref[1], tz = tg[3 * j + 2] - tref[2];
            w0 += w;
            w1 += w * w;
            double wx = w * sx, wy = w * sy, wz = w * sz;
            ax += wx;
            ay += wy;
            az += wz;
            bx += w * tx;
            by += w * ty;
            bz += w * tz;
            c[0] += wx * tx; c[1] += wx * ty; c[2] += wx * tz;
            c[3] += wy * tx; c[4] += wy * ty; c[5] += wy * tz;
            c[6] += wz * tx; c[7] += wz * ty; c[8] += wz * tz;
        }
        double *row = partial.data() + 17 * piece;
        row[0] = w0; row[1] = w1; row[2] = ax; row[3] = ay; row[4] = az; row[5] = bx; row[6] = by; row[7] = bz;
        for (int k = 0; k < 9; ++k) row[8 + k] = c[k];
    };
    if (pooled) {
        pooled_pieces(pieces, threads, moments);
    } else {
        parallel_pieces(pieces, count < 8192 ? 1 : threads, moments);
    }
    double sums[17] = {0};
    for (int64_t p = 0; p < pieces; ++p)
        for (int k = 0; k < 17; ++k) sums[k] += partial[17 * p + k];
    const double total = sums[0];
    o[0] = total;
    o[1] = sums[1];
    for (int a = 0; a < 3; ++a)
        for (int b = 0; b < 3; ++b)
            o[8 + 3 * a + b] = sums[8 + 3 * a + b] / total - (sums[2 + a] / total) * (sums[5 + b] / total);
    for (int a = 0; a < 3; ++a) {
        o[2 + a] = sums[2 + a] / total + sref[a];
        o[5 + a] = sums[5 + a] / total + tref[a];
    }
}

void pair_moments(CArr2 source, CArr2 rotation, CArr1 translation, CArr2 target, CIdx indices, CArr1 distances,
                  double scale, double shift, Arr1 out, int threads) {
    moments_of_pairs(source.data(), int64_t(source.shape(0)), rotation.data(), translation.data(), target.data(),
                     indices.data(), distances.data(), scale, shift, out.data(), threads, false);
}

// Eigen-decomposition of a symmetric N x N matrix by cyclic Jacobi sweeps (accurate to rounding, no
// special case for rank-deficient matrices): on return a is diagonal (the eigenvalues) and the
// columns of v are the unit eigenvectors. Used by best_rotation (N = 4) and knn_normals (N = 3).
template <int N>
void jacobi_eigen(double (&a)[N][N], double (&v)[N][N]) {
    for (int i = 0; i < N; ++i)
        for (int j = 0; j < N; ++j) v[i][j] = i == j ? 1.0 : 0.0;
    for (int sweep = 0; sweep < 64; ++sweep) {
        double off = 0.0, diagonal = 0.0;
        for (int i = 0; i < N; ++i) {
            diagonal += a[i][i] * a[i][i];
            for (int j = i + 1; j < N; ++j) off += a[i][j] * a[i][j];
        }
        if (off <= 1e-36 * diagonal || off == 0.0) break;
        for (int p = 0; p < N - 1; ++p) {
            for (int q = p + 1; q < N; ++q) {
                if (a[p][q] == 0.0) continue;
                double theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                double t = (theta >= 0 ? 1.0 : -1.0) / (std::fabs(theta) + std::sqrt(theta * theta + 1.0));
                double c = 1.0 / std::sqrt(t * t + 1.0), sn = t * c;
                for (int k = 0; k < N; ++k) {  // columns p, q of A
                    double akp = a[k][p], akq = a[k][q];
                    a[k][p] = c * akp - sn * akq;
                    a[k][q] = sn * akp + c * akq;
                }
                for (int k = 0; k < N; ++k) {  // rows p, q of A
                    double apk = a[p][k], aqk = a[q][k];
                    a[p][k] = c * apk - sn * aqk;
                    a[q][k] = sn * apk + c * aqk;
                }
                for (int k = 0; k < N; ++k) {
                    double vkp = v[k][p], vkq = v[k][q];
                    v[k][p] = c * vkp - sn * vkq;
                    v[k][q] = sn * vkp + c * vkq;
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Rotations from 3x3 matrices: Horn's quaternion method. The rotation R maximising trace(R H)
// (H = sum s t^T: the Kabsch rotation taking s onto t, reflection excluded) is the rotation of the
// eigenvector of the largest eigenvalue of a symmetric 4x4 matrix (jacobi_eigen).
void best_rotation(const double *h, double *r) {
    double scale = 0.0;
    for (int k = 0; k < 9; ++k) scale = std::max(scale, std::fabs(h[k]));
    if (!(scale > 0.0) || !std::isfinite(scale)) {
        if (std::isfinite(scale)) {  // H = 0: the identity, as the SVD gives
            for (int k = 0; k < 9; ++k) r[k] = (k % 4 == 0) ? 1.0 : 0.0;
        } else {
            for (int k = 0; k < 9; ++k) r[k] = std::numeric_limits<double>::quiet_NaN();
        }
        return;
    }
    const double xx = h[0] / scale, xy = h[1] / scale, xz = h[2] / scale, yx = h[3] / scale, yy = h[4] / scale,
                 yz = h[5] / scale, zx = h[6] / scale, zy = h[7] / scale, zz = h[8] / scale;
    double a[4][4] = {{xx + yy + zz, yz - zy, zx - xz, xy - yx},
                      {yz - zy, xx - yy - zz, xy + yx, zx + xz},
                      {zx - xz, xy + yx, -xx + yy - zz, yz + zy},
                      {xy - yx, zx + xz, yz + zy, -xx - yy + zz}};
    double v[4][4];
    jacobi_eigen<4>(a, v);
    int top = 0;
    for (int i = 1; i < 4; ++i)
        if (a[i][i] > a[top][top]) top = i;
    double w = v[0][top], x = v[1][top], y = v[2][top], z = v[3][top];
    const double norm = std::sqrt(w * w + x * x + y * y + z * z);
    w /= norm; x /= norm; y /= norm; z /= norm;
    r[0] = w * w + x * x - y * y - z * z; r[1] = 2 * (x * y - w * z);         r[2] = 2 * (x * z + w * y);
    r[3] = 2 * (x * y + w * z);         r[4] = w * w - x * x + y * y - z * z; r[5] = 2 * (y * z - w * x);
    r[6] = 2 * (x * z - w * y);         r[7] = 2 * (y * z + w * x);         r[8] = w * w - x * x - y * y + z * z;
}

// The rotation nearest (Frobenius) to the 3x3 matrix m: the one maximising trace(R^T m).
inline void nearest_rotation(const double *m, double *r) {
    const double transposed[9] = {m[0], m[3], m[6], m[1], m[4], m[7], m[2], m[5], m[8]};
    best_rotation(transposed, r);
}

inline double angle_of(const double *r) {
    const double sx = r[7] - r[5], sy = r[2] - r[6], sz = r[3] - r[1];
    return std::atan2(0.5 * std::sqrt(sx * sx + sy * sy + sz * sz), 0.5 * (r[0] + r[4] + r[8] - 1.0));
}

void kabsch(CArr2 cross_covariance, Arr2 out) { best_rotation(cross_covariance.data(), out.data()); }

void closest_rotation(CArr2 matrix, Arr2 out) { nearest_rotation(matrix.data(), out.data()); }

inline void add_outer(double *h, double w, double ax, double ay, double az, double bx, double by, double bz) {
    h[0] += w * ax * bx; h[1] += w * ax * by; h[2] += w * ax * bz;
    h[3] += w * ay * bx; h[4] += w * ay * by; h[5] += w * ay * bz;
    h[6] += w * az * bx; h[7] += w * az * by; h[8] += w * az * bz;
}

void paper_moments(CArr2 source, CArr2 rotation, CArr1 translation, CArr2 target, CIdx indices, CArr1 distances,
                   double scale, Arr1 out, int threads) {
    const int64_t count = int64_t(source.shape(0));
    const double *s = source.data(), *r = rotation.data(), *tr = translation.data(), *tg = target.data();
    const int64_t *ix = indices.data();
    const double *d = distances.data();
    const int64_t pieces = piece_count(count, SUM_PIECE);
    if (count < 8192) threads = 1;
    std::vector<double> partial(8 * pieces, 0.0);
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        double acc[8] = {0, 0, 0, 0, 0, 0, 0, 0};
        int64_t end = std::min(count, (piece + 1) * SUM_PIECE);
        for (int64_t i = piece * SUM_PIECE; i < end; ++i) {
            double x, y, z;
            mapped(s, i, r, tr, x, y, z);
            acc[0] += x; acc[1] += y; acc[2] += z;
            int64_t j = ix[i];
            acc[3] += tg[3 * j]; acc[4] += tg[3 * j + 1]; acc[5] += tg[3 * j + 2];
            double w = std::exp(-d[i] * d[i] * scale);
            acc[6] += w;
            acc[7] += w * w;
        }
        for (int k = 0; k < 8; ++k) partial[8 * piece + k] = acc[k];
    });
    double sums[8] = {0};
    for (int64_t p = 0; p < pieces; ++p)
        for (int k = 0; k < 8; ++k) sums[k] += partial[8 * p + k];
    double sb[3], tb[3];
    for (int a = 0; a < 3; ++a) {
        sb[a] = sums[a] / double(count);
        tb[a] = sums[3 + a] / double(count);
    }
    std::vector<double> blocks(9 * pieces, 0.0);
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        double h[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
        int64_t end = std::min(count, (piece + 1) * SUM_PIECE);
        for (int64_t i = piece * SUM_PIECE; i < end; ++i) {
            int64_t partner = ix[i];
            if (partner >= count) continue;
            double w = std::exp(-d[i] * d[i] * scale);
            bool mutual = ix[partner] == i;
            double first = w;
            if (mutual && partner > i) first = std::exp(-d[partner] * d[partner] * scale);
            double x, y, z;
            mapped(s, i, r, tr, x, y, z);
            int64_t k = ix[partner];
            add_outer(h, first, x - sb[0], y - sb[1], z - sb[2], tg[3 * k] - tb[0], tg[3 * k + 1] - tb[1],
                      tg[3 * k + 2] - tb[2]);
            if (!mutual) {
                mapped(s, partner, r, tr, x, y, z);
                int64_t j = ix[i];
                add_outer(h, w, x - sb[0], y - sb[1], z - sb[2], tg[3 * j] - tb[0], tg[3 * j + 1] - tb[1],
                          tg[3 * j + 2] - tb[2]);
            }
        }
        for (int k = 0; k < 9; ++k) blocks[9 * piece + k] = h[k];
    });
    double *o = out.data();
    for (int k = 0; k < 17; ++k) o[k] = 0.0;
    o[0] = sums[6];
    o[1] = sums[7];
    for (int a = 0; a < 3; ++a) {
        o[2 + a] = sb[a];
        o[5 + a] = tb[a];
    }
    for (int64_t p = 0; p < pieces; ++p)
        for (int k = 0; k < 9; ++k) o[8 + k] += blocks[9 * p + k];
}

// ---------------------------------------------------------------------------------------------
// Anderson acceleration of the local loop (esmicp.methods.acceleration): the whole proposal in
// one call. Poses are parametrised relative to a reference pose as (rotation vector, radians;
// translation / scale). The state (Python-owned, ANDERSON_STATE(window) numbers): the number of
// stored steps (0: no reference yet), the reference pose (16), then window + 1 rows of 6 for
// the residuals G(x) - x and as many for the images G(x), oldest first.
inline int64_t anderson_state_size(int64_t window) { return 17 + 12 * (window + 1); }

// Rotation vector of a rotation (every angle in [0, pi]): the same branches as a closed-form log.
void rotation_log(const double *r, double *v) {
    const double skew[3] = {r[7] - r[5], r[2] - r[6], r[3] - r[1]};
    const double angle = angle_of(r);
    if (angle < 1e-4) {
        const double f = 0.5 * (1.0 + angle * angle / 6.0);
        for (int a = 0; a < 3; ++a) v[a] = f * skew[a];
        return;
    }
    if (angle < 3.141592653589793 - 1e-4) {  // pi - 1e-4
        const double f = 0.5 * angle / std::sin(angle);
        for (int a = 0; a < 3; ++a) v[a] = f * skew[a];
        return;
    }
    // Near a half turn the skew part vanishes: the axis from the symmetric part,
    // (R + R^T) / 2 = cos(angle) I + (1 - cos(angle)) a a^T, at its largest diagonal entry.
    const double cosine = std::cos(angle);
    double outer[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            outer[3 * i + j] = (0.5 * (r[3 * i + j] + r[3 * j + i]) - (i == j ? cosine : 0.0)) / (1.0 - cosine);
    int k = 0;
    for (int j = 1; j < 3; ++j)
        if (outer[4 * j] > outer[4 * k]) k = j;
    const double root = std::sqrt(std::max(outer[4 * k], 1e-300));
    double axis[3] = {outer[k] / root, outer[3 + k] / root, outer[6 + k] / root};
    if (axis[0] * skew[0] + axis[1] * skew[1] + axis[2] * skew[2] < 0.0)
        for (double &value : axis) value = -value;
    const double norm = std::sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]);
    for (int a = 0; a < 3; ++a) v[a] = angle * axis[a] / norm;
}

// Rotation of a rotation vector: Rodrigues' formula.
void rotation_exp(const double *v, double *r) {
    const double angle = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    const double k[9] = {0.0, -v[2], v[1], v[2], 0.0, -v[0], -v[1], v[0], 0.0};
    double a, b;
    if (angle < 1e-4) {
        a = 1.0 - angle * angle / 6.0;
        b = 0.5 - angle * angle / 24.0;
    } else {
        a = std::sin(angle) / angle;
        b = (1.0 - std::cos(angle)) / (angle * angle);
    }
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            const double kk = k[3 * i] * k[j] + k[3 * i + 1] * k[3 + j] + k[3 * i + 2] * k[6 + j];
            r[3 * i + j] = (i == j ? 1.0 : 0.0) + a * k[3 * i + j] + b * kk;
        }
}

// (rotation vector, translation / scale) of pose @ inv(reference), both 4x4 row-major.
void pose_parameters(const double *pose, const double *reference, double scale, double *p) {
    double rotation[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            rotation[3 * i + j] = pose[4 * i] * reference[4 * j] + pose[4 * i + 1] * reference[4 * j + 1] +
                                  pose[4 * i + 2] * reference[4 * j + 2];
    rotation_log(rotation, p);
    for (int i = 0; i < 3; ++i)
        p[3 + i] = (pose[4 * i + 3] - (rotation[3 * i] * reference[3] + rotation[3 * i + 1] * reference[7] +
                                       rotation[3 * i + 2] * reference[11])) / scale;
}

// Minimum-norm least-squares solution of A x = b (A: 6 x m, column j at a[6 j], m <= 8), singular
// values below 6 eps times the largest taken as zero (NumPy's lstsq default): one-sided Jacobi SVD.
void least_squares_6(double *a, int m, const double *b, double *x) {
    double v[64] = {0.0};
    for (int j = 0; j < m; ++j) v[9 * j] = 1.0;  // v[8 j + j]
    const double eps = std::numeric_limits<double>::epsilon();
    for (int sweep = 0; sweep < 60; ++sweep) {
        bool rotated = false;
        for (int p = 0; p < m - 1; ++p)
            for (int q = p + 1; q < m; ++q) {
                double alpha = 0.0, beta = 0.0, gamma = 0.0;
                for (int i = 0; i < 6; ++i) {
                    alpha += a[6 * p + i] * a[6 * p + i];
                    beta += a[6 * q + i] * a[6 * q + i];
                    gamma += a[6 * p + i] * a[6 * q + i];
                }
                if (!(std::fabs(gamma) > eps * std::sqrt(alpha * beta))) continue;
                rotated = true;
                const double zeta = (beta - alpha) / (2.0 * gamma);
                const double t = (zeta >= 0.0 ? 1.0 : -1.0) / (std::fabs(zeta) + std::sqrt(1.0 + zeta * zeta));
                const double c = 1.0 / std::sqrt(1.0 + t * t), s = c * t;
                for (int i = 0; i < 6; ++i) {
                    const double ap = a[6 * p + i], aq = a[6 * q + i];
                    a[6 * p + i] = c * ap - s * aq;
                    a[6 * q + i] = s * ap + c * aq;
                }
                for (int i = 0; i < m; ++i) {
                    const double vp = v[8 * p + i], vq = v[8 * q + i];
                    v[8 * p + i] = c * vp - s * vq;
                    v[8 * q + i] = s * vp + c * vq;
                }
            }
        if (!rotated) break;
    }
    double squared[8], largest = 0.0;
    for (int j = 0; j < m; ++j) {
        squared[j] = 0.0;
        for (int i = 0; i < 6; ++i) squared[j] += a[6 * j + i] * a[6 * j + i];
        largest = std::max(largest, squared[j]);
    }
    const double cutoff = 6.0 * eps * std::sqrt(largest);
    for (int i = 0; i < m; ++i) x[i] = 0.0;
    for (int j = 0; j < m; ++j) {
        if (!(std::sqrt(squared[j]) > cutoff)) continue;
        double projection = 0.0;
        for (int i = 0; i < 6; ++i) projection += a[6 * j + i] * b[i];
        for (int i = 0; i < m; ++i) x[i] += v[8 * j + i] * projection / squared[j];
    }
}

// One Anderson step: stores the residual and image of plain = G(current) (4x4 row-major each),
// and, from two stored steps on, writes the combination of the last `window` into `out` (the
// pose, 16, then its motion from `current`: angle in radians, translation norm) and returns
// true. Returns false when `plain` itself is the next pose (fewer than two steps stored, or a
// non-finite combination, which also clears the state).
bool anderson_propose(CArr2 current_, CArr2 plain_, Arr1 state_, double scale, int64_t window, Arr1 out_) {
    if (window < 1 || window > 8) throw nb::value_error("anderson_propose: window must be in [1, 8]");
    if (int64_t(state_.shape(0)) != anderson_state_size(window) || out_.shape(0) < 18 ||
        current_.shape(0) != 4 || current_.shape(1) != 4 || plain_.shape(0) != 4 || plain_.shape(1) != 4)
        throw nb::value_error("anderson_propose: wrong shapes");
    const double *current = current_.data(), *plain = plain_.data();
    double *state = state_.data(), *out = out_.data();
    double *reference = state + 1, *residuals = state + 17, *images = residuals + 6 * (window + 1);
    int64_t stored = int64_t(state[0]);
    if (stored == 0) std::copy(current, current + 16, reference);
    if (stored == window + 1) {  // drop the oldest
        std::copy(residuals + 6, residuals + 6 * (window + 1), residuals);
        std::copy(images + 6, images + 6 * (window + 1), images);
        --stored;
    }
    double *image = images + 6 * stored, *residual = residuals + 6 * stored, before[6];
    pose_parameters(plain, reference, scale, image);
    pose_parameters(current, reference, scale, before);
    for (int i = 0; i < 6; ++i) residual[i] = image[i] - before[i];
    state[0] = double(++stored);
    if (stored < 2) return false;
    bool finite = true;
    for (int64_t i = 0; i < 6 * stored; ++i) finite = finite && std::isfinite(residuals[i]) && std::isfinite(images[i]);
    double proposal[6];
    if (finite) {
        // gamma = lstsq(dF, residuals[-1]); proposal = images[-1] - dG gamma.
        const int m = int(stored - 1);
        double differences[48], gamma[8];
        for (int j = 0; j < m; ++j)
            for (int i = 0; i < 6; ++i) differences[6 * j + i] = residuals[6 * (j + 1) + i] - residuals[6 * j + i];
        least_squares_6(differences, m, residual, gamma);
        for (int i = 0; i < 6; ++i) {
            proposal[i] = image[i];
            for (int j = 0; j < m; ++j) proposal[i] -= (images[6 * (j + 1) + i] - images[6 * j + i]) * gamma[j];
            finite = finite && std::isfinite(proposal[i]);
        }
    }
    if (!finite) {
        state[0] = 0.0;
        return false;
    }
    // The pose [exp(r) | scale u] @ reference, and its motion from current.
    double rotation[9], pose_rotation[9];
    rotation_exp(proposal, rotation);
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j)
            pose_rotation[3 * i + j] = rotation[3 * i] * reference[j] + rotation[3 * i + 1] * reference[4 + j] +
                                       rotation[3 * i + 2] * reference[8 + j];
        out[4 * i + 3] = rotation[3 * i] * reference[3] + rotation[3 * i + 1] * reference[7] +
                         rotation[3 * i + 2] * reference[11] + proposal[3 + i] * scale;
        for (int j = 0; j < 3; ++j) out[4 * i + j] = pose_rotation[3 * i + j];
    }
    out[12] = out[13] = out[14] = 0.0;
    out[15] = 1.0;
    double relative[9], moved[3];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            relative[3 * i + j] = out[4 * i] * current[4 * j] + out[4 * i + 1] * current[4 * j + 1] +
                                  out[4 * i + 2] * current[4 * j + 2];
    for (int i = 0; i < 3; ++i)
        moved[i] = out[4 * i + 3] - (relative[3 * i] * current[3] + relative[3 * i + 1] * current[7] +
                                     relative[3 * i + 2] * current[11]);
    out[16] = angle_of(relative);
    out[17] = std::sqrt(moved[0] * moved[0] + moved[1] * moved[1] + moved[2] * moved[2]);
    return true;
}

// ---------------------------------------------------------------------------------------------
// One iteration of the local loop in one call: nearest neighbours (hash and tree, warm-started),
// the weights' sigma, the pair moments, the Kabsch increment and the composed pose.
//
// Weighting (`weighting`, 5 numbers): fixed sigma (> 0) or 0; the sigma floor; the factor on the
// median distance; 1 in the fine phase (sigma = floor) else 0; 1 for Gaussian weights, 0 for
// weights of 1 (icp). Objective sigma (> 0: also return the mean of exp(-d^2 / (2 s^2))).
// `reject_below`: when that mean is below it (the loop's trial of an accelerated pose that fits
// worse than the pose it came from), the step stops after the queries: out holds the rmse, the
// objective, the misses and the certified queries, and out[39] = 1 (else 0).
// With `use_graph` and a neighbour graph (build_graph), each warm-started query first walks it
// (graph_descent); the queries it certifies skip the hash and the tree.
//
// out (STEP_OUT numbers): sigma, rmse, objective, misses, effective pairs, increment angle,
// increment translation norm, R (9), t (3), the composed pose (16, re-orthonormalised), the motion
// of the pose (angle, translation norm), sum of weights, sum of squared weights, rejected (1/0),
// queries certified by the graph walk.
constexpr int STEP_OUT = 41;

struct Index {
    CArr2 target;
    CArr2 tree_points;
    CIdx tree_order, tree_rank, tree_starts, tree_ends, tree_lefts;
    CArr2 tree_boxes;
    bool has_hash = false;
    CArr2 sorted_points;
    CIdx sorted_index, hash_rank, cell_starts, table_keys, table_cells, dims;
    CArr1 low;
    double cell = 0.0;
    // The neighbour graph of the hash's points by sorted position (build_graph), empty until built.
    std::vector<int32_t> graph_neighbours;
    std::vector<double> graph_radii;
    int64_t graph_k = 0;

    Index(CArr2 target_, CArr2 points, CIdx order, CIdx rank, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes)
        : target(target_), tree_points(points), tree_order(order), tree_rank(rank), tree_starts(starts),
          tree_ends(ends), tree_lefts(lefts), tree_boxes(boxes) {}

    void set_hash(CArr2 sorted_points_, CIdx sorted_index_, CIdx rank_, CIdx cell_starts_, CIdx table_keys_,
                  CIdx table_cells_, CArr1 low_, double cell_, CIdx dims_) {
        sorted_points = sorted_points_;
        sorted_index = sorted_index_;
        hash_rank = rank_;
        cell_starts = cell_starts_;
        table_keys = table_keys_;
        table_cells = table_cells_;
        low = low_;
        cell = cell_;
        dims = dims_;
        has_hash = true;
    }

    // Builds the neighbour graph (k neighbours per target point) that the warm-started queries of
    // step() walk first; the walk certifies most of them near convergence (graph_descent) and
    // hands the rest, seeded with its end, to the hash or the tree.
    void build_graph(int64_t k, int threads) {
        const int64_t count = int64_t(tree_points.shape(0));
        if (!has_hash) throw nb::value_error("build_graph: set_hash first");
        if (k < 1 || k > GRAPH_K_MAX || k > count) throw nb::value_error("build_graph: 1 <= k <= min(M, 64)");
        if (count > int64_t(std::numeric_limits<int32_t>::max()))
            throw nb::value_error("build_graph: more than 2**31 - 1 target points");
        std::vector<int32_t> neighbours(static_cast<size_t>(count * k));
        std::vector<double> radii(static_cast<size_t>(count));
        const Hash h = make_hash(sorted_points, sorted_index, hash_rank, cell_starts, table_keys, table_cells, low,
                                 cell, dims);
        hash_graph(h, count, k, neighbours.data(), radii.data(), threads);
        graph_neighbours.swap(neighbours);
        graph_radii.swap(radii);
        graph_k = k;
    }

    void step(CArr2 source, CArr2 pose, Idx indices, Arr1 distances, bool warm, bool use_hash, bool use_graph,
              CArr1 weighting_,
              double objective_sigma, double reject_below, Arr1 out_, int threads) {
        const int64_t count = int64_t(source.shape(0));
        if (count == 0) throw nb::value_error("step needs at least one source point");
        if (int64_t(indices.shape(0)) != count || int64_t(distances.shape(0)) != count)
            throw nb::value_error("step: indices and distances must have one entry per source point");
        if (pose.shape(0) != 4 || pose.shape(1) != 4) throw nb::value_error("step: pose must be 4x4");
        if (int64_t(out_.shape(0)) < STEP_OUT) throw nb::value_error("step: out must hold STEP_OUT numbers");
        const double *T = pose.data(), *s = source.data(), *weighting = weighting_.data();
        const double r0[9] = {T[0], T[1], T[2], T[4], T[5], T[6], T[8], T[9], T[10]};
        const double t0[3] = {T[3], T[7], T[11]};
        double *out = out_.data();
        Tree t{tree_points.data(), tree_order.data(), tree_starts.data(), tree_ends.data(), tree_lefts.data(),
               tree_boxes.data(), int64_t(tree_points.shape(0))};
        const int64_t *trank = tree_rank.data();
        const bool hashed = has_hash && use_hash;
        const bool graphed = use_graph && warm && graph_k > 0 && has_hash;
        const NeighbourGraph<int32_t> graph{graph_neighbours.data(), graph_radii.data(), graph_k};
        Hash h{};
        if (has_hash) h = make_hash(sorted_points, sorted_index, hash_rank, cell_starts, table_keys, table_cells, low,
                                    cell, dims);
        int64_t *ix = indices.data();
        double *d = distances.data();
        const double objective_scale =
            objective_sigma > 0.0 ? 1.0 / (2.0 * std::max(objective_sigma, 1e-150) * std::max(objective_sigma, 1e-150))
                                  : 0.0;
        // Pass 1: the queries; per piece the misses, sum d^2, min d^2, the objective's sum and the
        // certified queries.
        const int64_t pieces = piece_count(count, QUERY_PIECE);
        std::vector<double> partial(5 * pieces, 0.0);
        auto query = [&](int64_t piece) {
            int64_t end = std::min(count, (piece + 1) * QUERY_PIECE);
            double misses = 0.0, squares = 0.0, least = INF, objective = 0.0, certified = 0.0;
            for (int64_t i = piece * QUERY_PIECE; i < end; ++i) {
                double x, y, z;
                mapped(s, i, r0, t0, x, y, z);
                int64_t seed = warm ? ix[i] : -1;
                bool found = false;
                if (graphed && seed >= 0) {
                    const double *sp = h.sorted_points;
                    int64_t p = h.rank[seed];
                    const double ex = sp[3 * p] - x, ey = sp[3 * p + 1] - y, ez = sp[3 * p + 2] - z;
                    double best = ex * ex + ey * ey + ez * ez;
                    found = graph_descent(graph, sp, x, y, z, p, best);
                    seed = h.sorted_index[p];
                    if (found) {
                        d[i] = std::sqrt(best);
                        ix[i] = seed;
                        misses += best > h.limit;
                        certified += 1.0;
                    }
                }
                if (!found) {  // the hash and the tree, seeded with the walk's end
                    if (has_hash) {
                        misses += hash_nearest(h, t, trank, x, y, z, seed, hashed, d[i], ix[i]);
                    } else {
                        tree_nearest(t, trank, x, y, z, seed, d[i], ix[i]);
                    }
                }
                double squared = d[i] * d[i];
                squares += squared;
                least = std::min(least, squared);
                if (objective_scale > 0.0) objective += std::exp(-squared * objective_scale);
            }
            double *row = partial.data() + 5 * piece;
            row[0] = misses; row[1] = squares; row[2] = least; row[3] = objective; row[4] = certified;
        };
        // Up to POOLED_STEP_MAX points the persistent helpers (a thread started per call costs a
        // large part of the work there); beyond, threads per call, with their Ctrl-C checks.
        if (count < POOLED_STEP_MAX) {
            pooled_pieces(pieces, threads, query);
        } else {
            parallel_pieces(pieces, threads, query);
        }
        double misses = 0.0, squares = 0.0, least = INF, objective = 0.0, certified = 0.0;
        for (int64_t p = 0; p < pieces; ++p) {
            misses += partial[5 * p];
            squares += partial[5 * p + 1];
            least = std::min(least, partial[5 * p + 2]);
            objective += partial[5 * p + 3];
            certified += partial[5 * p + 4];
        }
        out[1] = std::sqrt(squares / double(count));
        out[2] = objective / double(count);
        out[3] = misses;
        out[40] = certified;
        out[39] = out[2] < reject_below ? 1.0 : 0.0;
        if (out[39] != 0.0) return;
        // The sigma of this step.
        const double fixed = weighting[0], floor = weighting[1], factor = weighting[2];
        const bool fine = weighting[3] != 0.0, gaussian = weighting[4] != 0.0;
        double sigma = std::numeric_limits<double>::quiet_NaN(), scale = 0.0;
        if (gaussian) {
            if (fixed > 0.0) {
                sigma = fixed;
            } else if (fine) {
                sigma = floor;
            } else {
                std::vector<double> copy(d, d + count);
                const int64_t middle = count / 2;
                std::nth_element(copy.begin(), copy.begin() + middle, copy.end());
                double median = copy[middle];
                if (count % 2 == 0) median = (*std::max_element(copy.begin(), copy.begin() + middle) + median) / 2.0;
                sigma = std::max(floor, factor * median);
            }
            const double bounded = std::max(sigma, 1e-150);
            scale = 1.0 / (2.0 * bounded * bounded);
        }
        // Pass 2: the moments, and the increment.
        double m[17];
        moments_of_pairs(s, count, r0, t0, target.data(), ix, d, scale, gaussian ? least : 0.0, m, threads,
                         count < POOLED_STEP_MAX);
        double r[9], tr[3];
        best_rotation(m + 8, r);
        for (int a = 0; a < 3; ++a) tr[a] = m[5 + a] - (r[3 * a] * m[2] + r[3 * a + 1] * m[3] + r[3 * a + 2] * m[4]);
        // The composed pose [R | t] @ T, its rotation re-orthonormalised.
        double product[9], rotation[9], translation[3];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                product[3 * i + j] = r[3 * i] * r0[j] + r[3 * i + 1] * r0[3 + j] + r[3 * i + 2] * r0[6 + j];
        nearest_rotation(product, rotation);
        for (int i = 0; i < 3; ++i) translation[i] = r[3 * i] * t0[0] + r[3 * i + 1] * t0[1] + r[3 * i + 2] * t0[2] + tr[i];
        // Its motion from T: rotation part rotation @ r0^T, translation translation - (that) t0.
        double relative[9], moved[3];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                relative[3 * i + j] = rotation[3 * i] * r0[3 * j] + rotation[3 * i + 1] * r0[3 * j + 1] +
                                      rotation[3 * i + 2] * r0[3 * j + 2];
        for (int i = 0; i < 3; ++i)
            moved[i] = translation[i] - (relative[3 * i] * t0[0] + relative[3 * i + 1] * t0[1] + relative[3 * i + 2] * t0[2]);
        out[0] = sigma;
        out[4] = m[1] > 0.0 ? m[0] * m[0] / m[1] : 0.0;
        out[5] = angle_of(r);
        out[6] = std::sqrt(tr[0] * tr[0] + tr[1] * tr[1] + tr[2] * tr[2]);
        for (int k = 0; k < 9; ++k) out[7 + k] = r[k];
        for (int k = 0; k < 3; ++k) out[16 + k] = tr[k];
        double *composed = out + 19;
        for (int i = 0; i < 3; ++i) {
            for (int j = 0; j < 3; ++j) composed[4 * i + j] = rotation[3 * i + j];
            composed[4 * i + 3] = translation[i];
        }
        composed[12] = composed[13] = composed[14] = 0.0;
        composed[15] = 1.0;
        out[35] = angle_of(relative);
        out[36] = std::sqrt(moved[0] * moved[0] + moved[1] * moved[1] + moved[2] * moved[2]);
        out[37] = m[0];
        out[38] = m[1];
    }
};

// ---------------------------------------------------------------------------------------------
// Coincident points: one pass with a hash table of exact coordinates (-0.0 counts as 0.0).
// Marks first[i] = 1 for the first occurrence of each distinct point, 0 for a repeat; returns
// (repeats, index of the most repeated point, its number of occurrences).
inline uint64_t coordinate_bits(double value) {
    value += 0.0;  // -0.0 -> +0.0
    uint64_t bits;
    std::memcpy(&bits, &value, sizeof bits);
    return bits;
}

nb::tuple coincident(CArr2 points_, nb::ndarray<uint8_t, nb::ndim<1>, nb::c_contig, nb::device::cpu> first_) {
    const int64_t count = int64_t(points_.shape(0));
    const double *p = points_.data();
    uint8_t *first = first_.data();
    int bits = 4;
    while ((int64_t(1) << bits) < 2 * count) ++bits;
    const int64_t size = int64_t(1) << bits, mask = size - 1;
    const int shift = 64 - bits;
    struct Slot {
        int64_t index = -1, count = 0;
    };
    std::vector<Slot> slots(size);
    int64_t repeats = 0, most = 0, most_count = count > 0 ? 1 : 0;
    for (int64_t i = 0; i < count; ++i) {
        if ((i & ((int64_t(1) << 16) - 1)) == 0 && i > 0 && PyErr_CheckSignals() != 0) throw nb::python_error();
        const uint64_t x = coordinate_bits(p[3 * i]), y = coordinate_bits(p[3 * i + 1]), z = coordinate_bits(p[3 * i + 2]);
        uint64_t key = x * HASH_MULTIPLIER;
        key = (key ^ (key >> 29) ^ y) * HASH_MULTIPLIER;
        key = (key ^ (key >> 29) ^ z) * HASH_MULTIPLIER;
        int64_t slot = int64_t(key >> uint64_t(shift));
        while (true) {
            const int64_t stored = slots[slot].index;
            if (stored < 0) {
                slots[slot].index = i;
                slots[slot].count = 1;
                first[i] = 1;
                break;
            }
            if (p[3 * stored] == p[3 * i] && p[3 * stored + 1] == p[3 * i + 1] && p[3 * stored + 2] == p[3 * i + 2]) {
                first[i] = 0;
                ++repeats;
                if (++slots[slot].count > most_count) {
                    most_count = slots[slot].count;
                    most = stored;
                }
                break;
            }
            slot = (slot + 1) & mask;
        }
    }
    return nb::make_tuple(repeats, most, most_count);
}

// points @ R^T + t into out (N, 3), on `threads` threads (NumPy would call BLAS, whose own
// threads then compete with the kernels').
void transform_points(CArr2 points, CArr2 rotation, CArr1 translation, Arr2 out_, int threads) {
    const int64_t count = int64_t(points.shape(0));
    const double *q = points.data(), *r = rotation.data(), *t = translation.data();
    double *o = out_.data();
    if (count < 65536) threads = 1;
    parallel_pieces(piece_count(count, SUM_PIECE), threads, [&](int64_t piece) {
        int64_t end = std::min(count, (piece + 1) * SUM_PIECE);
        for (int64_t i = piece * SUM_PIECE; i < end; ++i) mapped(q, i, r, t, o[3 * i], o[3 * i + 1], o[3 * i + 2]);
    });
}


// ---------------------------------------------------------------------------------------------
// Batched ESM of the global search (esmicp.globalreg.rotation_search.batched_esm): K hypotheses
// (poses T_target_source) each run `iterations` ESM steps on the same n source points, one
// hypothesis per piece from start to end (they are independent), so the result does not depend on
// the number of threads. Per step: the nearest target point of each placed source point (the
// exact tree, warm-started with the hypothesis' previous neighbours; or the global search's
// lookup grid), sigma = max(floor, factor * median distance) (the floor itself in the last
// `fine` steps), Gaussian weights exp(-(d^2 - min d^2) / (2 sigma^2)) normalised to sum 1, the
// weighted centroids and cross-covariance, Horn's rotation, the composed pose. After the last
// step, the distances of the placed source (out_distances, K x n).

// The global search's nearest-target lookup table (esmicp.core.nearest_grid.NearestGrid).
struct Grid {
    const double *target;   // (M, 3)
    const int64_t *lookup;  // cell (C order) -> target index
    double low[3], cell;
    int64_t shape[3];
};

inline int64_t grid_cell(const Grid &g, double x, double y, double z) {
    const double p[3] = {x, y, z};
    int64_t ijk[3];
    for (int a = 0; a < 3; ++a) {
        double f = std::floor((p[a] - g.low[a]) / g.cell);
        // NaN and out-of-range values go to the border cells, as numpy.clip does after the cast.
        int64_t v = f >= double(g.shape[a] - 1) ? g.shape[a] - 1 : (f > 0.0 ? int64_t(f) : 0);
        ijk[a] = v;
    }
    return (ijk[0] * g.shape[1] + ijk[1]) * g.shape[2] + ijk[2];
}

struct GridLookup {
    const Grid &g;
    const double *points() const { return g.target; }
    void operator()(double x, double y, double z, int64_t, double &distance, int64_t &index) const {
        index = g.lookup[grid_cell(g, x, y, z)];
        const double ex = x - g.target[3 * index], ey = y - g.target[3 * index + 1], ez = z - g.target[3 * index + 2];
        distance = std::sqrt(ex * ex + ey * ey + ez * ez);
    }
};

struct TreeLookup {
    const Tree &t;
    const int64_t *rank;
    const double *target;  // (M, 3) as given (the neighbours' coordinates)
    const NeighbourGraph<int64_t> &graph;
    const Grid *seeds;  // or nullptr: a query without a warm start starts from its cell's point there
    const double *points() const { return target; }
    // Exact nearest target point: with a warm start, the certified walk (graph_descent) on the
    // graph of target indices; where it certifies none, the tree, seeded with the walk's end.
    void operator()(double x, double y, double z, int64_t warm, double &distance, int64_t &index) const {
        if (warm < 0 && seeds != nullptr) warm = seeds->lookup[grid_cell(*seeds, x, y, z)];
        if (warm >= 0) {
            int64_t p = warm;
            const double ex = target[3 * p] - x, ey = target[3 * p + 1] - y, ez = target[3 * p + 2] - z;
            double best = ex * ex + ey * ey + ez * ez;
            if (graph_descent(graph, target, x, y, z, p, best)) {
                distance = std::sqrt(best);
                index = p;
                return;
            }
            warm = p;
        }
        tree_nearest(t, rank, x, y, z, warm, distance, index);
        if (index >= t.count) {  // a non-finite query point: no neighbour (NaN distance, point 0)
            index = 0;
            distance = std::numeric_limits<double>::quiet_NaN();
        }
    }
};

// The k nearest tree points of (x, y, z) below `node` into best (squared distances) and slots,
// nearest first: the caller fills both with (INF, -1) and starts at the root. Recursive, nearer
// child first, a child skipped when its box is beyond the current k-th distance.
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

// For each of `count` queries (rows of q, (count, 3)), its k nearest tree points (squared distances
// best[0..k), tree slots slots[0..k), nearest first; -1 where fewer exist), handed to
// emit(i, best, slots). Pieces of queries on `threads` threads (1 below `parallel_min` queries).
// `limit` (squared distance, INF for none): only points within it are wanted, so the search starts
// bounded by it and skips every branch beyond (the same points, found sooner; slots beyond the
// points within `limit` stay -1).
template <class Emit>
void each_k_nearest(const Tree &t, const double *q, int64_t count, int64_t k, int threads, int64_t parallel_min,
                    Emit &&emit, double limit = INF) {
    // keep_nearer takes a point strictly nearer than the k-th best: start just above the limit,
    // so that a point at exactly `limit` is still taken.
    const double start = limit < INF ? std::nextafter(limit, INF) : INF;
    if (count < parallel_min) threads = 1;
    parallel_pieces(piece_count(count, QUERY_PIECE), threads, [&](int64_t piece) {
        double best[GRAPH_K_MAX];
        int64_t slots[GRAPH_K_MAX];
        const int64_t end = std::min(count, (piece + 1) * QUERY_PIECE);
        for (int64_t i = piece * QUERY_PIECE; i < end; ++i) {
            std::fill(best, best + k, start);
            std::fill(slots, slots + k, int64_t(-1));
            nearest_k(t, 0, q[3 * i], q[3 * i + 1], q[3 * i + 2], k, best, slots);
            emit(i, best, slots);
        }
    });
}

// The neighbour graph of the tree's target (out_neighbours (M, k), out_radii (M,); k <= min(M, 64)):
// each target point's k nearest (itself first), queried in tree order, written in the target's.
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

// The k nearest tree points of each query (out_distances, out_indices (Q, k), nearest first;
// Euclidean distances, indices into the target as given; k <= min(M, 64)).
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

//: knn_normals runs on one thread below this many queries (each costs a k-nearest search and a
//: 3 x 3 eigen-decomposition, several microseconds: a few hundred pay for the threads).
constexpr int64_t PARALLEL_NORMALS_MIN = 512;

// PCA normals: for each query, its k nearest tree points within `upper` (cloud units; INF for no
// radius), their covariance (coordinates relative to `centre`, the cloud's centroid, for accuracy)
// and the unit eigenvector of its smallest eigenvalue, sign as it comes (the caller orients it).
// out_counts: the neighbours used; below 3 the normal is left NaN (the caller's fallback).
void knn_normals(CArr2 queries, CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes,
                 int64_t k, double upper, CArr1 centre, Arr2 out_normals, Idx out_counts, int threads) {
    Tree t{tree_points.data(), order.data(), starts.data(), ends.data(), lefts.data(), boxes.data(),
           int64_t(tree_points.shape(0))};
    const int64_t count = int64_t(queries.shape(0));
    if (queries.shape(1) != 3 || k < 1 || k > GRAPH_K_MAX || k > t.count || int64_t(out_normals.shape(0)) != count ||
        out_normals.shape(1) != 3 || int64_t(out_counts.shape(0)) != count || centre.shape(0) != 3)
        throw std::invalid_argument("knn_normals: queries and out_normals (Q, 3), out_counts (Q,), centre (3,), "
                                    "1 <= k <= min(M, 64)");
    const double *c = centre.data();
    const double limit = upper * upper;
    double *normals = out_normals.data();
    int64_t *counts = out_counts.data();
    each_k_nearest(t, queries.data(), count, k, threads, PARALLEL_NORMALS_MIN,
                   [&](int64_t i, const double *best, const int64_t *slots) {
        double sum[3] = {0.0, 0.0, 0.0}, moment[3][3] = {{0.0}};
        int64_t used = 0;
        for (int64_t j = 0; j < k; ++j) {
            if (slots[j] < 0 || !(best[j] <= limit)) continue;
            const double *point = t.points + 3 * slots[j];
            const double x[3] = {point[0] - c[0], point[1] - c[1], point[2] - c[2]};
            for (int a = 0; a < 3; ++a) {
                sum[a] += x[a];
                for (int b = 0; b < 3; ++b) moment[a][b] += x[a] * x[b];
            }
            ++used;
        }
        counts[i] = used;
        double *normal = normals + 3 * i;
        if (used < 3) {
            normal[0] = normal[1] = normal[2] = std::numeric_limits<double>::quiet_NaN();
            return;
        }
        double covariance[3][3], vectors[3][3];
        const double inverse = 1.0 / double(used);
        for (int a = 0; a < 3; ++a)
            for (int b = 0; b < 3; ++b)
                covariance[a][b] = moment[a][b] * inverse - (sum[a] * inverse) * (sum[b] * inverse);
        jacobi_eigen<3>(covariance, vectors);
        int least = 0;
        for (int a = 1; a < 3; ++a)
            if (covariance[a][a] < covariance[least][least]) least = a;
        for (int a = 0; a < 3; ++a) normal[a] = vectors[a][least];
    }, limit);
}

// Squared lengths |p - q|^2 of a pair of correspondences in the source and in the target, the
// coordinates summed x, y, z in turn (as SciPy's cdist and NumPy's norm sum them).
inline void squared_lengths(const double *sp, const double *sq, const double *tp, const double *tq, double &source,
                            double &target) {
    double a = 0.0, b = 0.0, d;
    d = sp[0] - sq[0]; a += d * d;
    d = sp[1] - sq[1]; a += d * d;
    d = sp[2] - sq[2]; a += d * d;
    d = tp[0] - tq[0]; b += d * d;
    d = tp[1] - tq[1]; b += d * d;
    d = tp[2] - tq[2]; b += d * d;
    source = a;
    target = b;
}

// Length compatibility of K paired points (source[k] <-> target[k], e.g. feature correspondences):
// out[i][j] = 1 when the source length |s_i - s_j| and the target length |t_i - t_j| differ by at
// most `tolerance` (cloud units), else 0; the diagonal is 0. Lengths as SciPy's cdist computes them
// (the same sums, the same square roots), so the entries are those of its two distance matrices;
// float32 for the power iterations that follow. Rows in parallel.
void compatibility(CArr2 source, CArr2 target, double tolerance, F32Arr2 out, int threads) {
    const int64_t count = int64_t(source.shape(0));
    if (source.shape(1) != 3 || target.shape(1) != 3 || int64_t(target.shape(0)) != count ||
        int64_t(out.shape(0)) != count || int64_t(out.shape(1)) != count)
        throw std::invalid_argument("compatibility: source and target (K, 3), out (K, K)");
    const double *s = source.data(), *t = target.data();
    float *o = out.data();
    constexpr int64_t ROWS = 32;
    if (count < 256) threads = 1;
    parallel_pieces(piece_count(count, ROWS), threads, [&](int64_t piece) {
        const int64_t end = std::min(count, (piece + 1) * ROWS);
        for (int64_t i = piece * ROWS; i < end; ++i) {
            // Row i from its diagonal on; the entries below it are mirrored (the matrix is symmetric,
            // and each entry is written by the one row that computes it).
            float *row = o + count * i;
            const double *si = s + 3 * i, *ti = t + 3 * i;
            row[i] = 0.0f;
            for (int64_t j = i + 1; j < count; ++j) {
                double a, b;
                squared_lengths(si, s + 3 * j, ti, t + 3 * j, a, b);
                const float value = std::fabs(std::sqrt(a) - std::sqrt(b)) <= tolerance ? 1.0f : 0.0f;
                row[j] = value;
                o[count * j + i] = value;
            }
        }
    });
}

// Seeds of the second-order pruning, spread apart: the candidates `order` (K, best first) are
// taken in turn, each kept unless a kept one lies within `spread` of it in both clouds (source
// distance and target distance both below `spread`, as NumPy's norm computes them), until `seeds`
// are kept. Writes the kept candidates to `out` (at least `seeds` long) and returns how many.
int64_t spread_seeds(CIdx order, CArr2 source, CArr2 target, double spread, int64_t seeds, Idx out) {
    const int64_t count = int64_t(order.shape(0));
    if (source.shape(1) != 3 || target.shape(1) != 3 || target.shape(0) != source.shape(0) ||
        int64_t(out.shape(0)) < std::min(count, seeds))
        throw std::invalid_argument("spread_seeds: source and target (N, 3), out as long as the seeds");
    const double *s = source.data(), *t = target.data();
    const int64_t *candidates = order.data();
    const int64_t points = int64_t(source.shape(0));
    int64_t *kept = out.data();
    int64_t chosen = 0;
    for (int64_t c = 0; c < count && chosen < seeds; ++c) {
        const int64_t i = candidates[c];
        if (i < 0 || i >= points) throw std::invalid_argument("spread_seeds: order holds an index out of range");
        const double *si = s + 3 * i, *ti = t + 3 * i;
        bool near = false;
        for (int64_t k = 0; k < chosen && !near; ++k) {
            double a, b;
            squared_lengths(s + 3 * kept[k], si, t + 3 * kept[k], ti, a, b);
            near = std::sqrt(a) < spread && std::sqrt(b) < spread;
        }
        if (!near) kept[chosen++] = i;
    }
    return chosen;
}

// Row `row` of `count` floats as a bitset (bit j: row[j] != 0), `(count + 63) / 64` words.
// Branch-free: a branch per entry mispredicts on rows that are half ones (LiDAR correspondences).
void pack_row(const float *row, int64_t count, uint64_t *word) {
    for (int64_t w = 0; w * 64 < count; ++w) {
        const float *part = row + 64 * w;
        const int64_t end = std::min<int64_t>(64, count - 64 * w);
        uint64_t value = 0;
        int64_t k = 0;
#if defined(__SSE2__)
        const __m128 zero = _mm_setzero_ps();
        for (; k + 4 <= end; k += 4)
            value |= uint64_t(_mm_movemask_ps(_mm_cmpneq_ps(_mm_loadu_ps(part + k), zero))) << k;
#endif
        for (; k < end; ++k) value |= uint64_t(part[k] != 0.0f) << k;
        word[w] = value;
    }
}

// Population count and lowest set bit of a 64-bit word: GCC's and Clang's builtins, or plain C++
// for other compilers (MSVC).
#if defined(__GNUC__) || defined(__clang__)
inline int64_t popcount64(uint64_t x) { return __builtin_popcountll(x); }
inline int64_t lowest_set_bit(uint64_t x) { return __builtin_ctzll(x); }
#else
inline int64_t popcount64(uint64_t x) {
    x = x - ((x >> 1) & 0x5555555555555555ULL);
    x = (x & 0x3333333333333333ULL) + ((x >> 2) & 0x3333333333333333ULL);
    x = (x + (x >> 4)) & 0x0F0F0F0F0F0F0F0FULL;
    return int64_t((x * 0x0101010101010101ULL) >> 56);
}
inline int64_t lowest_set_bit(uint64_t x) {
    int64_t bit = 0;
    while (!(x & 1)) {
        x >>= 1;
        ++bit;
    }
    return bit;
}
#endif

// Bits set in both of two bitsets of `words` 64-bit words. On x86-64 with GCC, a version with the
// processor's popcount instructions (AVX-512 VPOPCNTDQ, eight words at a time, or POPCNT) is
// chosen once at run time when the processor has them (the baseline x86-64 target has neither, and
// its software popcount costs several times more).
int64_t common_bits_plain(const uint64_t *a, const uint64_t *b, int64_t words) {
    int64_t both = 0;
    for (int64_t v = 0; v < words; ++v) both += popcount64(a[v] & b[v]);
    return both;
}
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
__attribute__((target("popcnt"))) int64_t common_bits_popcnt(const uint64_t *a, const uint64_t *b, int64_t words) {
    int64_t both = 0;
    for (int64_t v = 0; v < words; ++v) both += __builtin_popcountll(a[v] & b[v]);
    return both;
}
// (The AVX-512 version from GCC 11 on, where its feature test is known for certain.)
#if __GNUC__ >= 11
__attribute__((target("avx512f,avx512vpopcntdq,popcnt"), optimize("tree-vectorize")))
int64_t common_bits_avx512(const uint64_t *a, const uint64_t *b, int64_t words) {
    int64_t both = 0;
    for (int64_t v = 0; v < words; ++v) both += __builtin_popcountll(a[v] & b[v]);
    return both;
}
#endif
using CommonBits = int64_t (*)(const uint64_t *, const uint64_t *, int64_t);
CommonBits pick_common_bits() {
    __builtin_cpu_init();
#if __GNUC__ >= 11
    if (__builtin_cpu_supports("avx512vpopcntdq") && __builtin_cpu_supports("avx512f")) return common_bits_avx512;
#endif
    if (__builtin_cpu_supports("popcnt")) return common_bits_popcnt;
    return common_bits_plain;
}
const CommonBits common_bits = pick_common_bits();
#else
const auto common_bits = common_bits_plain;
#endif

// Groups of the second-order pruning. `compatible` (K, K) is 0/1 and symmetric (compatibility()
// above). For each seed s, the second-order compatibility of candidate j is C[s][j] times the
// number of candidates compatible with both; `partners` (S, size) gets the `size` candidates of
// highest second-order compatibility, highest first, ties to the lower index, then (when fewer
// than `size` are above 0) the candidates at 0 in index order: the first `size` of a stable
// argsort of the negated second-order row. `valid` (S, size) is 1 where the partner's
// second-order compatibility is above 0. Seeds in parallel.
void second_order_partners(CF32Arr2 compatible, CIdx seeds, Idx2 partners, nb::ndarray<uint8_t, nb::ndim<2>, nb::c_contig, nb::device::cpu> valid, int threads) {
    const int64_t count = int64_t(compatible.shape(0));
    const int64_t groups = int64_t(seeds.shape(0));
    const int64_t size = int64_t(partners.shape(1));
    if (int64_t(compatible.shape(1)) != count || int64_t(partners.shape(0)) != groups ||
        int64_t(valid.shape(0)) != groups || int64_t(valid.shape(1)) != size || size > count)
        throw std::invalid_argument("second_order_partners: compatible (K, K), partners and valid (S, size <= K)");
    const float *c = compatible.data();
    const int64_t *seed = seeds.data();
    int64_t *out = partners.data();
    uint8_t *ok = valid.data();
    for (int64_t g = 0; g < groups; ++g)
        if (seed[g] < 0 || seed[g] >= count) throw std::invalid_argument("second_order_partners: seed out of range");
    // Each row as a bitset (bit j of row i: C[i][j] != 0): the count of candidates compatible with
    // both seed and partner is then the popcount of two rows' AND.
    const int64_t words = (count + 63) / 64;
    std::vector<uint64_t> bits(size_t(count * words), 0);
    parallel_pieces(piece_count(count, 64), threads, [&](int64_t piece) {
        const int64_t end = std::min(count, (piece + 1) * 64);
        for (int64_t i = piece * 64; i < end; ++i)
            pack_row(c + count * i, count, bits.data() + words * i);
    });
    parallel_pieces(groups, groups < 16 ? 1 : threads, [&](int64_t g) {
        const uint64_t *mine = bits.data() + words * seed[g];
        std::vector<std::pair<int64_t, int64_t>> ranked;  // (-second order, index)
        for (int64_t w = 0; w < words; ++w) {
            for (uint64_t word = mine[w]; word; word &= word - 1) {
                const int64_t j = w * 64 + lowest_set_bit(word);
                const uint64_t *other = bits.data() + words * j;
                const int64_t both = common_bits(mine, other, words);
                if (both > 0) ranked.emplace_back(-both, j);
            }
        }
        const int64_t top = std::min<int64_t>(size, int64_t(ranked.size()));
        std::partial_sort(ranked.begin(), ranked.begin() + top, ranked.end());
        int64_t *partner = out + size * g;
        uint8_t *flag = ok + size * g;
        for (int64_t k = 0; k < top; ++k) {
            partner[k] = ranked[k].second;
            flag[k] = 1;
        }
        if (top < size) {
            // The candidates at 0, in index order: every index not among the positive ones.
            std::vector<uint8_t> positive(count, 0);
            for (const auto &entry : ranked) positive[entry.second] = 1;
            int64_t k = top;
            for (int64_t j = 0; j < count && k < size; ++j)
                if (!positive[j]) {
                    partner[k] = j;
                    flag[k++] = 0;
                }
        }
    });
}

// How many of K paired points (source[k] <-> target[k]) each of S poses maps within `distance`:
// out[c] = #{k : |R_c source[k] + t_c - target[k]| <= distance}. `rotations` (S, 9) row-major,
// `translations` (S, 3). Poses in parallel.
void pair_inlier_counts(CArr2 rotations, CArr2 translations, CArr2 source, CArr2 target, double distance, Idx out,
                        int threads) {
    const int64_t poses = int64_t(rotations.shape(0));
    const int64_t count = int64_t(source.shape(0));
    if (rotations.shape(1) != 9 || translations.shape(1) != 3 || int64_t(translations.shape(0)) != poses ||
        source.shape(1) != 3 || target.shape(1) != 3 || int64_t(target.shape(0)) != count ||
        int64_t(out.shape(0)) != poses)
        throw std::invalid_argument("pair_inlier_counts: rotations (S, 9), translations (S, 3), source and target (K, 3), out (S,)");
    const double *r = rotations.data(), *t = translations.data(), *s = source.data(), *d = target.data();
    const double limit = distance * distance;
    int64_t *counts = out.data();
    parallel_pieces(poses, poses * count < 65536 ? 1 : threads, [&](int64_t c) {
        const double *rc = r + 9 * c, *tc = t + 3 * c;
        int64_t inside = 0;
        for (int64_t k = 0; k < count; ++k) {
            const double *sk = s + 3 * k, *dk = d + 3 * k;
            double sum = 0.0;
            for (int i = 0; i < 3; ++i) {
                const double e = rc[3 * i] * sk[0] + rc[3 * i + 1] * sk[1] + rc[3 * i + 2] * sk[2] + tc[i] - dk[i];
                sum += e * e;
            }
            inside += sum <= limit;
        }
        counts[c] = inside;
    });
}

//: Columns per piece of nearest_descriptors.
constexpr int64_t DESCRIPTOR_COLUMNS = 512;

// One row block of a descriptor matching both ways. gram (R, C) holds the dot products of R source
// descriptors (rows `row_offset` on of the source) with the C target descriptors, float32 (BLAS);
// each squared distance is formed as the NumPy version formed it, in float32 and in the same order
// ((-2 g + |t|^2) + |s|^2, clipped at 0), so the results are its own. Per row: the nearest column
// (the first of equal ones), its squared distance and the second smallest (out_row_*). Per column,
// carried across blocks (callers start from INF and 0): the two smallest squared distances over
// every row so far (column_best (2, C)) and the row of the first (column_index, the first of equal
// ones). Column pieces in parallel; each piece's row minima are merged in column order.
void nearest_descriptors(CF32Arr2 gram_, CF32Arr1 row_squares_, CF32Arr1 column_squares_, int64_t row_offset,
                         Idx out_row_index_, F32Arr1 out_row_best_, F32Arr1 out_row_second_, F32Arr2 column_best_,
                         Idx column_index_, int threads) {
    const int64_t rows = int64_t(gram_.shape(0)), columns = int64_t(gram_.shape(1));
    if (int64_t(row_squares_.shape(0)) != rows || int64_t(column_squares_.shape(0)) != columns ||
        int64_t(out_row_index_.shape(0)) != rows || int64_t(out_row_best_.shape(0)) != rows ||
        int64_t(out_row_second_.shape(0)) != rows || column_best_.shape(0) != 2 ||
        int64_t(column_best_.shape(1)) != columns || int64_t(column_index_.shape(0)) != columns || rows < 1 ||
        columns < 1)
        throw std::invalid_argument("nearest_descriptors: gram (R, C), row arrays (R,), column_best (2, C), "
                                    "column_index (C,), R, C >= 1");
    const float *gram = gram_.data(), *row_squares = row_squares_.data(), *column_squares = column_squares_.data();
    float *first = column_best_.data(), *second = column_best_.data() + columns;
    int64_t *column_index = column_index_.data();
    const int64_t pieces = piece_count(columns, DESCRIPTOR_COLUMNS);
    const float inf = std::numeric_limits<float>::infinity();
    std::vector<float> piece_best(size_t(pieces) * size_t(rows)), piece_second(size_t(pieces) * size_t(rows));
    std::vector<int64_t> piece_index(size_t(pieces) * size_t(rows));
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        const int64_t begin = piece * DESCRIPTOR_COLUMNS, end = std::min(columns, begin + DESCRIPTOR_COLUMNS);
        float values[DESCRIPTOR_COLUMNS];
        int32_t moved[DESCRIPTOR_COLUMNS];
        for (int64_t i = 0; i < rows; ++i) {
            const float *row = gram + columns * i + begin;
            const float own = row_squares[i];
            const int64_t width = end - begin, label = row_offset + i;
            // Distances, then the columns' running minima: no dependence between columns, so
            // both loops vectorise; then the row's minima, whose branches are rarely taken.
            for (int64_t j = 0; j < width; ++j) {
                float value = row[j] * -2.0f;
                value = value + column_squares[begin + j];
                value = value + own;
                values[j] = value < 0.0f ? 0.0f : value;
            }
            float *column_first = first + begin, *column_second = second + begin;
            int64_t *column_label = column_index + begin;
            for (int64_t j = 0; j < width; ++j) {
                const float value = values[j], low = column_first[j];
                const bool lower = value < low;
                column_second[j] = lower ? low : std::min(column_second[j], value);
                column_first[j] = lower ? value : low;
                moved[j] = lower ? 1 : 0;  // int32 beside float32: the loop vectorises
            }
            for (int64_t j = 0; j < width; ++j)
                if (moved[j]) column_label[j] = label;
            float best = inf, runner_up = inf;
            int64_t nearest = 0;
            for (int64_t j = 0; j < width; ++j) {
                const float value = values[j];
                if (value < runner_up) {
                    if (value < best) {
                        runner_up = best;
                        best = value;
                        nearest = j;
                    } else {
                        runner_up = value;
                    }
                }
            }
            const size_t slot = size_t(piece) * size_t(rows) + size_t(i);
            piece_best[slot] = best;
            piece_second[slot] = runner_up;
            piece_index[slot] = begin + nearest;
        }
    });
    int64_t *row_index = out_row_index_.data();
    float *row_best = out_row_best_.data(), *row_second = out_row_second_.data();
    for (int64_t i = 0; i < rows; ++i) {
        float best = piece_best[size_t(i)], runner_up = piece_second[size_t(i)];
        int64_t nearest = piece_index[size_t(i)];
        for (int64_t piece = 1; piece < pieces; ++piece) {
            const size_t slot = size_t(piece) * size_t(rows) + size_t(i);
            if (piece_best[slot] < best) {
                runner_up = std::min(best, piece_second[slot]);
                best = piece_best[slot];
                nearest = piece_index[slot];
            } else {
                runner_up = std::min(runner_up, piece_best[slot]);
            }
        }
        row_index[i] = nearest;
        row_best[i] = best;
        row_second[i] = runner_up;
    }
}

// ---------------------------------------------------------------------------------------------
// FPFH (features.fpfh documents the definition; the formulas and their order of operations are
// the ones there, so that the bins are those of the NumPy reference to the last bit).

//: Bins per FPFH angle feature, the feature length, and what each SPFH block sums to.
constexpr int FPFH_BINS = 11;
constexpr int FPFH_DIMENSION = 3 * FPFH_BINS;
constexpr double SPFH_BLOCK_SUM = 100.0;
//: Two cosines closer than this count as equal when choosing a pair's source point.
constexpr double FPFH_TIE = 1e-9;
//: Points per piece of the FPFH passes.
constexpr int64_t FPFH_PIECE = 64;
//: pi, the double NumPy's np.pi is (the POSIX macro for it is not standard C++).
constexpr double FPFH_PI = 3.141592653589793;

// Tree slots within squared distance `limit` of (x, y, z), appended to `found` (tree order).
void within(const Tree &t, double x, double y, double z, double limit, std::vector<int64_t> &found) {
    int64_t stack[STACK];
    stack[0] = 0;
    int depth = box_distance(t.boxes, x, y, z) <= limit ? 1 : 0;
    while (depth > 0) {
        const int64_t node = stack[--depth];
        const int64_t left = t.lefts[node];
        if (left < 0) {
            for (int64_t s = t.starts[node]; s < t.ends[node]; ++s) {
                const double ex = t.points[3 * s] - x, ey = t.points[3 * s + 1] - y, ez = t.points[3 * s + 2] - z;
                if (ex * ex + ey * ey + ez * ez <= limit) found.push_back(s);
            }
            continue;
        }
        for (int64_t child : {left + 1, left})
            if (box_distance(t.boxes + 6 * child, x, y, z) <= limit) stack[depth++] = child;
    }
}

inline int fpfh_bin(double scaled) {
    // Truncation toward zero, clipped to the bins (NaN to the first): the NumPy reference's
    // astype(intp) then clip.
    if (!(scaled >= 1.0)) return 0;
    return scaled >= double(FPFH_BINS - 1) ? FPFH_BINS - 1 : int(scaled);
}

// The offset o from point a to point b of the pair, a < b (points p, (N, 3)), and its length: the
// same operands from either end of the pair, so both ends see the same distance.
inline double pair_offset(const double *p, int64_t a, int64_t b, double o[3]) {
    const double *pa = p + 3 * a, *pb = p + 3 * b;
    for (int c = 0; c < 3; ++c) o[c] = pb[c] - pa[c];
    return std::sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2]);
}

// The (theta, alpha, phi) bins of the pair (a, b), a < b (unit normals n, (N, 3)), from its offset o
// and length distance > 0 (pair_offset).
inline void pair_bins(const double *n, int64_t a, int64_t b, double o[3], double distance, int bins[3]) {
    const double *u = n + 3 * a, *m = n + 3 * b;
    for (int c = 0; c < 3; ++c) o[c] /= distance;
    const double cos_first = u[0] * o[0] + u[1] * o[1] + u[2] * o[2];
    const double cos_second = m[0] * o[0] + m[1] * o[1] + m[2] * o[2];
    const double normals_cos = u[0] * m[0] + u[1] * m[1] + u[2] * m[2];
    const double triple = o[0] * (u[1] * m[2] - u[2] * m[1]) + o[1] * (u[2] * m[0] - u[0] * m[2]) +
                          o[2] * (u[0] * m[1] - u[1] * m[0]);
    const double gap = std::fabs(cos_first) - std::fabs(cos_second);
    const bool swap = std::fabs(gap) <= FPFH_TIE ? -cos_second > cos_first : gap < 0.0;
    const double total = cos_first + cos_second, chosen = swap ? 1.0 : 0.0;
    const double phi = cos_first - chosen * total, target_cos = cos_second - chosen * total;
    const double frame_norm = std::sqrt(std::max(1.0 - phi * phi, 0.0));
    const double alpha = triple / std::max(frame_norm, std::numeric_limits<double>::min());
    const double theta = std::atan2(target_cos - phi * normals_cos, normals_cos * frame_norm);
    bins[0] = fpfh_bin((theta + FPFH_PI) * (FPFH_BINS / (2.0 * FPFH_PI)));
    bins[1] = FPFH_BINS + fpfh_bin((alpha + 1.0) * (0.5 * FPFH_BINS));
    bins[2] = 2 * FPFH_BINS + fpfh_bin((phi + 1.0) * (0.5 * FPFH_BINS));
}

// FPFH of every point of the tree's cloud within `radius` (cloud units): out (N, 33), rows in the
// cloud's order; normals (N, 3) in that order too. In parallel, each point's neighbours and the
// bins of its pairs with the later points (each pair computed once), counted for that point; then,
// on one thread, the same bins counted for the later points (integer counts, so the order of the
// adds does not matter, and no atomic add: those cost more than the features); in parallel again,
// the SPFHs from the counts, and each point's SPFH plus its neighbours' weighted by 1 / squared
// distance, renormalised per block.
void fpfh(CArr2 normals_, CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes,
          double radius, Arr2 out_, int threads) {
    Tree t{tree_points.data(), order.data(), starts.data(), ends.data(), lefts.data(), boxes.data(),
           int64_t(tree_points.shape(0))};
    const int64_t count = t.count;
    if (int64_t(normals_.shape(0)) != count || normals_.shape(1) != 3 || int64_t(out_.shape(0)) != count ||
        out_.shape(1) != FPFH_DIMENSION || !(radius > 0.0))
        throw std::invalid_argument("fpfh: normals (N, 3) and out (N, 33) for the tree's N points, radius > 0");
    // The cloud in its own order (the pair features index points and normals alike).
    std::vector<double> cloud(3 * size_t(count));
    for (int64_t s = 0; s < count; ++s)
        for (int a = 0; a < 3; ++a) cloud[3 * t.order[s] + a] = t.points[3 * s + a];
    const double *p = cloud.data(), *n = normals_.data(), limit = radius * radius;
    double *out = out_.data();
    struct Neighbour {
        int64_t index;
        double weight;  // 1 / squared distance
    };
    std::vector<std::vector<Neighbour>> neighbours(count);
    std::vector<std::vector<uint32_t>> later_bins(count);  // the bins of (i, j > i), 8 bits each
    std::vector<int64_t> histograms(size_t(FPFH_DIMENSION) * size_t(count), 0), pairs(count, 0);
    std::vector<double> spfh(size_t(FPFH_DIMENSION) * size_t(count));
    const int64_t pieces = piece_count(count, FPFH_PIECE);
    if (count < 4 * FPFH_PIECE) threads = 1;
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        std::vector<int64_t> found;
        const int64_t end = std::min(count, (piece + 1) * FPFH_PIECE);
        for (int64_t i = piece * FPFH_PIECE; i < end; ++i) {
            found.clear();
            within(t, p[3 * i], p[3 * i + 1], p[3 * i + 2], limit, found);
            std::vector<Neighbour> &around = neighbours[i];
            around.reserve(found.size());
            for (int64_t slot : found) {
                const int64_t j = t.order[slot];
                double o[3];
                const double distance = j == i ? 0.0 : pair_offset(p, std::min(i, j), std::max(i, j), o);
                if (!(distance > 0.0)) continue;  // itself, or a coincident point: no direction
                around.push_back({j, 1.0 / (distance * distance)});
                if (j < i) continue;  // the features are computed from the pair's first point
                int bins[3];
                pair_bins(n, i, j, o, distance, bins);
                for (int b : bins) ++histograms[FPFH_DIMENSION * i + b];
                ++pairs[i];
                later_bins[i].push_back(uint32_t(bins[0]) | uint32_t(bins[1]) << 8 | uint32_t(bins[2]) << 16);
            }
        }
    });
    for (int64_t i = 0; i < count; ++i) {
        const uint32_t *packed = later_bins[i].data();
        for (const Neighbour &neighbour : neighbours[i]) {
            const int64_t j = neighbour.index;
            if (j < i) continue;
            const uint32_t bins = *packed++;
            int64_t *histogram = histograms.data() + FPFH_DIMENSION * j;
            ++histogram[bins & 0xFF];
            ++histogram[(bins >> 8) & 0xFF];
            ++histogram[bins >> 16];
            ++pairs[j];
        }
    }
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        const int64_t end = std::min(count, (piece + 1) * FPFH_PIECE);
        for (int64_t i = piece * FPFH_PIECE; i < end; ++i) {
            const double scale = SPFH_BLOCK_SUM / double(std::max<int64_t>(pairs[i], 1));
            for (int b = 0; b < FPFH_DIMENSION; ++b)
                spfh[FPFH_DIMENSION * i + b] = double(histograms[FPFH_DIMENSION * i + b]) * scale;
        }
    });
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        const int64_t end = std::min(count, (piece + 1) * FPFH_PIECE);
        for (int64_t i = piece * FPFH_PIECE; i < end; ++i) {
            double around[FPFH_DIMENSION] = {0.0};
            for (const Neighbour &neighbour : neighbours[i]) {
                const double *theirs = spfh.data() + FPFH_DIMENSION * neighbour.index;
                for (int k = 0; k < FPFH_DIMENSION; ++k) around[k] += neighbour.weight * theirs[k];
            }
            double *row = out + FPFH_DIMENSION * i;
            const double *own = spfh.data() + FPFH_DIMENSION * i;
            for (int block = 0; block < 3; ++block) {
                double sum = 0.0;
                for (int k = 0; k < FPFH_BINS; ++k) sum += around[FPFH_BINS * block + k];
                const double scale = SPFH_BLOCK_SUM / (sum > 0.0 ? sum : 1.0);
                for (int k = 0; k < FPFH_BINS; ++k) {
                    const int index = FPFH_BINS * block + k;
                    row[index] = own[index] + around[index] * scale;
                }
            }
        }
    });
}

inline void compose_step(const double *step_r, const double *step_t, double *r, double *t) {
    double nr[9], nt[3];
    for (int a = 0; a < 3; ++a) {
        for (int b = 0; b < 3; ++b)
            nr[3 * a + b] = step_r[3 * a] * r[b] + step_r[3 * a + 1] * r[3 + b] + step_r[3 * a + 2] * r[6 + b];
        nt[a] = step_r[3 * a] * t[0] + step_r[3 * a + 1] * t[1] + step_r[3 * a + 2] * t[2] + step_t[a];
    }
    std::memcpy(r, nr, sizeof nr);
    std::memcpy(t, nt, sizeof nt);
}

template <class Lookup>
void esm_hypothesis(const Lookup &look, const double *source, int64_t n, double *r, double *t, int64_t iterations,
                    double floor, double factor, int64_t fine, double *distances, int64_t *indices,
                    std::vector<double> &moved, std::vector<double> &scratch) {
    const double *target = look.points();
    for (int64_t i = 0; i < n; ++i) indices[i] = -1;
    for (int64_t iteration = 0; iteration <= iterations; ++iteration) {
        for (int64_t i = 0; i < n; ++i) {
            double x, y, z;
            mapped(source, i, r, t, x, y, z);
            moved[3 * i] = x;
            moved[3 * i + 1] = y;
            moved[3 * i + 2] = z;
            look(x, y, z, indices[i], distances[i], indices[i]);
        }
        if (iteration == iterations) return;  // the last query: the final pose's distances
        double sigma = floor;
        if (iteration < iterations - fine) {
            scratch.assign(distances, distances + n);
            const int64_t half = n / 2;
            std::nth_element(scratch.begin(), scratch.begin() + half, scratch.end());
            double median = scratch[half];
            if (n % 2 == 0) median = 0.5 * (median + *std::max_element(scratch.begin(), scratch.begin() + half));
            sigma = std::max(floor, factor * median);
        }
        double smallest = INF;
        for (int64_t i = 0; i < n; ++i) smallest = std::min(smallest, distances[i] * distances[i]);
        const double spread = 2.0 * (sigma * sigma);
        double total = 0.0;
        for (int64_t i = 0; i < n; ++i) {
            scratch[i] = std::exp(-(distances[i] * distances[i] - smallest) / spread);
            total += scratch[i];
        }
        double cp[3] = {0, 0, 0}, cm[3] = {0, 0, 0};
        for (int64_t i = 0; i < n; ++i) {
            const double w = scratch[i] / total;
            scratch[i] = w;
            const double *m = target + 3 * indices[i];
            for (int a = 0; a < 3; ++a) {
                cp[a] += w * moved[3 * i + a];
                cm[a] += w * m[a];
            }
        }
        double h[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
        for (int64_t i = 0; i < n; ++i) {
            const double *m = target + 3 * indices[i];
            const double w = scratch[i];
            add_outer(h, w, moved[3 * i] - cp[0], moved[3 * i + 1] - cp[1], moved[3 * i + 2] - cp[2], m[0] - cm[0],
                      m[1] - cm[1], m[2] - cm[2]);
        }
        double step_r[9], step_t[3];
        best_rotation(h, step_r);
        for (int a = 0; a < 3; ++a)
            step_t[a] = cm[a] - (step_r[3 * a] * cp[0] + step_r[3 * a + 1] * cp[1] + step_r[3 * a + 2] * cp[2]);
        compose_step(step_r, step_t, r, t);
    }
}

template <class Lookup>
void esm_hypotheses(const Lookup &look, CArr2 source, Arr2 rotations, Arr2 translations, int64_t iterations,
                    double floor, double factor, int64_t fine, Arr2 out_distances, int threads) {
    const int64_t count = int64_t(rotations.shape(0)), n = int64_t(source.shape(0));
    if (rotations.shape(1) != 9 || translations.shape(0) != size_t(count) || translations.shape(1) != 3 ||
        out_distances.shape(0) != size_t(count) || out_distances.shape(1) != size_t(n) || source.shape(1) != 3)
        throw std::invalid_argument("batched ESM: rotations (K, 9), translations (K, 3), distances (K, n)");
    if (n == 0) throw std::invalid_argument("batched ESM: no source points");
    std::vector<int64_t> indices(size_t(count * n));
    double *r = rotations.data(), *t = translations.data(), *d = out_distances.data();
    const double *s = source.data();
    parallel_pieces(count, threads, [&](int64_t k) {
        std::vector<double> moved(static_cast<size_t>(3 * n)), scratch(static_cast<size_t>(n));
        esm_hypothesis(look, s, n, r + 9 * k, t + 3 * k, iterations, floor, factor, fine, d + n * k,
                       indices.data() + n * k, moved, scratch);
    });
}

void batched_esm_tree(CArr2 source, Arr2 rotations, Arr2 translations, int64_t iterations, double floor,
                      double factor, int64_t fine, Arr2 out_distances, CArr2 target, CIdx rank, CArr2 tree_points,
                      CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes, CIdx2 graph_neighbours,
                      CArr1 graph_radii, CIdx seed_lookup, CArr1 seed_low, double seed_cell, CIdx seed_shape,
                      int threads) {
    Tree tree{tree_points.data(), order.data(), starts.data(), ends.data(), lefts.data(), boxes.data(),
              int64_t(tree_points.shape(0))};
    const int64_t k = int64_t(graph_neighbours.shape(1));
    if (int64_t(graph_radii.shape(0)) != tree.count || k < 1 || int64_t(graph_neighbours.shape(0)) != tree.count)
        throw std::invalid_argument("batched ESM: the neighbour graph does not match the target");
    const NeighbourGraph<int64_t> graph{graph_neighbours.data(), graph_radii.data(), k};
    // The seeds' grid (esmicp.core.nearest_grid.NearestGrid over the same target), if any (an empty lookup: none).
    const Grid seeds{target.data(), seed_lookup.data(), {seed_low.data()[0], seed_low.data()[1], seed_low.data()[2]},
                     seed_cell, {seed_shape.data()[0], seed_shape.data()[1], seed_shape.data()[2]}};
    const bool seeded = seed_lookup.shape(0) > 0;
    if (seeded && int64_t(seed_lookup.shape(0)) != seeds.shape[0] * seeds.shape[1] * seeds.shape[2])
        throw std::invalid_argument("batched ESM: the seeds' lookup table does not match its grid's shape");
    esm_hypotheses(TreeLookup{tree, rank.data(), target.data(), graph, seeded ? &seeds : nullptr}, source, rotations,
                   translations, iterations, floor, factor, fine, out_distances, threads);
}

void batched_esm_grid(CArr2 source, Arr2 rotations, Arr2 translations, int64_t iterations, double floor,
                      double factor, int64_t fine, Arr2 out_distances, CArr2 target, CIdx lookup, CArr1 low,
                      double cell, CIdx shape, int threads) {
    Grid grid{target.data(), lookup.data(), {low.data()[0], low.data()[1], low.data()[2]}, cell,
              {shape.data()[0], shape.data()[1], shape.data()[2]}};
    if (int64_t(lookup.shape(0)) != grid.shape[0] * grid.shape[1] * grid.shape[2])
        throw std::invalid_argument("batched ESM: the lookup table does not match the grid's shape");
    esm_hypotheses(GridLookup{grid}, source, rotations, translations, iterations, floor, factor, fine, out_distances,
                   threads);
}

// ---------------------------------------------------------------------------------------------
// The global search's lookup grid (esmicp.core.nearest_grid.NearestGrid): each cell's nearest
// occupied cell (Euclidean, in cells) by the separable feature transform of Maurer, Qi and
// Raghavan (2003), computed as scipy.ndimage.distance_transform_edt(return_indices=True) does:
// lines along axis 0, then 1, then 2; on each line the sites kept by the same integer-exact tests
// and a tie going to the earlier site, so that every cell gets the occupied cell SciPy's gives.
// Then each cell's target point: the last target point (in input order) of that occupied cell.

// One line of the feature transform along axis d. `feature` holds each cell's nearest occupied
// cell so far, 3 coordinates per cell (the first -1: none yet); the line starts at cell `base`
// with step `stride`, `length` cells; `fixed` holds its coordinates on the other axes. SciPy's
// tests, in doubles on small integers, are exact: integer arithmetic takes the same branches.
struct LineScratch {
    std::vector<int64_t> along, off, sites;  // a site's coordinate on axis d, squared distance off the line
    std::vector<int32_t> coordinates;         // a site's 3 coordinates
};

void voronoi_line(int32_t *feature, int64_t base, int64_t stride, int64_t length, int d, const int64_t *fixed,
                  LineScratch &work) {
    int64_t found = 0;
    for (int64_t i = 0; i < length; ++i) {
        const int32_t *f = feature + 3 * (base + i * stride);
        if (f[0] < 0) continue;
        int64_t off = 0;
        for (int a = 0; a < 3; ++a) {
            if (a == d) continue;
            const int64_t gap = int64_t(f[a]) - fixed[a];
            off += gap * gap;
        }
        std::memcpy(work.coordinates.data() + 3 * found, f, 3 * sizeof(int32_t));
        work.along[size_t(found)] = f[d];
        work.off[size_t(found)] = off;
        ++found;
    }
    if (found == 0) return;
    // The lower envelope of the sites' parabolas (SciPy's first loop).
    int64_t *sites = work.sites.data();
    const int64_t *along = work.along.data(), *off = work.off.data();
    int64_t last = -1;
    for (int64_t s = 0; s < found; ++s) {
        while (last >= 1) {
            const int64_t one = sites[last], two = sites[last - 1];
            const int64_t a = along[one] - along[two], b = along[s] - along[one], c = a + b;
            if (c * off[one] - b * off[two] - a * off[s] - a * b * c <= 0) break;
            --last;
        }
        sites[++last] = s;
    }
    // Each cell's nearest site along the envelope, a tie to the earlier one (its second loop).
    int64_t l = 0;
    for (int64_t i = 0; i < length; ++i) {
        int64_t gap = along[sites[l]] - i, nearest = gap * gap + off[sites[l]];
        while (l < last) {
            gap = along[sites[l + 1]] - i;
            const int64_t next = gap * gap + off[sites[l + 1]];
            if (nearest <= next) break;
            nearest = next;
            ++l;
        }
        std::memcpy(feature + 3 * (base + i * stride), work.coordinates.data() + 3 * sites[l], 3 * sizeof(int32_t));
    }
}

// Fills out_lookup (prod(shape),) with each cell's target index (see above); cells are C-ordered
// over `shape`, a target point's cell is as in grid_cell.
void nearest_grid(CArr2 target, CArr1 low, double cell, CIdx shape_, Idx out_lookup) {
    const int64_t shape[3] = {shape_.data()[0], shape_.data()[1], shape_.data()[2]};
    const int64_t size = shape[0] * shape[1] * shape[2], count = int64_t(target.shape(0));
    if (int64_t(out_lookup.shape(0)) != size || size <= 0 || count == 0 || target.shape(1) != 3)
        throw std::invalid_argument("nearest_grid: target (M, 3) with M >= 1, out_lookup (prod(shape),)");
    if (size > (int64_t(1) << 31) - 1) throw std::invalid_argument("nearest_grid: more than 2^31 - 1 cells");
    // The envelope test's products reach 4 L^3 on an axis of L cells: within int64 up to 10^6.
    if (std::max({shape[0], shape[1], shape[2]}) > 1000000)
        throw std::invalid_argument("nearest_grid: more than 10^6 cells along an axis");
    Grid grid{target.data(), nullptr, {low.data()[0], low.data()[1], low.data()[2]}, cell,
              {shape[0], shape[1], shape[2]}};
    std::vector<int64_t> representative(size_t(size), -1);
    for (int64_t i = 0; i < count; ++i) {
        const double *p = target.data() + 3 * i;
        representative[size_t(grid_cell(grid, p[0], p[1], p[2]))] = i;
    }
    std::vector<int32_t> feature(size_t(3 * size), -1);
    for (int64_t c = 0; c < size; ++c) {
        if (representative[size_t(c)] < 0) continue;
        feature[size_t(3 * c)] = int32_t(c / (shape[1] * shape[2]));
        feature[size_t(3 * c + 1)] = int32_t((c / shape[2]) % shape[1]);
        feature[size_t(3 * c + 2)] = int32_t(c % shape[2]);
    }
    const int64_t strides[3] = {shape[1] * shape[2], shape[2], 1};
    const size_t longest = size_t(std::max({shape[0], shape[1], shape[2]}));
    LineScratch work{std::vector<int64_t>(longest), std::vector<int64_t>(longest), std::vector<int64_t>(longest),
                     std::vector<int32_t>(3 * longest)};
    for (int d = 0; d < 3; ++d) {
        const int u = d == 0 ? 1 : 0, v = d == 2 ? 1 : 2;  // the other two axes
        int64_t fixed[3] = {0, 0, 0};
        for (int64_t i = 0; i < shape[u]; ++i) {
            if (PyErr_CheckSignals() != 0) throw nb::python_error();
            for (int64_t j = 0; j < shape[v]; ++j) {
                fixed[u] = i;
                fixed[v] = j;
                voronoi_line(feature.data(), i * strides[u] + j * strides[v], strides[d], shape[d], d, fixed, work);
            }
        }
    }
    int64_t *lookup = out_lookup.data();
    for (int64_t c = 0; c < size; ++c) {
        const int32_t *f = feature.data() + 3 * c;
        lookup[c] = representative[size_t((int64_t(f[0]) * shape[1] + f[1]) * shape[2] + f[2])];
    }
}

}  // namespace

NB_MODULE(_kernels, m) {
    m.doc() = "esmicp's compiled kernels (KD-tree, voxel hash, pair moments); std::thread, GIL released.";
    m.attr("STACK") = STACK;
    m.attr("CELL_SCAN_MAX") = CELL_SCAN_MAX;
    m.def("build_tree", &build_tree);
    m.def("tree_query", &tree_query);
    m.def("build_table", &build_table);
    m.def("hash_query", &hash_query);
    m.def("pair_moments", &pair_moments);
    m.def("paper_moments", &paper_moments);
    m.def("kabsch", &kabsch);
    m.def("transform_points", &transform_points);
    m.def("coincident", &coincident);
    m.def("nearest_rotation", &closest_rotation);
    m.def("anderson_propose", &anderson_propose);
    m.def("anderson_state_size", &anderson_state_size);
    m.def("batched_esm_tree", &batched_esm_tree);
    m.def("batched_esm_grid", &batched_esm_grid);
    m.def("neighbour_graph", &neighbour_graph);
    m.def("tree_knn", &tree_knn);
    m.def("knn_normals", &knn_normals);
    m.def("compatibility", &compatibility);
    m.def("spread_seeds", &spread_seeds);
    m.def("second_order_partners", &second_order_partners);
    m.def("pair_inlier_counts", &pair_inlier_counts);
    m.def("fpfh", &fpfh);
    m.def("nearest_descriptors", &nearest_descriptors);
    m.attr("FPFH_DIMENSION") = FPFH_DIMENSION;
    m.def("nearest_grid", &nearest_grid);
    m.attr("STEP_OUT") = STEP_OUT;
    nb::class_<Index>(m, "Index")
        .def(nb::init<CArr2, CArr2, CIdx, CIdx, CIdx, CIdx, CIdx, CArr2>())
        .def("set_hash", &Index::set_hash)
        .def("build_graph", &Index::build_graph)
        .def("step", &Index::step);
    m.def("hardware_threads", []() { return int(std::max(1u, std::thread::hardware_concurrency())); });
}
