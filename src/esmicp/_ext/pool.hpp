// The kernels' threads: a small pool of std::thread per call (parallel_pieces: no persistent
// runtime, so a fork() after a call is safe), sized by the caller's `threads`, or, for the short
// calls of the local loop, persistent helper threads (pooled_pieces). The GIL is released during
// the work; the calling thread checks for signals every few milliseconds (PyErr_CheckSignals with
// the GIL taken back), and a pending Ctrl-C stops every thread at its next piece and raises
// KeyboardInterrupt. Work is cut into pieces of fixed size (independent of the thread count), and
// partial sums are added in piece order: results are bitwise the same whatever the number of threads.
// The loops are templates, so that each kernel's work is compiled into them; what touches Python
// (the GIL, the signal handlers) and the persistent helpers are in pool.cpp.
#pragma once

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <exception>
#include <thread>
#include <type_traits>
#include <vector>

namespace kernels {

// Thrown when a Python signal handler raised (Ctrl-C: KeyboardInterrupt): the Python error is set,
// and the bindings hand it to Python as it is.
struct PythonError : std::exception {};

// Runs Python's signal handlers (the calling thread holds the GIL): true when one raised, its
// error then set.
bool signal_raised();

// The same from a thread that released the GIL: takes it back for the check.
bool signal_raised_taking_gil();

// Releases the GIL for its lifetime (the calling thread holds it: a kernel called from Python).
class GilReleased {
  public:
    GilReleased();
    ~GilReleased();
    GilReleased(const GilReleased &) = delete;
    GilReleased &operator=(const GilReleased &) = delete;

  private:
    void *state;  // the thread's Python state, saved
};

// Releases the GIL for its lifetime when the calling thread holds it (a kernel called from Python),
// and does nothing when it does not (a kernel called from a helper thread or a released region).
class ReleaseIfHeld {
  public:
    ReleaseIfHeld();
    ~ReleaseIfHeld();
    ReleaseIfHeld(const ReleaseIfHeld &) = delete;
    ReleaseIfHeld &operator=(const ReleaseIfHeld &) = delete;

  private:
    void *state = nullptr;  // the thread's Python state, saved (none: the GIL was not held)
};

// Parallel loop over pieces [0, pieces), interruptible: work(piece) once for each piece, on
// `threads` threads started for the call (0: every core), the GIL released; throws PythonError
// when Ctrl-C (a signal handler) interrupted it.
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
        GilReleased release;
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
                if (signal_raised_taking_gil()) {
                    interrupted = true;
                    cancel.store(true);
                }
            }
        }
        for (auto &thread : pool) thread.join();
    }
    if (interrupted) throw PythonError();
}

// The persistent helper threads (pool.cpp).
struct Pool;

// Hands a job to `helpers` persistent helpers (started on first use): each takes pieces from
// `next` until it passes `pieces` and runs call(context, piece) for each. Returns their pool.
Pool &open_job(int helpers, int64_t pieces, std::atomic<int64_t> *next, void (*call)(void *, int64_t),
               void *context);

// Closes the job (no helper joins it from here on) and returns once the helpers inside are done.
void close_job(Pool &pool);

// The loop of parallel_pieces on the persistent helpers, for calls of a few milliseconds at most:
// no signal checks (the loop around such calls sees Ctrl-C).
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
    std::atomic<int64_t> next{0};
    Pool &pool = open_job(threads - 1, pieces, &next,
                          [](void *data, int64_t piece) { (*static_cast<std::remove_reference_t<F> *>(data))(piece); },
                          static_cast<void *>(&work));
    for (int64_t piece = next.fetch_add(1); piece < pieces; piece = next.fetch_add(1)) work(piece);
    close_job(pool);
}

inline int64_t piece_count(int64_t count, int64_t size) { return (count + size - 1) / size; }

}  // namespace kernels
