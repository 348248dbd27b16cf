"""Tests of esmicp.io: round trips, the real data files, and every kind of bad input."""

from __future__ import annotations

import io
import os
import pickle
import struct
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import plyfile
import pytest
from conftest import assert_file_error, require_shared
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import esmicp
from esmicp.errors import (
    InvalidInputError,
    NonFinitePointsWarning,
    OutputExistsError,
    PointCloudFileError,
)
from esmicp.io import (
    READ_EXTENSIONS,
    SUPPORTED_EXTENSIONS,
    WRITE_EXTENSIONS,
    atomic_write,
    check_writable,
    read_points,
    read_transform,
    write_points,
    write_transform,
)

# (file name, write_points keyword arguments): every writable format and variant.
VARIANTS = [
    ("cloud.pcd", {"pcd_format": "ascii"}),
    ("cloud.pcd", {"pcd_format": "binary"}),
    ("cloud.pcd", {"pcd_format": "binary_compressed"}),
    ("cloud.ply", {"ply_format": "ascii"}),
    ("cloud.ply", {"ply_format": "binary"}),
    ("cloud.xyz", {}),
    ("cloud.txt", {}),
    ("cloud.csv", {}),
    ("cloud.npy", {}),
]
VARIANT_IDS = [f"{name}-{'-'.join(kw.values()) or 'default'}" for name, kw in VARIANTS]

TETRAHEDRON = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
TETRAHEDRON_OFF = """OFF
# a unit tetrahedron
4 4 0
0 0 0
1 0 0
0 1 0
0 0 1
3 0 2 1
3 0 1 3
3 0 3 2
3 1 2 3
"""
# ModelNet's OFF files glue the counts to the magic word ("OFF8 6 0"); quads are triangulated.
CUBE_OFF = (
    "OFF8 6 0\n"
    + "".join(f"{x} {y} {z}\n" for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5))
    + "4 0 1 3 2\n4 4 6 7 5\n4 0 4 5 1\n4 2 3 7 6\n4 0 2 6 4\n4 1 5 7 3\n"
)


def random_cloud(seed: int = 0, n: int = 200) -> np.ndarray:
    """A cloud whose values need all 17 significant digits (and spans many magnitudes)."""
    generator = np.random.default_rng(seed)
    return generator.normal(size=(n, 3)) * 10.0 ** generator.integers(-8, 8, size=(n, 1))


def pcd_header(
    data: str, points: int, *, fields="x y z", size="4 4 4", kind="F F F", count="1 1 1", width=None, height=1
) -> bytes:
    width = points if width is None else width
    return (
        f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\n"
        f"TYPE {kind}\nCOUNT {count}\nWIDTH {width}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {points}\nDATA {data}\n"
    ).encode()


def ply_header(
    fmt: str, vertices: int, properties=("float x", "float y", "float z"), extra: str = ""
) -> bytes:
    lines = ["ply", f"format {fmt} 1.0", f"element vertex {vertices}"]
    lines += [f"property {p}" for p in properties]
    return ("\n".join(lines) + "\n" + extra + "end_header\n").encode()


def leftover_files(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir())


# --------------------------------------------------------------------------------------------
# Round trips


@pytest.mark.parametrize(("name", "kwargs"), VARIANTS, ids=VARIANT_IDS)
def test_round_trip_is_exact(tmp_path, name, kwargs):
    points = random_cloud(1)
    path = tmp_path / name
    write_points(path, points, **kwargs)
    back = read_points(path)
    assert back.dtype == np.float64 and back.flags.c_contiguous
    # Every writer keeps float64 (doubles, or 17 significant digits): bit-exact round trip.
    np.testing.assert_array_equal(back, points)
    assert leftover_files(tmp_path) == [name]


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    points=arrays(
        np.float64,
        st.tuples(st.integers(3, 25), st.just(3)),
        elements=st.floats(allow_nan=False, allow_infinity=False, width=64),
    ),
    variant=st.sampled_from(VARIANTS),
)
def test_round_trip_hypothesis(points, variant):
    name, kwargs = variant
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / name
        write_points(path, points, **kwargs)
        back = read_points(path)
    np.testing.assert_array_equal(back, points)


def test_round_trip_float32_input_is_exact(tmp_path):
    points = random_cloud(2).astype(np.float32)
    for name, kwargs in VARIANTS:
        path = tmp_path / f"{kwargs.get('pcd_format', kwargs.get('ply_format', 'x'))}-{name}"
        write_points(path, points, **kwargs)
        np.testing.assert_array_equal(read_points(path), points.astype(np.float64))


@pytest.mark.parametrize("name", ["CLOUD.PLY", "Cloud.Pcd", "cloud.XYZ", "cloud.CSV", "cloud.NPY"])
def test_extensions_are_case_insensitive(tmp_path, name):
    points = random_cloud(3, 20)
    write_points(tmp_path / name, points)
    np.testing.assert_array_equal(read_points(tmp_path / name), points)


def test_string_paths_work(tmp_path):
    points = random_cloud(4, 10)
    write_points(str(tmp_path / "a.ply"), points)
    np.testing.assert_array_equal(read_points(str(tmp_path / "a.ply")), points)


def test_written_files_are_standard(tmp_path):
    """The files other tools read: plyfile / pypcd4 directly, doubles, the requested encodings."""
    from pypcd4 import PointCloud

    points = random_cloud(5, 30)
    write_points(tmp_path / "a.ply", points, ply_format="ascii")
    write_points(tmp_path / "b.ply", points)
    for name in ("a.ply", "b.ply"):
        vertex = plyfile.PlyData.read(str(tmp_path / name))["vertex"]
        assert vertex.data.dtype["x"] == np.dtype("<f8")
        np.testing.assert_array_equal(vertex["y"], points[:, 1])
    assert (tmp_path / "a.ply").read_bytes().startswith(b"ply\nformat ascii 1.0\n")
    assert (tmp_path / "b.ply").read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")

    for encoding in ("ascii", "binary", "binary_compressed"):
        path = tmp_path / f"{encoding}.pcd"
        write_points(path, points, pcd_format=encoding)
        # pypcd4 silently falls back to DATA binary when LZF cannot shrink random doubles; the
        # writer keeps the requested encoding.
        assert f"\nDATA {encoding}\n".encode() in path.read_bytes()
        cloud = PointCloud.from_path(path)
        assert cloud.metadata.type == ("F", "F", "F") and cloud.metadata.size == (8, 8, 8)
        np.testing.assert_array_equal(cloud.numpy(("x", "y", "z")), points)

    write_points(tmp_path / "c.csv", points)
    write_points(tmp_path / "c.xyz", points)
    first_csv = (tmp_path / "c.csv").read_text().splitlines()[0]
    first_xyz = (tmp_path / "c.xyz").read_text().splitlines()[0]
    assert first_csv.count(",") == 2 and " " not in first_csv
    assert len(first_xyz.split(" ")) == 3
    write_points(tmp_path / "d.npy", points)
    saved = np.load(tmp_path / "d.npy", allow_pickle=False)
    assert saved.dtype == np.float64 and saved.shape == points.shape


def test_supported_extensions_listed():
    assert set(SUPPORTED_EXTENSIONS) == {"read", "write"}
    assert SUPPORTED_EXTENSIONS["read"] == READ_EXTENSIONS
    assert SUPPORTED_EXTENSIONS["write"] == WRITE_EXTENSIONS
    assert {".ply", ".pcd", ".xyz", ".txt", ".csv", ".pts", ".npy", ".off"} <= set(READ_EXTENSIONS)
    assert set(WRITE_EXTENSIONS) == {".ply", ".pcd", ".xyz", ".txt", ".csv", ".npy"}
    # The package root exposes the readers lazily.
    assert esmicp.read_points is read_points and esmicp.write_transform is write_transform


# --------------------------------------------------------------------------------------------
# Reading tolerated variants


def test_text_variants(tmp_path):
    expected = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [-7.5, 8e-3, 9e10]])
    contents = {
        "space.xyz": "1 2 3\n4 5 6\n-7.5 0.008 9e10\n",
        "tabs.txt": "1\t2\t3\n4\t5\t6\n-7.5\t0.008\t9e10\n",
        "semicolon.csv": "1;2;3\n4;5;6\n-7.5;0.008;9e10\n",
        "comma_space.csv": "1, 2, 3\n4, 5, 6\n-7.5, 0.008, 9e10\n",
        "modelnet.txt": "1,2,3,0,0,1\n4,5,6,0,1,0\n-7.5,0.008,9e10,1,0,0\n",
        "count.txt": "3\n1 2 3\n4 5 6\n-7.5 0.008 9e10\n",
        "comments.xyz": "# exported\n// CloudCompare style\n\n1 2 3\n  4 5 6  \n# mid\n-7.5 0.008 9e10\n\n",
        "crlf.pts": "3\r\n1 2 3 100 1 2 3\r\n4 5 6 100 1 2 3\r\n-7.5 0.008 9e10 100 1 2 3\r\n",
        "names.csv": "x,y,z,intensity\n1,2,3,a\n4,5,6,b\n-7.5,0.008,9e10,c\n",
        "bom.xyz": "\ufeff1 2 3\n4 5 6\n-7.5 0.008 9e10\n",
    }
    for name, content in contents.items():
        (tmp_path / name).write_bytes(content.encode("utf-8"))
        np.testing.assert_array_equal(read_points(tmp_path / name), expected, err_msg=name)


def test_ply_variants(tmp_path):
    """Extra vertex properties, extra elements before/after, integer and double coordinates."""
    vertices = np.array(
        [(1, 2, 3, 0.5, 7), (4, 5, 6, 0.25, 8), (7, 8, 10, 0.125, 9)],
        dtype=[("nx", "f4"), ("x", "i4"), ("y", "f8"), ("confidence", "f4"), ("z", "u2")],
    )
    faces = np.array([([0, 1, 2],)], dtype=[("vertex_indices", "i4", (3,))])
    camera = np.array([(1.0,)], dtype=[("fx", "f4")])
    expected = np.array([[2.0, 3.0, 7.0], [5.0, 6.0, 8.0], [8.0, 10.0, 9.0]])
    for text in (True, False):
        for byte_order in ("<", ">"):
            data = plyfile.PlyData(
                [
                    plyfile.PlyElement.describe(camera, "camera"),
                    plyfile.PlyElement.describe(vertices, "vertex"),
                    plyfile.PlyElement.describe(faces, "face"),
                ],
                text=text,
                byte_order=byte_order,
            )
            path = tmp_path / f"v-{text}-{byte_order == '<'}.ply"
            data.write(str(path))
            np.testing.assert_array_equal(read_points(path), expected, err_msg=path.name)


def test_ply_with_variable_list_before_vertices(tmp_path):
    lists = np.empty(2, dtype=[("ids", "O")])
    lists["ids"] = [np.array([1, 2], "i4"), np.array([3], "i4")]
    vertices = np.array(
        [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")]
    )
    data = plyfile.PlyData(
        [
            plyfile.PlyElement.describe(lists, "group", len_types={"ids": "u1"}, val_types={"ids": "i4"}),
            plyfile.PlyElement.describe(vertices, "vertex"),
        ]
    )
    data.write(str(tmp_path / "g.ply"))
    np.testing.assert_array_equal(read_points(tmp_path / "g.ply"), [[0, 0, 0], [1, 0, 0], [0, 1, 0]])


def test_pcd_variants(tmp_path):
    """PCL's VERSION .5 header, extra fields of other types, COUNT > 1, padding, irregular spaces."""
    rows = np.array([[1.5, 2.5, 3.5], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]])
    ascii_body = "".join(f"7  {x}\t{y} {z}  1 2 \n" for x, y, z in rows)
    header = pcd_header(
        "ascii", 3, fields="label x y z normal", size="4 4 4 4 4", kind="U F F F F", count="1 1 1 1 2"
    )
    (tmp_path / "a.pcd").write_bytes(header.replace(b"VERSION 0.7", b"VERSION .5") + ascii_body.encode())
    np.testing.assert_array_equal(read_points(tmp_path / "a.pcd"), rows)

    table = np.zeros(3, dtype=[("x", "<f8"), ("_", "u1", (3,)), ("y", "<f4"), ("z", "<i2"), ("rgb", "<f4")])
    table["x"], table["y"], table["z"] = rows[:, 0], rows[:, 1], [3, 6, 9]
    header = pcd_header(
        "binary", 3, fields="x _ y z rgb", size="8 1 4 2 4", kind="F U F I F", count="1 3 1 1 1"
    )
    (tmp_path / "b.pcd").write_bytes(header + table.tobytes() + b"trailing bytes are ignored")
    np.testing.assert_array_equal(read_points(tmp_path / "b.pcd"), [[1.5, 2.5, 3], [4, 5, 6], [7, 8, 9]])


def test_pcd_organized_cloud_with_nans(tmp_path):
    grid = np.arange(24, dtype="<f4").reshape(8, 3)
    grid[[1, 6]] = np.nan
    (tmp_path / "org.pcd").write_bytes(pcd_header("binary", 8, width=4, height=2) + grid.tobytes())
    with pytest.warns(NonFinitePointsWarning, match="dropped 2"):
        points = read_points(tmp_path / "org.pcd")
    np.testing.assert_array_equal(points, grid[[0, 2, 3, 4, 5, 7]])


def test_npy_structured_array(tmp_path):
    table = np.zeros(4, dtype=[("z", "f4"), ("x", "i8"), ("y", "f8"), ("i", "u1")])
    table["x"], table["y"], table["z"] = [1, 2, 3, 4], [5, 6, 7, 8], [9, 10, 11, 12]
    np.save(tmp_path / "s.npy", table)
    np.testing.assert_array_equal(read_points(tmp_path / "s.npy")[:, 0], [1, 2, 3, 4])
    np.save(tmp_path / "f.npy", np.asfortranarray(np.arange(12, dtype=np.int32).reshape(4, 3)))
    np.testing.assert_array_equal(read_points(tmp_path / "f.npy"), np.arange(12).reshape(4, 3))


# --------------------------------------------------------------------------------------------
# Meshes


def on_tetrahedron_surface(points: np.ndarray) -> bool:
    inside = (points >= -1e-12).all(axis=1) & (points.sum(axis=1) <= 1 + 1e-12)
    distance = np.minimum(np.abs(points).min(axis=1), np.abs(points.sum(axis=1) - 1))
    return bool(inside.all() and (distance <= 1e-12).all())


def test_off_vertices_and_sampling(tmp_path):
    path = tmp_path / "tet.off"
    path.write_text(TETRAHEDRON_OFF)
    np.testing.assert_array_equal(read_points(path), TETRAHEDRON)

    first = read_points(path, sample_points=500, rng=7)
    second = read_points(path, sample_points=500, rng=7)
    third = read_points(path, sample_points=500, rng=np.random.default_rng(7))
    assert first.shape == (500, 3)
    np.testing.assert_array_equal(first, second)
    np.testing.assert_array_equal(first, third)
    assert not np.array_equal(first, read_points(path, sample_points=500, rng=8))
    assert on_tetrahedron_surface(first)
    # Every face gets samples (area-weighted: the slanted face is the largest).
    on_slanted = np.abs(first.sum(axis=1) - 1) <= 1e-12
    assert 0.2 < on_slanted.mean() < 0.6


def test_off_cube_with_quads(tmp_path):
    path = tmp_path / "cube.OFF"
    path.write_text(CUBE_OFF)
    assert read_points(path).shape == (8, 3)
    samples = read_points(path, sample_points=300, rng=0)
    np.testing.assert_allclose(np.abs(samples).max(axis=1), 0.5, atol=1e-12)
    assert (np.abs(samples) <= 0.5 + 1e-12).all()
    # all six faces are hit
    faces = {
        (axis, sign)
        for row in samples
        for axis in range(3)
        for sign in (-1, 1)
        if abs(row[axis] - sign * 0.5) < 1e-12
    }
    assert len(faces) == 6


def test_mesh_formats_via_trimesh(tmp_path):
    import trimesh

    mesh = trimesh.Trimesh(TETRAHEDRON, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], process=False)
    for extension in (".ply", ".obj", ".stl"):
        path = tmp_path / f"tet{extension}"
        mesh.export(path)
        vertices = read_points(path)
        np.testing.assert_allclose(np.unique(vertices, axis=0), np.unique(TETRAHEDRON, axis=0))
        samples = read_points(path, sample_points=200, rng=1)
        assert samples.shape == (200, 3) and on_tetrahedron_surface(samples)
        np.testing.assert_array_equal(samples, read_points(path, sample_points=200, rng=1))


def test_sampling_needs_a_mesh(tmp_path):
    write_points(tmp_path / "c.ply", random_cloud(0, 10))
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(tmp_path / "c.ply", sample_points=10, rng=0)
    assert_file_error(excinfo, tmp_path / "c.ply", "no faces")
    write_points(tmp_path / "c.pcd", random_cloud(0, 10))
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(tmp_path / "c.pcd", sample_points=10)
    assert_file_error(excinfo, tmp_path / "c.pcd", "mesh")
    (tmp_path / "flat.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n2 0 0\n3 0 1 2\n")
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(tmp_path / "flat.off", sample_points=10)
    assert_file_error(excinfo, tmp_path / "flat.off", "zero")
    for bad in (0, -3, 2.5, True, "10"):
        with pytest.raises(InvalidInputError, match="sample_points"):
            read_points(tmp_path / "flat.off", sample_points=bad)
    with pytest.raises(InvalidInputError, match="rng"):
        read_points(tmp_path / "flat.off", sample_points=5, rng="seed")


# --------------------------------------------------------------------------------------------
# The real data files


BUNNY = {
    "bun_zipper.ply": 35947,
    "bun_zipper_res2.ply": 8171,
    "bun_zipper_res3.ply": 1889,
    "bun_zipper_res4.ply": 453,
}
BUNNY_SCANS = {
    "bun000.ply": 40256,
    "bun045.ply": 40097,
    "bun090.ply": 30379,
    "bun180.ply": 40251,
    "bun270.ply": 31701,
    "bun315.ply": 35336,
    "chin.ply": 37738,
    "ear_back.ply": 32193,
    "top2.ply": 38298,
    "top3.ply": 36023,
}
MODELNET = [
    "airplane/airplane_0126.txt",
    "bottle/bottle_0276.txt",
    "chair/chair_0848.txt",
    "cup/cup_0075.txt",
    "flower_pot/flower_pot_0085.txt",
    "guitar/guitar_0165.txt",
    "lamp/lamp_0094.txt",
    "night_stand/night_stand_0080.txt",
    "person/person_0025.txt",
    "piano/piano_0226.txt",
    "stool/stool_0072.txt",
    "vase/vase_0483.txt",
]
GOICP = {"model_bunny.txt": 35947, "data_bunny.txt": 30379, "model_rand.txt": 100, "data_rand.txt": 100}


def check_cloud(points, count):
    assert points.shape == (count, 3)
    assert points.dtype == np.float64
    assert np.isfinite(points).all()


@pytest.mark.parametrize(("name", "count"), BUNNY.items())
def test_shared_bunny(name, count):
    path = require_shared(f"bunny/{name}")
    points = read_points(path)
    check_cloud(points, count)
    assert np.abs(points).max() < 0.25  # metres, the bunny is ~15 cm


def test_shared_bunny_scans():
    total = 0
    for name, count in BUNNY_SCANS.items():
        points = read_points(require_shared(f"bunny_scans/{name}"))
        check_cloud(points, count)
        total += len(points)
    assert total == 362272


def test_shared_bunny_matches_plyfile():
    path = require_shared("bunny/bun_zipper_res3.ply")
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    expected = np.column_stack([vertex["x"], vertex["y"], vertex["z"]]).astype(np.float64)
    np.testing.assert_array_equal(read_points(path), expected)


def test_shared_modelnet():
    for name in MODELNET:
        path = require_shared(f"modelnet40/{name}")
        points = read_points(path)
        check_cloud(points, 10000)
        assert np.linalg.norm(points, axis=1).max() <= 1.001  # unit sphere, 4 printed decimals
    expected = np.loadtxt(path, delimiter=",")[:, :3]
    np.testing.assert_array_equal(points, expected)


@pytest.mark.parametrize(("name", "count"), GOICP.items())
def test_shared_goicp(name, count):
    path = require_shared(f"goicp/{name}")
    points = read_points(path)
    check_cloud(points, count)
    np.testing.assert_array_equal(points, np.loadtxt(path, skiprows=1))


def test_shared_pcl_bunny():
    points = read_points(require_shared("pcl_bunny/bunny.pcd"))
    check_cloud(points, 397)
    np.testing.assert_allclose(points[0], [0.0054216, 0.11349, 0.040749], rtol=1e-6)


@pytest.mark.parametrize(("name", "count"), [("source.ply", 69792), ("target.ply", 69088)])
def test_shared_lidar(name, count):
    path = require_shared(f"lidar_pair_small_gicp/{name}")
    points = read_points(path)
    check_cloud(points, count)
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    np.testing.assert_array_equal(points[:, 2], vertex["z"].astype(np.float64))


@pytest.mark.parametrize(
    "name",
    [
        "lidar_pair_small_gicp/T_target_source.txt",
        "esm_icp_paper/fig1_person_transform.txt",
        "esm_icp_paper/fig_piano_transform.txt",
        "esm_icp_paper/fig1_airplane_transform.txt",
    ],
)
def test_shared_transforms(name):
    path = require_shared(name)
    T = read_transform(path)
    assert T.shape == (4, 4) and T.dtype == np.float64
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_allclose(T, np.loadtxt(path), atol=1e-12)


def test_shared_goicp_output_is_not_a_4x4():
    path = require_shared("goicp/output.txt")
    with pytest.raises(PointCloudFileError) as excinfo:
        read_transform(path)
    assert_file_error(excinfo, path, "16 numbers", "13")


# --------------------------------------------------------------------------------------------
# Bad input


@pytest.mark.parametrize("extension", [".ply", ".pcd", ".xyz", ".npy", ".off"])
def test_missing_file(tmp_path, extension):
    path = tmp_path / f"nothing{extension}"
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "no such file")


@pytest.mark.parametrize("reader", ["read_points", "read_transform", "read_poses", "read_stanford_conf"])
@pytest.mark.parametrize("where", ["no such file", "a part of the path is a file"])
def test_a_missing_file_is_a_file_not_found_error_and_an_esmicp_error_naming_it(tmp_path, reader, where):
    """``except FileNotFoundError`` (and ``except OSError``) catch a missing input as they catch
    open()'s; ``except esmicp.PointCloudFileError`` too. The message and ``filename`` name the file,
    and the error survives a trip to a worker process and back (pickling)."""
    if where == "no such file":
        path = tmp_path / "nothing.txt"
    else:
        (tmp_path / "plain.txt").write_text("1 2 3\n")
        path = tmp_path / "plain.txt" / "inner.txt"
    with pytest.raises(FileNotFoundError) as excinfo:
        getattr(esmicp, reader)(path)
    error = excinfo.value
    assert isinstance(error, esmicp.PointCloudFileNotFoundError) and isinstance(error, esmicp.PointCloudFileError)
    assert isinstance(error, OSError) and isinstance(error, esmicp.EsmicpError)
    assert str(error).startswith(str(path)) and "no such file" in str(error) and "\n" not in str(error)
    assert error.filename == str(path) and error.errno == 2
    again = pickle.loads(pickle.dumps(error))
    assert type(again) is type(error) and str(again) == str(error) and again.path == error.path


def test_file_errors_survive_pickling(tmp_path):
    """A malformed file's error crosses process boundaries (register_many's worker processes) whole."""
    path = tmp_path / "bad.xyz"
    path.write_text("1 2\n")
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    again = pickle.loads(pickle.dumps(excinfo.value))
    assert type(again) is PointCloudFileError and str(again) == str(excinfo.value)
    assert (again.path, again.problem) == (excinfo.value.path, excinfo.value.problem)


def test_missing_parent_and_directory(tmp_path):
    write_points(tmp_path / "file.xyz", random_cloud(0, 5))
    path = tmp_path / "file.xyz" / "inner.ply"
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "no such file")
    folder = tmp_path / "folder.ply"
    folder.mkdir()
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(folder)
    assert_file_error(excinfo, folder, "directory")


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root reads every file")
def test_unreadable_file(tmp_path):
    path = tmp_path / "secret.xyz"
    write_points(path, random_cloud(0, 5))
    path.chmod(0)
    try:
        with pytest.raises(PointCloudFileError) as excinfo:
            read_points(path)
        assert_file_error(excinfo, path, "permission")
    finally:
        path.chmod(0o600)


def test_unreadable_file_simulated(tmp_path, monkeypatch):
    """The same refusal as a root-proof test: opening the file fails with EACCES."""
    import builtins

    import esmicp.io._files

    path = tmp_path / "secret.ply"
    write_points(path, random_cloud(0, 5))
    real_open = builtins.open

    def refusing_open(file, *args, **kwargs):
        if str(file) == str(path):
            raise PermissionError(13, "Permission denied", str(file))
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(esmicp.io._files, "open", refusing_open, raising=False)
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "permission denied")


@pytest.mark.parametrize("extension", READ_EXTENSIONS)
def test_empty_file(tmp_path, extension):
    path = tmp_path / f"empty{extension}"
    path.write_bytes(b"")
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "empty")


@pytest.mark.parametrize(
    ("extension", "words"),
    [
        (".ply", ["not a PLY file"]),
        (".pcd", ["not a PCD file"]),
        (".npy", ["not a .npy file"]),
        (".xyz", ["not a text file"]),
        (".csv", ["not a text file"]),
        (".off", ["not a text file"]),
        (".obj", []),
        (".stl", []),
    ],
)
def test_garbage_bytes(tmp_path, extension, words):
    path = tmp_path / f"garbage{extension}"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, *words)


def test_garbage_text_in_binary_formats(tmp_path):
    for name, words in [("t.ply", "ply"), ("t.pcd", "PCD"), ("t.npy", ".npy"), ("t.off", "OFF")]:
        path = tmp_path / name
        path.write_text("hello world\nthis is not a point cloud\n")
        with pytest.raises(PointCloudFileError) as excinfo:
            read_points(path)
        assert_file_error(excinfo, path, words)


@pytest.mark.parametrize("name", ["cloud.foo", "cloud", "cloud.ply.bak"])
def test_unknown_extension(tmp_path, name):
    path = tmp_path / name
    path.write_text("1 2 3\n4 5 6\n7 8 9\n")
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "extension", ".ply", ".pcd", ".xyz", ".npy", ".off")


@pytest.mark.parametrize("cut", [1, 24, 100, 1199])
def test_truncated_binary_ply(tmp_path, cut):
    path = tmp_path / "cut.ply"
    write_points(path, random_cloud(0, 50))  # 50 x 24 bytes of data
    path.write_bytes(path.read_bytes()[:-cut])
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "truncated", "50 vertices", f"{1200 - cut} bytes")


def test_truncated_ascii_ply(tmp_path):
    path = tmp_path / "cut.ply"
    path.write_bytes(ply_header("ascii", 5) + b"1.25 2.5 3.75\n" * 3)
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "truncated", "5 vertices", "3 lines")
    path.write_bytes(ply_header("ascii", 3) + b"1.25 2.5 3.75\n" * 2 + b"1.25 2.5")  # cut in a row
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "malformed PLY data", "end-of-line")


def test_truncated_ply_header(tmp_path):
    path = tmp_path / "head.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n")
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "end_header")


@pytest.mark.parametrize("encoding", ["binary", "binary_compressed"])
@pytest.mark.parametrize("cut", [1, 24, 400])
def test_truncated_binary_pcd(tmp_path, encoding, cut):
    path = tmp_path / "cut.pcd"
    write_points(path, random_cloud(0, 50), pcd_format=encoding)
    path.write_bytes(path.read_bytes()[:-cut])
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "truncated", "50 points")


def test_truncated_ascii_pcd(tmp_path):
    path = tmp_path / "cut.pcd"
    path.write_bytes(pcd_header("ascii", 5) + b"1.25 2.5 3.75\n" * 3)
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "truncated", "5 points", "3 data lines")
    path.write_bytes(pcd_header("ascii", 3) + b"1.25 2.5 3.75\n" * 2 + b"1.25 2.5")
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "point 3 has 2 values")


def test_truncated_npy_and_text(tmp_path):
    path = tmp_path / "cut.npy"
    write_points(path, random_cloud(0, 50))
    path.write_bytes(path.read_bytes()[:-8])
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "truncated")
    path = tmp_path / "cut.txt"
    path.write_text("50\n" + "1.5 2.5 3.5\n" * 49 + "1.5 2.")
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "line 51 has 2 columns")
    path.write_text("50\n" + "1.5 2.5 3.5\n" * 40)
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "says 50 points", "40 rows")


HUGE = 10**12


def huge_files() -> dict[str, bytes]:
    npy_header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        npy_header, {"descr": "<f8", "fortran_order": False, "shape": (HUGE, 3)}
    )
    filler = b"\x00" * 1000
    return {
        "binary.ply": ply_header("binary_little_endian", HUGE) + filler,
        "big_endian.ply": ply_header("binary_big_endian", HUGE, ("double x", "double y", "double z"))
        + filler,
        "faces.ply": ply_header(
            "binary_little_endian", 3, extra=f"element face {HUGE}\nproperty list uchar int vertex_indices\n"
        )
        + filler,
        "ascii.ply": ply_header("ascii", HUGE) + b"1 2 3\n" * 100,
        "binary.pcd": pcd_header("binary", HUGE) + filler,
        "compressed.pcd": pcd_header("binary_compressed", HUGE)
        + struct.pack("<II", 900, HUGE * 12 % 2**32)
        + filler,
        "compressed_ratio.pcd": pcd_header("binary_compressed", 10**8)
        + struct.pack("<II", 100, 12 * 10**8)
        + bytes(100),
        "ascii.pcd": pcd_header("ascii", HUGE) + b"1 2 3\n" * 100,
        "huge.npy": b"\x93NUMPY\x01\x00" + npy_header.getvalue()[8:] + filler,
        "huge.off": f"OFF\n{HUGE} 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n".encode(),
        "huge.txt": f"{HUGE}\n1 2 3\n4 5 6\n7 8 9\n".encode(),
    }


@pytest.mark.parametrize("name", sorted(huge_files()))
def test_header_claiming_huge_count_is_refused_fast(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(huge_files()[name])
    start = time.perf_counter()
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert time.perf_counter() - start < 2.0
    assert_file_error(excinfo, path)
    message = str(excinfo.value)
    assert any(word in message for word in ("truncated", "corrupt", "count line")), message


def test_header_lies(tmp_path):
    cases = {
        # POINTS disagrees with WIDTH x HEIGHT
        "lie.pcd": (pcd_header("binary", 4, width=2, height=1) + bytes(48), ["POINTS", "WIDTH"]),
        "compressed_size.pcd": (
            pcd_header("binary_compressed", 3) + struct.pack("<II", 10, 99) + bytes(10),
            ["unpacks"],
        ),
        "bad_lzf.pcd": (
            pcd_header("binary_compressed", 3) + struct.pack("<II", 36, 36) + b"\xff" * 36,
            ["binary_compressed"],
        ),
        "no_z.pcd": (pcd_header("ascii", 3, fields="x y w") + b"1 2 3\n" * 3, ["no z field"]),
        "z_count.pcd": (
            pcd_header("ascii", 3, fields="x y z", count="1 1 2") + b"1 2 3 4\n" * 3,
            ["COUNT 2"],
        ),
        "columns.pcd": (
            pcd_header("ascii", 3) + b"1.5 2.5 3.5\n1.5 2.5\n1.5 2.5 3.5\n",
            ["point 2", "2 values"],
        ),
        "short_text.pcd": (pcd_header("ascii", 3) + b"1 2 3\n1 2\n1", ["truncated", "3 points"]),
        "text.pcd": (pcd_header("ascii", 3) + b"1 2 3\n1 two 3\n1 2 3\n", ["malformed"]),
        "no_vertex.ply": (
            b"ply\nformat ascii 1.0\nelement point 3\nproperty float x\nend_header\n1\n2\n3\n",
            ["no 'vertex'"],
        ),
        "no_z.ply": (ply_header("ascii", 3, ("float x", "float y", "float nz")) + b"1 2 3\n" * 3, ["no z"]),
        "list_x.ply": (
            ply_header("ascii", 3, ("list uchar float x", "float y", "float z")) + b"1 1 2 3\n" * 3,
            ["list"],
        ),
        "extra_value.ply": (ply_header("ascii", 3) + b"1 2 3\n1 2 3 4\n1 2 3\n", ["malformed PLY data"]),
        "not_number.ply": (ply_header("ascii", 3) + b"1 2 3\n1 b 3\n1 2 3\n", ["malformed PLY data"]),
        "bad_format.ply": (b"ply\nformat binary_middle_endian 1.0\nend_header\n" + bytes(10), ["format"]),
        "bad_type.ply": (
            ply_header("binary_little_endian", 1, ("float128 x", "float y", "float z")) + bytes(12),
            ["type"],
        ),
        "bad_version.ply": (b"ply\nformat ascii 2.0\nend_header\n", ["unsupported format"]),
        "end_header_spaces.ply": (
            ply_header("ascii", 3).replace(b"end_header", b"end_header  ") + b"1 2 3\n" * 3,
            ["alone"],
        ),
        "bad_keyword.ply": (b"ply\nformat ascii 1.0\nbanana 3\nend_header\n1 2 3\n", ["line 3"]),
        "count.txt": (b"4\n1 2 3\n4 5 6\n7 8 9\n", ["count line", "says 4", "3 rows"]),
        "two_columns.xyz": (b"1 2\n3 4\n5 6\n7 8\n", ["at least 3 columns", "found 2"]),
        "mixed.csv": (b"1,2,3\n4,5,6\n7,8\n", ["line 3 has 2 columns"]),
        "words.xyz": (b"1 2 3\n4 five 6\n7 8 9\n", ["line 2, column 2", "'five' is not a number"]),
        "comments_only.xyz": (b"# nothing\n// here\n\n", ["no points"]),
        "npy_shape.npy": (None, ["shape (5, 2)"]),
        "npy_text.npy": (None, ["numeric"]),
        "npy_fields.npy": (None, ["no z field"]),
        "off_counts.off": (b"OFF\nfour faces\n", ["count line"]),
        "off_missing_faces.off": (
            b"OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n",
            ["truncated", "4 faces"],
        ),
    }
    np.save(tmp_path / "npy_shape.npy", np.zeros((5, 2)))
    np.save(tmp_path / "npy_text.npy", np.array([["a", "b", "c"]] * 3))
    np.save(tmp_path / "npy_fields.npy", np.zeros(3, dtype=[("x", "f8"), ("y", "f8")]))
    for name, (content, words) in cases.items():
        path = tmp_path / name
        if content is not None:
            path.write_bytes(content)
        with pytest.raises(PointCloudFileError) as excinfo:
            read_points(path)
        assert_file_error(excinfo, path, *words)


def test_too_few_points(tmp_path):
    for name in ("two.xyz", "two.ply", "two.pcd", "two.npy"):
        path = tmp_path / name
        if name.endswith(".xyz"):
            path.write_text("1 2 3\n4 5 6\n")
        elif name.endswith(".ply"):
            path.write_bytes(ply_header("ascii", 2) + b"1 2 3\n4 5 6\n")
        elif name.endswith(".pcd"):
            path.write_bytes(pcd_header("ascii", 2) + b"1 2 3\n4 5 6\n")
        else:
            np.save(path, np.ones((2, 3)))
        with pytest.raises(PointCloudFileError) as excinfo:
            read_points(path)
        assert_file_error(excinfo, path, "at least 3", "got 2")
    path = tmp_path / "zero.pcd"
    path.write_bytes(pcd_header("binary", 0))
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "got 0")


def test_all_nan(tmp_path):
    path = tmp_path / "nan.xyz"
    path.write_text("nan nan nan\nnan 1 2\n3 inf 4\nNaN NaN NaN\n")
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "NaN", "all 4 points")
    path = tmp_path / "nan.npy"
    np.save(path, np.full((10, 3), np.nan))
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "NaN")


def test_nan_rows_dropped_with_warning(tmp_path):
    path = tmp_path / "some_nan.csv"
    path.write_text("1,2,3\nnan,nan,nan\n4,5,6\n7,inf,9\n10,11,12\n")
    with pytest.warns(NonFinitePointsWarning, match="dropped 2") as record:
        points = read_points(path)
    np.testing.assert_array_equal(points, [[1, 2, 3], [4, 5, 6], [10, 11, 12]])
    assert str(path) in str(record[0].message)
    # ... and only 2 finite points left is an error, not a warning.
    path.write_text("1,2,3\nnan,nan,nan\n4,5,6\n")
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "at least 3")


def test_pickled_npy_is_refused(tmp_path):
    path = tmp_path / "objects.npy"
    np.save(path, np.array([[1, 2, 3], [4, 5, 6], [7, 8, {"x": 1}]], dtype=object), allow_pickle=True)
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "objects", "pickle")
    path = tmp_path / "raw_pickle.npy"
    path.write_bytes(pickle.dumps(np.zeros((3, 3))))
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "not a .npy file")


def test_non_path_argument():
    with pytest.raises(InvalidInputError):
        read_points(12.5)
    with pytest.raises(InvalidInputError):
        write_points(None, np.zeros((3, 3)))


# Fuzzing: mutated valid files (cut, flipped bytes) must give a cloud or a PointCloudFileError.

FUZZ_SOURCES = {}


def fuzz_source(name: str, kwargs: dict) -> bytes:
    key = (name, tuple(kwargs.items()))
    if key not in FUZZ_SOURCES:
        with tempfile.TemporaryDirectory() as directory:
            path = Path(directory) / name
            write_points(path, random_cloud(9, 12), **kwargs)
            FUZZ_SOURCES[key] = path.read_bytes()
    return FUZZ_SOURCES[key]


FUZZ_VARIANTS = [*VARIANTS, ("mesh.off", {})]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    variant=st.sampled_from(FUZZ_VARIANTS),
    cut=st.integers(0, 2000),
    flips=st.lists(st.tuples(st.integers(0, 2000), st.integers(0, 255)), max_size=4),
)
def test_fuzzed_files_never_leak_library_errors(variant, cut, flips):
    name, kwargs = variant
    data = bytearray(TETRAHEDRON_OFF.encode() if name.endswith(".off") else fuzz_source(name, kwargs))
    for position, value in flips:
        data[position % len(data)] = value
    data = bytes(data[: max(len(data) - cut % len(data), 0)])
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / name
        path.write_bytes(data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NonFinitePointsWarning)
            try:
                points = read_points(path)
            except PointCloudFileError as exc:
                assert str(exc).startswith(str(path))
            else:
                assert points.ndim == 2 and points.shape[1] == 3 and np.isfinite(points).all()


# --------------------------------------------------------------------------------------------
# Transforms


def random_rigid(seed: int) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = np.random.default_rng(seed).normal(size=3) * 100
    return T


@pytest.mark.parametrize("seed", range(5))
def test_transform_round_trip_is_exact(tmp_path, seed):
    T = random_rigid(seed)
    path = tmp_path / "T.txt"
    write_transform(path, T)
    np.testing.assert_array_equal(read_transform(path), T)
    lines = path.read_text().splitlines()
    assert len(lines) == 4 and all(len(line.split()) == 4 for line in lines)


def test_transform_tolerant_reading(tmp_path):
    T = random_rigid(1)
    rows = T.tolist()
    variants = {
        "commas.txt": "\n".join(", ".join(repr(v) for v in row) for row in rows),
        "tabs.txt": "\n".join("\t".join(repr(v) for v in row) for row in rows) + "\n\n",
        "numpy.txt": "# T_target_source\n"
        + "\n".join("[" + " ".join(repr(v) for v in row) + "]" for row in rows),
        "one_line.txt": " ".join(repr(v) for row in rows for v in row),
    }
    for name, content in variants.items():
        (tmp_path / name).write_text(content)
        np.testing.assert_array_equal(read_transform(tmp_path / name), T, err_msg=name)


def test_bad_transforms(tmp_path):
    T = random_rigid(2)
    scaled = T.copy()
    scaled[:3, :3] *= 2
    reflected = T.copy()
    reflected[:3, 0] *= -1
    last_row = T.copy()
    last_row[3, 0] = 0.5

    def as_text(matrix):
        return "\n".join(" ".join(repr(v) for v in row) for row in matrix.tolist())

    cases = {
        "scaled.txt": (as_text(scaled), ["not rigid"]),
        "reflection.txt": (as_text(reflected), ["reflection"]),
        "last_row.txt": (as_text(last_row), ["last row"]),
        "short.txt": ("1 0 0 0\n0 1 0 0\n0 0 1 0\n", ["16 numbers", "12"]),
        "words.txt": ("1 0 0 0\n0 1 0 0\n0 0 one 0\n0 0 0 1\n", ["'one' is not a number"]),
        "nan.txt": ("1 0 0 nan\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", ["NaN"]),
        "empty.txt": ("", ["empty"]),
    }
    for name, (content, words) in cases.items():
        path = tmp_path / name
        path.write_text(content)
        with pytest.raises(PointCloudFileError) as excinfo:
            read_transform(path)
        assert_file_error(excinfo, path, *words)
    for path, words in [(tmp_path / "missing.txt", ["no such file"]), (tmp_path, ["directory"])]:
        with pytest.raises(PointCloudFileError) as excinfo:
            read_transform(path)
        assert_file_error(excinfo, path, *words)
    (tmp_path / "binary.txt").write_bytes(b"\x00\x01\x02")
    with pytest.raises(PointCloudFileError) as excinfo:
        read_transform(tmp_path / "binary.txt")
    assert_file_error(excinfo, tmp_path / "binary.txt", "not a text file")


def test_write_transform_refuses_bad_matrix_and_existing_file(tmp_path):
    path = tmp_path / "T.txt"
    with pytest.raises(InvalidInputError):
        write_transform(path, np.eye(4) * 2)
    with pytest.raises(InvalidInputError):
        write_transform(path, np.eye(3))
    assert leftover_files(tmp_path) == []
    write_transform(path, np.eye(4))
    before = path.read_bytes()
    with pytest.raises(OutputExistsError):
        write_transform(path, random_rigid(3))
    assert path.read_bytes() == before
    write_transform(path, random_rigid(3), overwrite=True)
    np.testing.assert_array_equal(read_transform(path), random_rigid(3))


# --------------------------------------------------------------------------------------------
# Writing safely


def test_write_refuses_existing_file(tmp_path):
    path = tmp_path / "out.ply"
    path.write_bytes(b"precious")
    with pytest.raises(OutputExistsError) as excinfo:
        write_points(path, random_cloud(0, 10))
    assert str(path) in str(excinfo.value)
    assert path.read_bytes() == b"precious"
    assert leftover_files(tmp_path) == ["out.ply"]
    write_points(path, random_cloud(0, 10), overwrite=True)
    np.testing.assert_array_equal(read_points(path), random_cloud(0, 10))
    assert leftover_files(tmp_path) == ["out.ply"]


def test_written_file_has_ordinary_permissions(tmp_path):
    mask = os.umask(0o022)
    os.umask(mask)
    write_points(tmp_path / "p.xyz", random_cloud(0, 5))
    assert (tmp_path / "p.xyz").stat().st_mode & 0o777 == 0o666 & ~mask


def test_write_unsupported_extension_creates_nothing(tmp_path):
    for name in ("mesh.off", "cloud.pts", "noext", "cloud.stl"):
        with pytest.raises(PointCloudFileError) as excinfo:
            write_points(tmp_path / name, random_cloud(0, 10))
        assert_file_error(excinfo, tmp_path / name, "extension", ".ply", ".pcd", ".npy")
    assert leftover_files(tmp_path) == []


def test_check_writable(tmp_path):
    check_writable(tmp_path / "ok.PCD")
    check_writable(tmp_path / "T.mat", kind="transform")
    for path, words in [
        (tmp_path / "mesh.off", ["extension"]),
        (tmp_path / "missing" / "a.ply", ["does not exist"]),
        (tmp_path, ["directory"]),
    ]:
        with pytest.raises(PointCloudFileError) as excinfo:
            check_writable(path, kind="points" if path.suffix else "transform")
        assert_file_error(excinfo, path, *words)
    assert leftover_files(tmp_path) == []


def test_write_invalid_points_or_options_creates_nothing(tmp_path):
    for bad in (np.zeros((5, 2)), [[1, 2, 3], [4, 5, 6]], "points", np.full((4, 3), np.nan)):
        with pytest.raises(InvalidInputError):
            write_points(tmp_path / "bad.ply", bad)
    with pytest.raises(InvalidInputError, match="pcd_format"):
        write_points(tmp_path / "bad.pcd", random_cloud(0, 5), pcd_format="binary_scompressed")
    with pytest.raises(InvalidInputError, match="ply_format"):
        write_points(tmp_path / "bad.ply", random_cloud(0, 5), ply_format="binary_big_endian")
    assert leftover_files(tmp_path) == []


def test_write_into_missing_folder_or_onto_directory(tmp_path):
    with pytest.raises(PointCloudFileError) as excinfo:
        write_points(tmp_path / "missing" / "a.ply", random_cloud(0, 5))
    assert_file_error(excinfo, tmp_path / "missing" / "a.ply", "does not exist")
    (tmp_path / "dir.ply").mkdir()
    with pytest.raises(PointCloudFileError) as excinfo:
        write_points(tmp_path / "dir.ply", random_cloud(0, 5), overwrite=True)
    assert_file_error(excinfo, tmp_path / "dir.ply", "directory")


@pytest.mark.parametrize(("name", "kwargs"), VARIANTS, ids=VARIANT_IDS)
def test_failing_write_leaves_nothing(tmp_path, monkeypatch, name, kwargs):
    """An exception in the middle of writing: no file, no temporary file, old file untouched."""
    import esmicp.io.npy
    import esmicp.io.pcd
    import esmicp.io.ply
    import esmicp.io.text

    def broken(*args, **kw):
        handle = args[0]
        handle.write(b"partial garbage")
        raise RuntimeError("disk exploded")

    monkeypatch.setattr(np, "savetxt", broken)
    monkeypatch.setattr(np, "save", broken)
    monkeypatch.setattr(plyfile.PlyData, "write", lambda self, handle: broken(handle))
    monkeypatch.setattr(esmicp.io.pcd, "struct", _BrokenStruct())
    import pypcd4

    monkeypatch.setattr(pypcd4.PointCloud, "save", lambda self, handle, encoding=None: broken(handle))
    path = tmp_path / name
    with pytest.raises(RuntimeError, match="disk exploded"):
        write_points(path, random_cloud(0, 10), **kwargs)
    assert leftover_files(tmp_path) == []

    path.write_bytes(b"old content")
    with pytest.raises(RuntimeError, match="disk exploded"):
        write_points(path, random_cloud(0, 10), overwrite=True, **kwargs)
    assert path.read_bytes() == b"old content"
    assert leftover_files(tmp_path) == [name]


class _BrokenStruct:
    def pack(self, *args):
        raise RuntimeError("disk exploded")


def test_atomic_write_directly(tmp_path):
    path = tmp_path / "a.bin"
    with atomic_write(path, overwrite=False) as handle:
        handle.write(b"one")
        # Written next to the target, to an unnamed file (Linux O_TMPFILE) or under a hidden
        # temporary name; nothing at path yet.
        assert not path.exists()
        temporary = [p for p in tmp_path.iterdir() if p.name != "a.bin"]
        assert len(temporary) <= 1 and all(p.name.startswith(".a.bin.") for p in temporary)
    assert path.read_bytes() == b"one"
    with pytest.raises(OutputExistsError), atomic_write(path, overwrite=False) as handle:
        handle.write(b"two")  # pragma: no cover - not reached
    with pytest.raises(KeyboardInterrupt), atomic_write(path, overwrite=True) as handle:
        handle.write(b"three")
        raise KeyboardInterrupt
    assert path.read_bytes() == b"one"
    with atomic_write(path, overwrite=True, mode="w") as handle:
        handle.write("four\n")
    assert path.read_bytes() == b"four\n"
    assert leftover_files(tmp_path) == ["a.bin"]


def test_atomic_write_no_clobber_race(tmp_path):
    """A file that appears at the path while writing is not clobbered without overwrite."""
    path = tmp_path / "race.txt"
    with pytest.raises(OutputExistsError), atomic_write(path, overwrite=False, mode="w") as handle:
        handle.write("mine")
        path.write_text("theirs")
    assert path.read_text() == "theirs"
    assert leftover_files(tmp_path) == ["race.txt"]


@pytest.mark.parametrize(
    "properties, body",
    [
        (("float x", "float y", "float z"), "0.1 -2.5e-3 1e72\nnan inf -inf\n3.4028235e38 1.17549435e-38 7\n"),
        (("double x", "float y", "double z", "float confidence"), "0.1 0.1 0.1 1\n1e300 1e-45 -0 0.5\n"),
        (("float z", "float intensity", "float x", "float y"), " 1  2\t3 4 \n5 6 7 8\n9 10 11 12\n"),
        (("uchar x", "float y", "float z"), "1 2 3\n4 5 6\n"),  # not all floats: plyfile alone
        (("float x", "float y", "float z"), "1 2 3\n\n4 5 6\n"),  # a blank line: malformed, for both
        (("float x", "float y", "float z"), "1 2 3\n4 # 6\n"),  # not a number: malformed, for both
    ],
)
def test_ascii_ply_fast_path_reads_what_plyfile_reads(tmp_path, properties, body, monkeypatch):
    from esmicp.io import ply

    path = tmp_path / "a.ply"
    rows = body.count("\n") - body.count("\n\n")
    path.write_bytes(ply_header("ascii", rows, properties) + body.encode())

    def read():
        try:
            return ply.read_ply(path)  # the raw rows, non-finite ones kept
        except PointCloudFileError as exc:
            return str(exc)

    fast = read()
    monkeypatch.setattr(ply, "_float_rows", lambda lines, vertex: None)
    reference = read()
    if isinstance(reference, str):
        assert fast == reference
    else:
        np.testing.assert_array_equal(fast, reference)


def test_ascii_ply_fast_path_is_taken_on_float_rows():
    from esmicp.io import ply

    vertex = ply._Element("vertex", 2, [ply._Property(a, "float") for a in "xyz"])
    points = ply._float_rows(["0.1 0.2 0.3\n", "1e72 -1 2\n"], vertex)
    np.testing.assert_array_equal(points, np.array([[0.1, 0.2, 0.3], [np.inf, -1, 2]], np.float32))
    assert ply._float_rows(["0.1 0.2\n", "1 2 3\n"], vertex) is None


def _data_after_line_by_line(text, rows: int, longest: int) -> bool:
    """What follows the next ``rows`` non-blank lines, judged one line at a time: the reference of
    the ascii PLY reader's block-wise check (a line of ``longest`` characters or more is not a row)."""
    while rows:
        line = text.readline(longest)
        if not line:
            return False
        if len(line) == longest and not line.endswith("\n"):
            return True
        if line.strip():
            rows -= 1
    return bool(text.read().strip())


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.sampled_from(["1 2 3", "", "  ", "\t", "\x0c", "\x1f", "x", "\ufffd", "a" * 20, " " * 20]),
                          st.sampled_from(["\n", "\r\n", "\r", "\n\n"])), max_size=30),
       st.integers(0, 12), st.sampled_from([8, 16, 64]), st.booleans())
def test_what_follows_the_declared_ascii_rows_is_judged_as_line_by_line(parts, rows, longest, cut):
    """The rows after the vertices (a scanner's range grid: 200k of them) are counted a block at a
    time; the verdict, data after them or not, is the one a line-by-line reading gives, blank lines,
    line endings, lines too long to be rows and blocks that end inside a line included."""
    from esmicp.io import ply

    text = "".join(part + end for part, end in parts)
    if cut:
        text = text[: len(text) // 2]
    data = text.encode("utf-8")

    def wrapped():
        return io.TextIOWrapper(io.BytesIO(data), encoding="ascii", newline=None, errors="replace")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ply, "_MAX_ASCII_ROW", longest)
        assert ply._ascii_data_after(wrapped(), rows) == _data_after_line_by_line(wrapped(), rows, longest)
