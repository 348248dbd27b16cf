// The arrays the kernels take: a NumPy array's data (C order, on the CPU) and its shape, as
// bindings.cpp hands them over; the kernels themselves know nothing of Python's objects.
#pragma once

#include <cstddef>
#include <cstdint>

namespace kernels {

// Data and shape of an N-dimensional C-contiguous array of T (const T: read only).
template <class T, int N>
struct Array {
    T *pointer = nullptr;
    size_t extents[N] = {};
    T *data() const { return pointer; }
    size_t shape(size_t axis) const { return extents[axis]; }
};

using CArr2 = Array<const double, 2>;
using CArr1 = Array<const double, 1>;
using Arr1 = Array<double, 1>;
using Arr2 = Array<double, 2>;
using CIdx = Array<const int64_t, 1>;
using Idx = Array<int64_t, 1>;
using Idx2 = Array<int64_t, 2>;
using CIdx2 = Array<const int64_t, 2>;
using F32Arr2 = Array<float, 2>;
using CF32Arr2 = Array<const float, 2>;
using CF32Arr1 = Array<const float, 1>;
using F32Arr1 = Array<float, 1>;
using U8Arr1 = Array<uint8_t, 1>;
using U8Arr2 = Array<uint8_t, 2>;

}  // namespace kernels
