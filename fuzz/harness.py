"""The contract every point-cloud reader must keep, and the valid seed files of every fuzz target.

Shared by the atheris scripts (``fuzz/fuzz_reader.py``), the hypothesis mutation tests
(``tests/test_fuzz_hypothesis.py``) and the corpus replay (``tests/test_fuzz_corpus.py``).

The contract, for any bytes written to a file of the target's extension and read with
:func:`esmicp.read_points`:

- either a new ``(N, 3)`` float64 array of finite values with ``N >= 3`` comes back,
- or :class:`esmicp.errors.PointCloudFileError` is raised, with a one-line message that starts
  with the file's path, says the problem in plain words (not the reader's catch-all wrapping of an
  unanticipated exception, e.g. ``could not be read (IndexError: ...)``), and does not come from
  trying to allocate what a lying header claims (``too large to load into memory``);
- and no warning other than :class:`esmicp.errors.NonFinitePointsWarning` is emitted.

Anything else (another exception, a catch-all message, a stray warning, a wrong array) raises
:class:`ContractViolation`: a bug to fix, whose input then goes into ``tests/corpus/``.
"""

from __future__ import annotations

import io
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["TARGETS", "ContractViolation", "Target", "check_file", "seeds"]

#: Message fragments that mean a reader did not anticipate the input (see the module docstring).
CATCH_ALL_MARKERS = ("could not be read (", "too large to load into memory", "No module named")

#: A clear message is one line and not a dump of the data.
MAX_MESSAGE_CHARS = 400


class ContractViolation(AssertionError):
    """A reader broke the contract of this module on some input."""


@dataclass(frozen=True)
class Target:
    """One fuzz target: a reader reached through a file extension, with its valid seed files."""

    name: str
    extension: str
    description: str


TARGETS = {
    target.name: target
    for target in (
        Target("pcd-ascii", ".pcd", "PCD, DATA ascii"),
        Target("pcd-binary", ".pcd", "PCD, DATA binary"),
        Target("pcd-compressed", ".pcd", "PCD, DATA binary_compressed (LZF)"),
        Target("ply-ascii", ".ply", "PLY, format ascii"),
        Target("ply-binary", ".ply", "PLY, binary little- and big-endian"),
        Target("off", ".off", "OFF mesh (vertices)"),
        Target("xyz", ".xyz", "text x y z (also .txt, .pts)"),
        Target("csv", ".csv", "comma-separated text"),
        Target("npy", ".npy", "NumPy .npy array"),
        Target("obj", ".obj", "Wavefront OBJ mesh (vertices, via trimesh)"),
        Target("stl", ".stl", "STL mesh, ascii and binary (vertices, via trimesh)"),
    )
}


#: Mesh files are also read with ``sample_points`` (surface sampling), under the same contract.
MESH_EXTENSIONS = (".off", ".obj", ".stl")
SAMPLE_POINTS = 16


def check_file(path: Path) -> str:
    """Read ``path`` with :func:`esmicp.read_points` and check the contract.

    Mesh files are read twice: their vertices, and :data:`SAMPLE_POINTS` points sampled on them.

    Returns
    -------
    str
        ``"points"`` or ``"error"``: how reading the vertices ended (both are fine).

    Raises
    ------
    ContractViolation
        The reader broke the contract; the message says how.
    """
    outcome = _check_read(path, {})
    if Path(path).suffix.lower() in MESH_EXTENSIONS:
        _check_read(path, {"sample_points": SAMPLE_POINTS, "rng": 0})
    return outcome


def _check_read(path: Path, options: dict) -> str:
    from esmicp import io as esmicp_io
    from esmicp.errors import NonFinitePointsWarning, PointCloudFileError

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            points = esmicp_io.read_points(path, **options)
        except PointCloudFileError as exc:
            _check_error(path, exc)
            outcome = "error"
        except Exception as exc:  # noqa: BLE001 - that is exactly what the fuzzer looks for
            raise ContractViolation(
                f"{type(exc).__name__} escaped read_points{_describe(options)} (not PointCloudFileError): {exc}"
            ) from exc
        else:
            _check_points(points)
            if "sample_points" in options and len(points) != options["sample_points"]:
                raise ContractViolation(f"asked for {options['sample_points']} samples, got {len(points)}")
            outcome = "points"
    stray = [w for w in caught if not issubclass(w.category, NonFinitePointsWarning)]
    if stray:
        first = stray[0]
        raise ContractViolation(
            f"stray warning {first.category.__name__} from {first.filename}:{first.lineno}"
            f"{_describe(options)}: {first.message}"
        )
    return outcome


def _describe(options: dict) -> str:
    return f" (with sample_points={options['sample_points']})" if options else ""


def _check_error(path: Path, exc: Exception) -> None:
    message = str(exc)
    if not message.startswith(str(path)):
        raise ContractViolation(f"error message does not start with the path: {message!r}")
    if "\n" in message or len(message) > MAX_MESSAGE_CHARS:
        raise ContractViolation(f"error message is not one short line: {message[:200]!r}...")
    problem = message[len(str(path)) :]
    for marker in CATCH_ALL_MARKERS:
        if marker in problem:
            raise ContractViolation(f"unanticipated failure, wrapped by the catch-all: {message!r}") from exc


def _check_points(points) -> None:
    if not isinstance(points, np.ndarray) or points.dtype != np.float64:
        raise ContractViolation(f"expected a float64 ndarray, got {type(points).__name__} {getattr(points, 'dtype', '')}")
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 3:
        raise ContractViolation(f"expected (N >= 3, 3) points, got shape {points.shape}")
    if not np.isfinite(points).all():
        raise ContractViolation("returned points contain NaN or infinite values")


# --------------------------------------------------------------------------------------------
# Seeds: small valid files of every target, in the variants real files come in.


def _cloud(count: int = 5, seed: int = 0) -> np.ndarray:
    generator = np.random.default_rng(seed)
    return np.round(generator.normal(size=(count, 3)), 3)


def _written(extension: str, points: np.ndarray, **kwargs) -> bytes:
    """What :func:`esmicp.write_points` writes for ``points`` (written to memory via a temp file)."""
    import tempfile

    from esmicp.io import write_points

    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / f"seed{extension}"
        write_points(path, points, **kwargs)
        return path.read_bytes()


def _pcd_header(data: str, points: int, fields="x y z", size="4 4 4", kind="F F F", count="1 1 1",
                width=None, height=1, version="0.7") -> bytes:
    width = points if width is None else width
    return (
        f"# .PCD v{version} - Point Cloud Data file format\nVERSION {version}\nFIELDS {fields}\n"
        f"SIZE {size}\nTYPE {kind}\nCOUNT {count}\nWIDTH {width}\nHEIGHT {height}\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {data}\n"
    ).encode()


def _ply_header(fmt: str, vertices: int, properties=("float x", "float y", "float z"), extra="") -> bytes:
    lines = ["ply", f"format {fmt} 1.0", "comment seed", f"element vertex {vertices}"]
    lines += [f"property {p}" for p in properties]
    return ("\n".join(lines) + "\n" + extra + "end_header\n").encode()


def _lzf_block(raw: bytes) -> bytes:
    import lzf

    compressed = lzf.compress(raw, len(raw) + len(raw) // 16 + 64)
    return struct.pack("<II", len(compressed), len(raw)) + compressed


def _seeds_pcd_ascii() -> list[bytes]:
    points = _cloud()
    return [
        _written(".pcd", points, pcd_format="ascii"),
        _pcd_header("ascii", 4, fields="x y z intensity", size="4 4 4 4", kind="F F F F", count="1 1 1 1",
                    version=".5")
        + b"1 2 3 0.5\n4 5 6 1\n7 8 9 2\n-1 -2 -3 nan\n",
        _pcd_header("ascii", 4, width=2, height=2, fields="x y z rgb", size="4 4 4 4", kind="F F F U",
                    count="1 1 1 1")
        + b"1 2 3 255\nnan nan nan 0\n4\t5\t6 7\n7 8 9 1\n",
        _pcd_header("ascii", 3, fields="x y z normal", size="8 8 8 4", kind="F F F F", count="1 1 1 3")
        + b"1 2 3 0 0 1\n4 5 6 0 1 0\n7 8 9 1 0 0\n",
    ]


def _seeds_pcd_binary() -> list[bytes]:
    points = _cloud()
    mixed = np.zeros(4, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<u2"), ("ring", "<u1")])
    mixed["x"], mixed["y"], mixed["z"] = points[:4].T
    integer = np.arange(12, dtype="<i2").reshape(4, 3)
    return [
        _written(".pcd", points, pcd_format="binary"),
        _pcd_header("binary", 4, fields="x y z intensity ring", size="4 4 4 2 1", kind="F F F U U",
                    count="1 1 1 1 1")
        + mixed.tobytes(),
        _pcd_header("binary", 4, size="2 2 2", kind="I I I", width=2, height=2) + integer.tobytes(),
    ]


def _seeds_pcd_compressed() -> list[bytes]:
    points = _cloud()
    columns = b"".join(np.ascontiguousarray(points[:4, c], dtype="<f4").tobytes() for c in range(3))
    intensity = np.arange(4, dtype="<f4").tobytes()
    return [
        _written(".pcd", points, pcd_format="binary_compressed"),
        _pcd_header("binary_compressed", 4) + _lzf_block(columns),
        _pcd_header("binary_compressed", 4, fields="x y z intensity", size="4 4 4 4", kind="F F F F",
                    count="1 1 1 1")
        + _lzf_block(columns + intensity),
        _pcd_header("binary_compressed", 4) + _lzf_block(bytes(48)),  # zeros compress well
    ]


def _seeds_ply_ascii() -> list[bytes]:
    points = _cloud()
    faces = "element face 2\nproperty list uchar int vertex_indices\n"
    return [
        _written(".ply", points, ply_format="ascii"),
        _ply_header("ascii", 4, ("float x", "float y", "float z", "uchar red", "float nx"), faces)
        + b"0 0 0 255 1\n1 0 0 0 0\n0 1 0 12 0.5\n0 0 1 1 1\n3 0 1 2\n3 0 2 3\n",
        _ply_header("ascii", 3, ("double x", "double y", "double z")).replace(b"\n", b"\r\n")
        + b"1 2 3\r\n4 5 6\r\n7 8 9\r\n",
    ]


def _seeds_ply_binary() -> list[bytes]:
    points = _cloud()
    vertices = np.zeros(4, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("red", "u1")])
    vertices["x"], vertices["y"], vertices["z"] = points[:4].T
    faces = "element face 2\nproperty list uchar int vertex_indices\n"
    face_rows = struct.pack(">B3i", 3, 0, 1, 2) + struct.pack(">B3i", 3, 0, 2, 3)
    grid = "element range_grid 2\nproperty list uchar int vertex_indices\n"
    return [
        _written(".ply", points, ply_format="binary"),
        _ply_header("binary_big_endian", 4, ("float x", "float y", "float z", "uchar red"), faces)
        + vertices.tobytes()
        + face_rows,
        _ply_header("binary_little_endian", 4, ("short x", "short y", "short z"))
        + np.arange(12, dtype="<i2").tobytes(),
        # A list element before the vertices (the Stanford scans' layout puts it after).
        b"ply\nformat binary_little_endian 1.0\n" + grid.encode()
        + b"element vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        + struct.pack("<Bi", 1, 0) + struct.pack("<B", 0)
        + np.arange(9, dtype="<f4").tobytes(),
    ]


_TETRAHEDRON_OFF = "OFF\n# tetrahedron\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n"


def _seeds_off() -> list[bytes]:
    cube = "OFF8 6 0\n" + "".join(
        f"{x} {y} {z}\n" for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)
    ) + "4 0 1 3 2\n4 4 6 7 5\n4 0 4 5 1\n4 2 3 7 6\n4 0 2 6 4\n4 1 5 7 3\n"
    coloured = "COFF\n3 1 0\n0 0 0 255 0 0 255\n1 0 0 0 255 0 255\n0 1 0 0 0 255 255\n3 0 1 2\n"
    return [_TETRAHEDRON_OFF.encode(), cube.encode(), coloured.encode()]


def _seeds_xyz() -> list[bytes]:
    points = _cloud()
    return [
        _written(".xyz", points),
        b"4\n1 2 3\n4 5 6\n7 8 9\n1e-3 -2.5E+2 0\n",
        b"# comment\nx y z nx ny nz\n1\t2\t3 0 0 1\n4;5;6;0;1;0\n\n// more\n7 8 9 1 0 0\n",
    ]


def _seeds_csv() -> list[bytes]:
    return [_written(".csv", _cloud()), b"x,y,z,intensity\n1,2,3,4\n5,6,7,8\n9,10,11,12\nnan,1,2,3\n"]


def _seeds_npy() -> list[bytes]:
    def saved(array, version=None) -> bytes:
        buffer = io.BytesIO()
        if version is None:
            np.save(buffer, array, allow_pickle=False)
        else:
            np.lib.format.write_array(buffer, array, version=version, allow_pickle=False)
        return buffer.getvalue()

    points = _cloud()
    structured = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "<u1")])
    return [
        saved(points),
        saved(points.astype(">f4")),
        saved(np.asfortranarray(np.arange(12, dtype="<i4").reshape(4, 3))),
        saved(structured),
        saved(points, version=(2, 0)),
    ]


def _seeds_obj() -> list[bytes]:
    return [
        b"# tetrahedron\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n",
        b"o thing\nv 0 0 0 1 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nvt 0 0\nf 1/1/1 2/1/1 3/1/1\n",
    ]


def _seeds_stl() -> list[bytes]:
    triangles = [((0, 0, 0), (1, 0, 0), (0, 1, 0)), ((0, 0, 0), (0, 0, 1), (1, 0, 0))]
    ascii_stl = "solid seed\n" + "".join(
        "facet normal 0 0 1\nouter loop\n" + "".join(f"vertex {x} {y} {z}\n" for x, y, z in tri)
        + "endloop\nendfacet\n"
        for tri in triangles
    ) + "endsolid seed\n"
    binary = bytes(80) + struct.pack("<I", len(triangles)) + b"".join(
        struct.pack("<12fH", 0, 0, 1, *[c for v in tri for c in v], 0) for tri in triangles
    )
    return [ascii_stl.encode(), binary]


_SEEDS = {
    "pcd-ascii": _seeds_pcd_ascii,
    "pcd-binary": _seeds_pcd_binary,
    "pcd-compressed": _seeds_pcd_compressed,
    "ply-ascii": _seeds_ply_ascii,
    "ply-binary": _seeds_ply_binary,
    "off": _seeds_off,
    "xyz": _seeds_xyz,
    "csv": _seeds_csv,
    "npy": _seeds_npy,
    "obj": _seeds_obj,
    "stl": _seeds_stl,
}


def seeds(target: str) -> list[bytes]:
    """Small valid files of ``target`` (each reads back as a cloud)."""
    return _SEEDS[target]()
