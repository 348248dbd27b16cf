"""Poses of many scans as text: ``T_world_scan`` per scan, in three formats.

``matrix`` (the default of ``esmicp merge --poses-out``)
    One line per scan, in scan order: the 16 numbers of the 4x4 ``T_world_scan``, row-major, then
    a comment ``# index status file``. ``nan`` (16 times) where a scan has no pose.
    ``np.loadtxt(path).reshape(-1, 4, 4)`` reads the poses (NumPy drops everything after ``#``).
``tum``
    The TUM RGB-D benchmark's ``timestamp tx ty tz qx qy qz qw`` (translation, then the rotation as
    a unit quaternion, scalar last), one line per scan that has a pose; a scan with no pose has no
    line. The timestamp is the scan index unless others are given. Comment lines (``#``) before
    the data name every scan: ``# scan index timestamp status file``.
``kitti``
    The KITTI odometry benchmark's 12 numbers a line: the top 3x4 of ``T_world_scan``, row-major.
    One line per scan, in scan order, with no comment (KITTI tools read the lines as they are);
    ``nan`` (12 times) where a scan has no pose. Names and statuses are not kept.

Every number is written with 17 significant digits, so the matrix and KITTI formats round-trip
exactly and TUM to the precision of the quaternion conversion (about 1e-16).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError, PointCloudFileError
from ..types import as_transform
from ._files import as_path, check_input_file
from ._messages import excerpt
from .atomic import atomic_write
from .text import text_lines

__all__ = ["POSE_FORMATS", "PoseFile", "read_poses", "write_poses"]

#: The formats :func:`write_poses` writes and :func:`read_poses` reads.
POSE_FORMATS = ("matrix", "tum", "kitti")

#: Numbers per data line of each format.
_COLUMNS = {"matrix": 16, "tum": 8, "kitti": 12}
#: First line of the files written here; names the format.
_MARK = re.compile(r"^#\s*esmicp poses, format (\w+)")
_WORLD = re.compile(r"world\s*=\s*the frame of scan (\d+)")
#: A TUM quaternion whose norm is further than this from 1 is not a rotation (a file of another
#: kind, or columns in another order); closer ones (files written with few decimals) are normalised.
QUATERNION_NORM_TOLERANCE = 1e-3


@dataclass(frozen=True, eq=False)
class PoseFile:
    """What a pose file holds.

    Attributes
    ----------
    poses : numpy.ndarray
        ``(N, 4, 4)`` float64 ``T_world_scan`` per scan; all NaN where the file gives a scan no pose.
    format : str
        One of :data:`POSE_FORMATS`.
    names : tuple of str, or None
        The scans' files as written (None when the file does not name them: KITTI, a TUM file
        written elsewhere; an entry is None for a scan written without one).
    status : tuple of str, or None
        Per scan, ``"placed"``, ``"doubtful"`` or ``"unplaced"`` as the merge judged it (None when
        the file does not say; an entry is None for a scan written without one).
    timestamps : numpy.ndarray or None
        TUM only: ``(N,)`` float64 timestamp per scan (a scan with no pose line keeps the timestamp
        its header line gives).
    reference : int or None
        The scan whose frame is the world, when the file says.
    """

    poses: np.ndarray
    format: str
    names: tuple[str | None, ...] | None = None
    status: tuple[str | None, ...] | None = None
    timestamps: np.ndarray | None = None
    reference: int | None = None

    def __len__(self) -> int:
        return len(self.poses)


def _number(value: float) -> str:
    return f"{value:.17g}"


def _shown_name(name: str) -> str:
    """A file name for the end of a line: as it is, or JSON-quoted when reading it back as the
    rest of the line would change it (edge spaces, quotes, control characters)."""
    if name != name.strip() or name.startswith('"') or not name.isprintable() or not name:
        return json.dumps(name)
    return name


def _read_name(text: str) -> str:
    if text.startswith('"'):
        try:
            name = json.loads(text)
        except ValueError:
            return text
        if isinstance(name, str):
            return name
    return text


def _as_poses(poses) -> np.ndarray:
    try:
        array = np.array(poses, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"poses: expected an (N, 4, 4) array of transforms, could not convert: {exc}") from None
    if array.ndim != 3 or array.shape[1:] != (4, 4):
        raise InvalidInputError(f"poses: expected an (N, 4, 4) array of transforms, got shape {array.shape}")
    for k, T in enumerate(array):
        finite = np.isfinite(T)
        if not finite.all() and finite.any():
            raise InvalidInputError(f"poses[{k}]: some entries are NaN or infinite (all NaN means no pose)")
        if finite.all():
            as_transform(T, name=f"poses[{k}]")
    return array


def _per_scan(values, count: int, name: str) -> tuple | None:
    if values is None:
        return None
    values = tuple(values)
    if len(values) != count:
        raise InvalidInputError(f"{name}: expected one per pose ({count}), got {len(values)}")
    return values


def _quaternion(R: np.ndarray) -> np.ndarray:
    """``(qx, qy, qz, qw)`` of a rotation matrix, ``qw >= 0``."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R).as_quat()
    return -q if q[3] < 0 else q


def write_poses(path, poses, *, format: str = "matrix", names=None, status=None, timestamps=None,
                reference: int | None = None, overwrite: bool = False) -> None:
    """Write one ``T_world_scan`` per scan in one of :data:`POSE_FORMATS` (see :mod:`esmicp.io.poses`).

    Parameters
    ----------
    path : str or os.PathLike
        Output text file; written atomically.
    poses : array_like
        ``(N, 4, 4)`` rigid ``T_world_scan``, in the scans' units; a scan with no pose is all NaN
        (matrix, KITTI: a line of ``nan``; TUM: no line).
    format : {"matrix", "tum", "kitti"}
    names, status : sequence of str, optional
        Per scan, its file and its verdict (``placed`` / ``doubtful`` / ``unplaced``); kept by the
        matrix and TUM formats, not by KITTI.
    timestamps : sequence of float, optional
        TUM only: a timestamp per scan (default: the scan index).
    reference : int, optional
        The scan whose frame is the world, named in the matrix and TUM headers.
    overwrite : bool
        Replace an existing file.

    Raises
    ------
    InvalidInputError
        A bad argument: an unknown format, a pose that is not rigid (or partly NaN), per-scan
        values not one per pose, timestamps not finite or not distinct (nothing is written).
    OutputExistsError
        ``path`` exists and ``overwrite`` is False.
    PointCloudFileError
        The file cannot be written.
    """
    path = as_path(path)
    if format not in POSE_FORMATS:
        raise InvalidInputError(f"format: expected one of {', '.join(POSE_FORMATS)}, got {format!r}")
    array = _as_poses(poses)
    count = len(array)
    names = _per_scan(names, count, "names")
    status = _per_scan(status, count, "status")
    if timestamps is not None and format != "tum":
        raise InvalidInputError(f"timestamps: only the tum format holds timestamps, not {format}")
    stamps = np.arange(count, dtype=np.float64) if timestamps is None else np.asarray(
        _per_scan(timestamps, count, "timestamps"), dtype=np.float64)
    if not np.isfinite(stamps).all() or len(set(stamps.tolist())) < count:
        raise InvalidInputError("timestamps: expected finite, distinct numbers")
    if reference is not None and not 0 <= reference < max(count, 1):
        raise InvalidInputError(f"reference: expected a scan index in [0, {count}), got {reference}")
    for k, word in enumerate(status or ()):
        if word is not None and (not word or any(c.isspace() for c in str(word))):
            raise InvalidInputError(f"status[{k}]: expected one word, got {word!r}")
    world = f" (world = the frame of scan {reference})" if reference is not None else ""
    lines = []
    placed = [k for k in range(count) if np.isfinite(array[k]).all()]
    if format == "matrix":
        lines.append(f"# esmicp poses, format matrix: T_world_scan per scan{world}, row-major 4x4; nan: no pose")
        lines.append("# np.loadtxt(path).reshape(-1, 4, 4) reads the poses; after each '#': index, status, file")
        for k, T in enumerate(array):
            tail = f"  # {k} {'-' if status is None or status[k] is None else status[k]}"
            if names is not None:
                tail += f" {_shown_name(str(names[k]))}"
            lines.append(" ".join(_number(v) for v in T.ravel()) + tail)
    elif format == "tum":
        lines.append(f"# esmicp poses, format tum: timestamp tx ty tz qx qy qz qw, T_world_scan{world}")
        lines.append("# one line per scan with a pose; per scan: index, timestamp, status, file")
        for k in range(count):
            word = "-" if status is None or status[k] is None else status[k]
            name = "" if names is None else f" {_shown_name(str(names[k]))}"
            lines.append(f"# scan {k} {_number(stamps[k])} {word}{name}")
        for k in placed:
            T = array[k]
            values = [stamps[k], *T[:3, 3], *_quaternion(T[:3, :3])]
            lines.append(" ".join(_number(v) for v in values))
    else:
        for T in array:
            lines.append(" ".join(_number(v) for v in T[:3].ravel()))
    with atomic_write(path, overwrite, mode="w") as handle:
        handle.write("".join(line + "\n" for line in lines))


def _error(path, line: int, problem: str) -> PointCloudFileError:
    return PointCloudFileError(path, f"line {line}: {problem}")


def _numbers(path, number: int, words: list[str]) -> list[float]:
    values = []
    for word in words:
        try:
            values.append(float(word))
        except ValueError:
            raise _error(path, number, f"{excerpt(word, 30)} is not a number") from None
    return values


def _pose_from_row(path, number: int, format: str, values: list[float]) -> np.ndarray:
    """The 4x4 pose of one data line (all NaN for a line of NaN), checked rigid."""
    array = np.array(values, dtype=np.float64)
    body = array[1:] if format == "tum" else array
    if np.isnan(body).all() and format != "tum":
        return np.full((4, 4), np.nan)
    if not np.isfinite(array).all():
        raise _error(path, number, "NaN or infinite numbers in a pose (a pose is all numbers, or all nan for none)")
    if format == "matrix":
        T = array.reshape(4, 4)
    elif format == "kitti":
        T = np.vstack([array.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
    else:
        from scipy.spatial.transform import Rotation

        q = array[4:8]
        norm = float(np.linalg.norm(q))
        if not abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
            raise _error(path, number, f"the quaternion qx qy qz qw has norm {norm:.6g}, not 1")
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
        T[:3, 3] = array[1:4]
    try:
        return as_transform(T, name="pose")
    except InvalidInputError as exc:
        raise _error(path, number, str(exc).removeprefix("pose: ")) from None


def read_poses(path, *, format: str | None = None) -> PoseFile:
    """Read a pose file written by :func:`write_poses` (``esmicp merge --poses-out``), or a TUM or
    KITTI trajectory written elsewhere.

    Parameters
    ----------
    path : str or os.PathLike
    format : {"matrix", "tum", "kitti"}, optional
        None (default): from the file's first line when esmicp wrote it, else from the numbers on
        its first data line (16: matrix, 12: KITTI, 8: TUM).

    Returns
    -------
    PoseFile
        ``poses`` ``(N, 4, 4)`` ``T_world_scan`` (all NaN for a scan with no pose), and what else
        the file holds: names, statuses, TUM timestamps, the reference scan. In a TUM file that
        lists its scans in its header, each line goes to the scan of its timestamp; otherwise
        the poses are the lines in order.

    Raises
    ------
    PointCloudFileError
        The file is missing or unreadable, or a line is not a pose of the format (the message
        names the file and the line): a word that is not a number, a count of numbers that does
        not fit, a rotation that is not one, a TUM timestamp listed for no scan or twice.
    InvalidInputError
        ``format`` is not one of :data:`POSE_FORMATS`.
    """
    path = as_path(path)
    if format is not None and format not in POSE_FORMATS:
        raise InvalidInputError(f"format: expected one of {', '.join(POSE_FORMATS)}, got {format!r}")
    check_input_file(path)
    header: list[tuple[int, str]] = []  # (line number, comment) before the first pose
    lines: list[int] = []  # per pose line: its number in the file
    poses: list[np.ndarray] = []
    comments: list[str | None] = []  # per pose line: what follows its '#'
    stamps: list[float] = []  # TUM: per pose line, its timestamp
    try:
        for number, line in enumerate(text_lines(path), 1):
            stripped = line.strip()
            if not stripped or stripped.startswith("//"):
                continue
            if stripped.startswith("#"):
                if not poses:
                    header.append((number, stripped))
                continue
            data, mark, comment = stripped.partition("#")
            words = data.translate(_SEPARATORS).split()
            if format is None:  # the first pose line: the format from the header, else from it
                named = _MARK.match(header[0][1]) if header else None
                format = named.group(1) if named is not None and named.group(1) in POSE_FORMATS else next(
                    (name for name, columns in _COLUMNS.items() if columns == len(words)), None)
                if format is None:
                    raise _error(path, number, f"{len(words)} values; a pose line has 16 (matrix), 12 (KITTI) "
                                 "or 8 (TUM: timestamp tx ty tz qx qy qz qw)")
            if len(words) != _COLUMNS[format]:
                raise _error(path, number, f"{len(words)} values; a {format} pose line has {_COLUMNS[format]}")
            values = _numbers(path, number, words)
            poses.append(_pose_from_row(path, number, format, values))
            lines.append(number)
            comments.append(comment.strip() if mark else None)
            if format == "tum":
                stamps.append(values[0])
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot read: {exc.strerror or exc}") from None
    if not poses:
        raise PointCloudFileError(path, "no poses: only comments and blank lines")
    marked = _MARK.match(header[0][1]) if header else None
    world = _WORLD.search(header[0][1]) if marked is not None else None
    reference = int(world.group(1)) if world is not None else None
    if format == "matrix":
        return _matrix_file(path, poses, list(zip(lines, comments)), reference)
    if format == "kitti":
        return PoseFile(np.array(poses).reshape(-1, 4, 4), "kitti", reference=reference)
    return _tum_file(path, header, lines, poses, stamps, reference)


#: Separators accepted between numbers (as in the transform files).
_SEPARATORS = str.maketrans({",": " ", ";": " ", "\t": " "})


def _matrix_file(path, poses, comments, reference) -> PoseFile:
    names: list[str | None] = []
    status: list[str | None] = []
    for k, (number, comment) in enumerate(comments):
        if comment is None:
            names.append(None)
            status.append(None)
            continue
        words = comment.split(maxsplit=2)
        if not words or not words[0].isdigit():  # a comment of the user's own, not a scan's
            names.append(None)
            status.append(None)
            continue
        if int(words[0]) != k:
            raise _error(path, number, f"pose line {k + 1} names scan {words[0]}: the lines must be "
                         "in scan order, one per scan")
        status.append(None if len(words) < 2 or words[1] == "-" else words[1])
        names.append(_read_name(words[2]) if len(words) > 2 else None)
    return PoseFile(
        np.array(poses).reshape(-1, 4, 4), "matrix",
        names=None if all(n is None for n in names) else tuple(names),
        status=None if all(s is None for s in status) else tuple(status),
        reference=reference,
    )


_SCAN_LINE = re.compile(r"^#\s*scan\s+(\d+)\s+(\S+)\s+(\S+)(?:\s+(.*))?$")


def _tum_file(path, header, lines, poses, stamps, reference) -> PoseFile:
    listed = [(number, m) for number, m in ((n, _SCAN_LINE.match(line)) for n, line in header) if m is not None]
    if not listed:  # a trajectory written elsewhere: the lines in order
        return PoseFile(np.array(poses).reshape(-1, 4, 4), "tum", timestamps=np.array(stamps, dtype=np.float64),
                        reference=reference)
    count = len(listed)
    names: list[str | None] = [None] * count
    status: list[str | None] = [None] * count
    timestamps = np.full(count, np.nan)
    scan_of: dict[float, int] = {}
    for position, (number, match) in enumerate(listed):
        index = int(match.group(1))
        if index != position:
            raise _error(path, number, f"the header lists scan {index} where scan {position} belongs "
                         "(scans 0, 1, 2, ... in order)")
        try:
            timestamps[index] = float(match.group(2))
        except ValueError:
            raise _error(path, number, f"scan {index}'s timestamp {excerpt(match.group(2), 30)} is not a number") from None
        if timestamps[index] in scan_of:
            raise _error(path, number, f"scan {index} has the timestamp of scan {scan_of[timestamps[index]]}")
        scan_of[timestamps[index]] = index
        status[index] = None if match.group(3) == "-" else match.group(3)
        names[index] = None if match.group(4) is None else _read_name(match.group(4))
    out = np.full((count, 4, 4), np.nan)
    seen: set[int] = set()
    for number, T, stamp in zip(lines, poses, stamps):
        k = scan_of.get(stamp)
        if k is None:
            raise _error(path, number, f"timestamp {_number(stamp)} is none of the scans the header lists")
        if k in seen:
            raise _error(path, number, f"a second pose for scan {k} (timestamp {_number(stamp)})")
        seen.add(k)
        out[k] = T
    return PoseFile(
        out, "tum",
        names=None if all(n is None for n in names) else tuple(names),
        status=None if all(s is None for s in status) else tuple(status),
        timestamps=timestamps, reference=reference,
    )
