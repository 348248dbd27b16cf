// The kernels' threads: a small pool of std::thread per call (parallel_pieces: no persistent
// runtime, so a fork() after a call is safe), sized by the caller's `threads`, or, for the short
// calls of the local loop, persistent helper threads (pooled_pieces). The GIL is released during
// the work; the calling thread checks for signals every few milliseconds (PyErr_CheckSignals with
// the GIL taken back), and a pending Ctrl-C stops every thread at its next piece and raises
// KeyboardInterrupt. Work is cut into pieces of fixed size (independent of the thread count), and
// partial sums are added in piece order: results are bitwise the same whatever the number of threads.
#pragma once

#include <cstdint>
#include <exception>
#include <type_traits>

namespace kernels {

// Thrown when a Python signal handler raised (Ctrl-C: KeyboardInterrupt): the Python error is set,
// and the bindings hand it to Python as it is.
struct PythonError : std::exception {};

// Runs Python's signal handlers (the calling thread holds the GIL): true when one raised, its
// error then set.
bool signal_raised();

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

// The two loops below, the work given as work(context, piece) (pool.cpp).
void run_pieces(int64_t pieces, int threads, void (*work)(void *, int64_t), void *context);
void run_pooled_pieces(int64_t pieces, int threads, void (*work)(void *, int64_t), void *context);

// A callable F as (function, context) for the loops above.
template <class F>
void (*piece_call())(void *, int64_t) {
    return [](void *data, int64_t piece) { (*static_cast<std::remove_reference_t<F> *>(data))(piece); };
}

template <class F>
void *piece_context(F &&work) {
    return const_cast<void *>(static_cast<const void *>(&work));
}

// Parallel loop over pieces [0, pieces), interruptible: work(piece) once for each piece, on
// `threads` threads started for the call (0: every core), the GIL released; throws PythonError
// when Ctrl-C (a signal handler) interrupted it.
template <class F>
void parallel_pieces(int64_t pieces, int threads, F &&work) {
    run_pieces(pieces, threads, piece_call<F>(), piece_context(work));
}

// The same loop on the persistent helper threads (pool.cpp), for calls of a few milliseconds at
// most: no signal checks (the loop around such calls sees Ctrl-C).
template <class F>
void pooled_pieces(int64_t pieces, int threads, F &&work) {
    run_pooled_pieces(pieces, threads, piece_call<F>(), piece_context(work));
}

inline int64_t piece_count(int64_t count, int64_t size) { return (count + size - 1) / size; }

}  // namespace kernels
