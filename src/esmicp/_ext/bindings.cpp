// The Python module esmicp._kernels: esmicp's compiled kernels, bound with nanobind (the only file
// that includes it). Each NumPy array reaches a kernel as an Array (arrays.hpp: data and shape)
// once nanobind has checked it (dtype, dimensions, C order, CPU; writable where the kernel
// writes); the kernels' errors reach Python as std::invalid_argument -> ValueError, and
// PythonError -> the Python error already set (KeyboardInterrupt after Ctrl-C).
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

#include "anderson.hpp"
#include "arrays.hpp"
#include "batched_esm.hpp"
#include "features.hpp"
#include "matching.hpp"
#include "moments.hpp"
#include "nearest_grid.hpp"
#include "points.hpp"
#include "pool.hpp"
#include "rotation.hpp"
#include "step.hpp"
#include "tree.hpp"
#include "trimmed_icp.hpp"
#include "voxel_hash.hpp"

#include <algorithm>
#include <exception>
#include <thread>

namespace nb = nanobind;

namespace {

// The NumPy array a kernel's Array<T, N> stands for.
template <class T, int N>
using NdArray = nb::ndarray<T, nb::ndim<N>, nb::c_contig, nb::device::cpu>;

// A kernel's parameter as Python passes it: an Array as the NumPy array it views, anything else
// as it is.
template <class T>
struct Python {
    using type = T;
    static T pass(T value) { return value; }
};

template <class T, int N>
struct Python<kernels::Array<T, N>> {
    using type = NdArray<T, N>;
    static kernels::Array<T, N> pass(const type &array) {
        kernels::Array<T, N> out;
        out.pointer = array.data();
        for (int axis = 0; axis < N; ++axis) out.extents[axis] = array.shape(size_t(axis));
        return out;
    }
};

// The Array (View) a kernel takes for `array`.
template <class View>
View view(const typename Python<View>::type &array) {
    return Python<View>::pass(array);
}

// The kernel F with Python's parameters.
template <auto F>
struct Bound;

template <class R, class... A, R (*F)(A...)>
struct Bound<F> {
    static R call(typename Python<A>::type... args) { return F(Python<A>::pass(args)...); }
};

using CArr2 = NdArray<const double, 2>;
using CArr1 = NdArray<const double, 1>;
using Arr1 = NdArray<double, 1>;
using Idx = NdArray<int64_t, 1>;
using CIdx = NdArray<const int64_t, 1>;
using U8Arr1 = NdArray<uint8_t, 1>;

// The local loop's index (kernels::Index), holding the arrays it views so that they live as long.
struct BoundIndex : kernels::Index {
    CArr2 target_array, tree_points_array, tree_boxes_array;
    CIdx tree_order_array, tree_rank_array, tree_starts_array, tree_ends_array, tree_lefts_array;
    CArr2 sorted_points_array;
    CIdx sorted_index_array, hash_rank_array, cell_starts_array, table_keys_array, table_cells_array, dims_array;
    CArr1 low_array;

    BoundIndex(CArr2 target_, CArr2 points, CIdx order, CIdx rank, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes)
        : kernels::Index(view<kernels::CArr2>(target_), view<kernels::CArr2>(points), view<kernels::CIdx>(order),
                         view<kernels::CIdx>(rank), view<kernels::CIdx>(starts), view<kernels::CIdx>(ends),
                         view<kernels::CIdx>(lefts), view<kernels::CArr2>(boxes)),
          target_array(target_), tree_points_array(points), tree_boxes_array(boxes), tree_order_array(order),
          tree_rank_array(rank), tree_starts_array(starts), tree_ends_array(ends), tree_lefts_array(lefts) {}

    void set_hash(CArr2 sorted_points_, CIdx sorted_index_, CIdx rank_, CIdx cell_starts_, CIdx table_keys_,
                  CIdx table_cells_, CArr1 low_, double cell_, CIdx dims_) {
        kernels::Index::set_hash(view<kernels::CArr2>(sorted_points_), view<kernels::CIdx>(sorted_index_),
                                 view<kernels::CIdx>(rank_), view<kernels::CIdx>(cell_starts_),
                                 view<kernels::CIdx>(table_keys_), view<kernels::CIdx>(table_cells_),
                                 view<kernels::CArr1>(low_), cell_, view<kernels::CIdx>(dims_));
        sorted_points_array = sorted_points_;
        sorted_index_array = sorted_index_;
        hash_rank_array = rank_;
        cell_starts_array = cell_starts_;
        table_keys_array = table_keys_;
        table_cells_array = table_cells_;
        low_array = low_;
        dims_array = dims_;
    }

    void build_graph(int64_t k, int threads) { kernels::Index::build_graph(k, threads); }

    void step(CArr2 source, CArr2 pose, Idx indices, Arr1 distances, bool warm, bool use_hash, bool use_graph,
              CArr1 weighting_, double objective_sigma, double reject_below, Arr1 out_, int threads) {
        kernels::Index::step(view<kernels::CArr2>(source), view<kernels::CArr2>(pose), view<kernels::Idx>(indices),
                             view<kernels::Arr1>(distances), warm, use_hash, use_graph,
                             view<kernels::CArr1>(weighting_), objective_sigma, reject_below,
                             view<kernels::Arr1>(out_), threads);
    }
};

}  // namespace

NB_MODULE(_kernels, m) {
    // A PythonError: the Python error is already set (a signal handler raised it), and Python sees it
    // as it is; any other exception goes on to nanobind's own translation.
    nb::register_exception_translator([](const std::exception_ptr &error, void *) {
        try {
            std::rethrow_exception(error);
        } catch (const kernels::PythonError &) {
            // translated: the error is set
        }
    });
    m.doc() = "esmicp's compiled kernels (KD-tree, voxel hash, pair moments); std::thread, GIL released.";
    m.attr("STACK") = kernels::STACK;
    m.attr("GRAPH_K_MAX") = kernels::GRAPH_K_MAX;
    m.attr("CELL_SCAN_MAX") = kernels::CELL_SCAN_MAX;
    m.def("build_tree", &Bound<&kernels::build_tree>::call);
    m.def("tree_query", &Bound<&kernels::tree_query>::call);
    m.def("tree_within", &Bound<&kernels::tree_within>::call);
    m.def("build_table", &Bound<&kernels::build_table>::call);
    m.def("cell_order", &Bound<&kernels::cell_order>::call);
    m.def("hash_query", &Bound<&kernels::hash_query>::call);
    m.def("pair_moments", &Bound<&kernels::pair_moments>::call);
    m.def("paper_moments", &Bound<&kernels::paper_moments>::call);
    m.def("kabsch", &Bound<&kernels::kabsch>::call);
    m.def("transform_points", &Bound<&kernels::transform_points>::call);
    m.def("voxel_cells", &Bound<&kernels::voxel_cells>::call);
    m.def("voxel_count", &Bound<&kernels::voxel_count>::call);
    m.def("centred_scatter", &Bound<&kernels::centred_scatter>::call);
    m.def("column_sums", &Bound<&kernels::column_sums>::call);
    m.def("knn_in_cells", &Bound<&kernels::knn_in_cells>::call);
    m.def("coincident", [](CArr2 points, U8Arr1 first) {
        const kernels::Coincident found =
            kernels::coincident(view<kernels::CArr2>(points), view<kernels::U8Arr1>(first));
        return nb::make_tuple(found.repeats, found.most, found.most_count);
    });
    m.def("nearest_rotation", &Bound<&kernels::closest_rotation>::call);
    m.def("anderson_propose", &Bound<&kernels::anderson_propose>::call);
    m.def("anderson_state_size", &Bound<&kernels::anderson_state_size>::call);
    m.def("batched_esm_tree", &Bound<&kernels::batched_esm_tree>::call);
    m.def("batched_esm_grid", &Bound<&kernels::batched_esm_grid>::call);
    m.def("trimmed_icp_tree", &Bound<&kernels::trimmed_icp_tree>::call);
    m.def("neighbour_graph", &Bound<&kernels::neighbour_graph>::call);
    m.def("tree_knn", &Bound<&kernels::tree_knn>::call);
    m.def("knn_normals", &Bound<&kernels::knn_normals>::call);
    m.def("compatibility", &Bound<&kernels::compatibility>::call);
    m.def("leading_vector", &Bound<&kernels::leading_vector>::call);
    m.def("spread_seeds", &Bound<&kernels::spread_seeds>::call);
    m.def("second_order_partners", &Bound<&kernels::second_order_partners>::call);
    m.def("group_second_order", &Bound<&kernels::group_second_order>::call);
    m.def("pair_inlier_counts", &Bound<&kernels::pair_inlier_counts>::call);
    m.def("count_within", &Bound<&kernels::count_within>::call);
    m.def("fpfh", &Bound<&kernels::fpfh>::call);
    m.def("nearest_descriptors", &Bound<&kernels::nearest_descriptors>::call);
    m.attr("FPFH_BINS") = kernels::FPFH_BINS;
    m.attr("FPFH_DIMENSION") = kernels::FPFH_DIMENSION;
    m.attr("SPFH_BLOCK_SUM") = kernels::SPFH_BLOCK_SUM;
    m.attr("FPFH_BLOCK_SUM") = kernels::FPFH_BLOCK_SUM;
    m.def("nearest_grid", &Bound<&kernels::nearest_grid>::call);
    m.attr("STEP_OUT") = kernels::STEP_OUT;
    nb::class_<BoundIndex>(m, "Index")
        .def(nb::init<CArr2, CArr2, CIdx, CIdx, CIdx, CIdx, CIdx, CArr2>())
        .def("set_hash", &BoundIndex::set_hash)
        .def("build_graph", &BoundIndex::build_graph)
        .def("step", &BoundIndex::step);
    m.def("hardware_threads", []() { return int(std::max(1u, std::thread::hardware_concurrency())); });
}
