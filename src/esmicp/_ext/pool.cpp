// The kernels' threads (pool.hpp): threads per call, and the persistent helpers of the local loop.
#include <Python.h>

#include "pool.hpp"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <mutex>
#include <pthread.h>
#include <thread>
#include <vector>

namespace kernels {
namespace {

// The GIL taken back for its lifetime, by a thread that released it.
struct GilHeld {
    PyGILState_STATE state = PyGILState_Ensure();
    ~GilHeld() { PyGILState_Release(state); }
    GilHeld() = default;
    GilHeld(const GilHeld &) = delete;
    GilHeld &operator=(const GilHeld &) = delete;
};

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

}  // namespace

bool signal_raised() { return PyErr_CheckSignals() != 0; }

GilReleased::GilReleased() : state(PyEval_SaveThread()) {}

GilReleased::~GilReleased() { PyEval_RestoreThread(static_cast<PyThreadState *>(state)); }

void run_pieces(int64_t pieces, int threads, void (*work)(void *, int64_t), void *context) {
    if (pieces <= 0) return;
    unsigned hw = std::max(1u, std::thread::hardware_concurrency());
    if (threads <= 0) threads = int(hw);
    threads = int(std::min<int64_t>(threads, pieces));
    std::atomic<int64_t> next{0};
    std::atomic<bool> cancel{false};
    bool interrupted = false;
    {
        GilReleased release;
        auto runner = [&]() {
            while (!cancel.load(std::memory_order_relaxed)) {
                int64_t piece = next.fetch_add(1);
                if (piece >= pieces) break;
                work(context, piece);
            }
        };
        std::vector<std::thread> pool;
        pool.reserve(threads - 1);
        for (int t = 1; t < threads; ++t) pool.emplace_back(runner);
        auto last_check = std::chrono::steady_clock::now();
        while (!cancel.load(std::memory_order_relaxed)) {
            int64_t piece = next.fetch_add(1);
            if (piece >= pieces) break;
            work(context, piece);
            auto now = std::chrono::steady_clock::now();
            if (now - last_check > std::chrono::milliseconds(5)) {
                last_check = now;
                GilHeld acquire;
                if (PyErr_CheckSignals() != 0) {
                    interrupted = true;
                    cancel.store(true);
                }
            }
        }
        for (auto &thread : pool) thread.join();
    }
    if (interrupted) throw PythonError();
}

void run_pooled_pieces(int64_t pieces, int threads, void (*work)(void *, int64_t), void *context) {
    if (pieces <= 0) return;
    unsigned hw = std::max(1u, std::thread::hardware_concurrency());
    if (threads <= 0) threads = int(hw);
    threads = int(std::min<int64_t>(threads, pieces));
    // The GIL is released on every path, one thread included: several Python threads each running
    // a registration on one thread (register_many's thread pool, workers=1) then run in parallel.
    ReleaseIfHeld release;
    if (threads <= 1) {
        for (int64_t piece = 0; piece < pieces; ++piece) work(context, piece);
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
        pool.call = work;
        pool.context = context;
        pool.generation.fetch_add(1, std::memory_order_acq_rel);
    }
    pool.wake.notify_all();
    for (int64_t piece = next.fetch_add(1); piece < pieces; piece = next.fetch_add(1)) work(context, piece);
    {
        std::lock_guard<std::mutex> lock(pool.mutex);
        pool.open = false;  // no helper joins from here on
    }
    while (pool.active.load(std::memory_order_acquire) != 0) std::this_thread::yield();
}

}  // namespace kernels
