"""esmicp: rigid registration of 3D point clouds with ESM-ICP.

Frames: every transform is ``T_target_source``, a 4x4 matrix that maps source coordinates into
the target frame (``target ~= source @ R.T + t``).

``import esmicp`` loads only the version and the error types; each public name below is imported
on first use (PEP 562, as SciPy does), so the command line and ``import esmicp`` start fast and
NumPy, SciPy and the file readers load when something needs them.
"""

from ._version import __version__
from .errors import (
    EsmicpError,
    CoincidentPointsWarning,
    EsmicpWarning,
    IndexAlignmentWarning,
    InvalidInputError,
    NonFinitePointsWarning,
    OutputExistsError,
    PointCloudFileError,
    PointCloudFileNotFoundError,
)

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # what type checkers see: the names of the lazy table below, with their types
    from .api import register
    from .batch import RegistrationFailure, register_many
    from .io import PoseFile, read_points, read_poses, read_transform, write_points, write_poses, write_transform
    from .io.stanford_conf import read_stanford_conf
    from .methods import METHODS
    from .multiview import MultiRegistrationResult, register_scans
    from .result import Correspondences, IterationRecord, RegistrationResult

#: Public name -> the submodule that defines it (loaded on first access).
_LAZY = {
    "register": ".api",
    "RegistrationFailure": ".batch",
    "register_many": ".batch",
    "METHODS": ".methods",
    "MultiRegistrationResult": ".multiview",
    "register_scans": ".multiview",
    "Correspondences": ".result",
    "IterationRecord": ".result",
    "RegistrationResult": ".result",
    # The file readers pull in plyfile / pypcd4 / trimesh.
    "read_points": ".io",
    "write_points": ".io",
    "read_transform": ".io",
    "write_transform": ".io",
    "read_poses": ".io",
    "write_poses": ".io",
    "PoseFile": ".io",
    "read_stanford_conf": ".io.stanford_conf",
}


def __getattr__(name: str) -> object:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'esmicp' has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(module, __name__), name)
    globals()[name] = value  # later look-ups skip this hook
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "METHODS",
    "EsmicpError",
    "CoincidentPointsWarning",
    "Correspondences",
    "EsmicpWarning",
    "IndexAlignmentWarning",
    "InvalidInputError",
    "IterationRecord",
    "MultiRegistrationResult",
    "NonFinitePointsWarning",
    "OutputExistsError",
    "PointCloudFileError",
    "PointCloudFileNotFoundError",
    "PoseFile",
    "RegistrationFailure",
    "RegistrationResult",
    "__version__",
    "read_points",
    "read_poses",
    "read_stanford_conf",
    "read_transform",
    "register",
    "register_many",
    "register_scans",
    "write_points",
    "write_poses",
    "write_transform",
]
