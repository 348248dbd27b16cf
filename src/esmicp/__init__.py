"""esmicp: rigid registration of 3D point clouds with ESM-ICP.

Frames: every transform is ``T_target_source``, a 4x4 matrix that maps source coordinates into
the target frame (``target ~= source @ R.T + t``).
"""

from ._version import __version__
from .api import register
from .batch import RegistrationFailure, register_many
from .errors import (
    EsmicpError,
    CoincidentPointsWarning,
    EsmicpWarning,
    IndexAlignmentWarning,
    InvalidInputError,
    NonFinitePointsWarning,
    OutputExistsError,
    PointCloudFileError,
)
from .methods import METHODS
from .multiview import MultiRegistrationResult, register_scans
from .result import IterationRecord, RegistrationResult


def __getattr__(name):
    # The file readers pull in plyfile / pypcd4 / trimesh: load them on first use only.
    if name in ("read_points", "write_points", "read_transform", "write_transform"):
        from . import io

        return getattr(io, name)
    raise AttributeError(f"module 'esmicp' has no attribute {name!r}")


__all__ = [
    "METHODS",
    "EsmicpError",
    "CoincidentPointsWarning",
    "EsmicpWarning",
    "IndexAlignmentWarning",
    "InvalidInputError",
    "IterationRecord",
    "MultiRegistrationResult",
    "NonFinitePointsWarning",
    "OutputExistsError",
    "PointCloudFileError",
    "RegistrationFailure",
    "RegistrationResult",
    "__version__",
    "read_points",
    "read_transform",
    "register",
    "register_many",
    "register_scans",
    "write_points",
    "write_transform",
]
