// The kernels' threads (pool.hpp): the GIL, the signal handlers, the persistent helpers.
#include <Python.h>

#include "pool.hpp"

#include <condition_variable>
#include <mutex>
#include <pthread.h>

namespace kernels {

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

namespace {

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

}  // namespace

Pool &open_job(int helpers, int64_t pieces, std::atomic<int64_t> *next, void (*call)(void *, int64_t),
               void *context) {
    Pool &pool = pool_of(helpers);
    {
        std::lock_guard<std::mutex> lock(pool.mutex);
        pool.open = true;
        pool.seats = helpers;
        pool.pieces = pieces;
        pool.next = next;
        pool.call = call;
        pool.context = context;
        pool.generation.fetch_add(1, std::memory_order_acq_rel);
    }
    pool.wake.notify_all();
    return pool;
}

void close_job(Pool &pool) {
    {
        std::lock_guard<std::mutex> lock(pool.mutex);
        pool.open = false;  // no helper joins from here on
    }
    while (pool.active.load(std::memory_order_acquire) != 0) std::this_thread::yield();
}

bool signal_raised() { return PyErr_CheckSignals() != 0; }

bool signal_raised_taking_gil() {
    const PyGILState_STATE state = PyGILState_Ensure();
    const bool raised = PyErr_CheckSignals() != 0;
    PyGILState_Release(state);
    return raised;
}

GilReleased::GilReleased() : state(PyEval_SaveThread()) {}

GilReleased::~GilReleased() { PyEval_RestoreThread(static_cast<PyThreadState *>(state)); }

ReleaseIfHeld::ReleaseIfHeld() {
    if (PyGILState_Check()) state = PyEval_SaveThread();
}

ReleaseIfHeld::~ReleaseIfHeld() {
    if (state != nullptr) PyEval_RestoreThread(static_cast<PyThreadState *>(state));
}

}  // namespace kernels
