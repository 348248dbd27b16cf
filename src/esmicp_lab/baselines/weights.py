"""Where the learned baselines look for pretrained weights (never shipped in the repository).

In this order: the ``weights_dir`` argument of the adapter (only it, when given); the
``ESMICP_WEIGHTS_DIR`` environment variable; ``shared/weights`` beside the repository checkout
(the project's shared folder) when esmicp runs from its source tree; ``../shared/weights`` from the
current directory (a checkout's root, when esmicp is installed as a package, as in CI). Inside it,
each model has its own folder (``pointnetlk/best_model.t7``, ...).
"""

from __future__ import annotations

import os
from pathlib import Path

from .base import WeightsNotAvailableError

#: The environment variable naming a weights folder.
WEIGHTS_ENV = "ESMICP_WEIGHTS_DIR"

_CHECKOUT_SHARED = Path(__file__).resolve().parents[3].parent / "shared" / "weights"


def candidate_dirs(weights_dir=None) -> list[Path]:
    """The folders searched, in order (see the module's docstring)."""
    if weights_dir is not None:
        return [Path(weights_dir)]
    folders = []
    if os.environ.get(WEIGHTS_ENV):
        folders.append(Path(os.environ[WEIGHTS_ENV]))
    folders.append(_CHECKOUT_SHARED)
    beside_cwd = Path.cwd().resolve().parent / "shared" / "weights"
    if beside_cwd != _CHECKOUT_SHARED:
        folders.append(beside_cwd)
    return folders


def find_weights(method: str, relative: str, weights_dir=None) -> Path:
    """The path of ``relative`` (e.g. ``pointnetlk/best_model.t7``) in the first folder of
    :func:`candidate_dirs` that has it; :class:`WeightsNotAvailableError` naming every place
    looked at otherwise."""
    folders = candidate_dirs(weights_dir)
    for folder in folders:
        path = folder / relative
        if path.is_file():
            return path
    looked = ", ".join(str(folder / relative) for folder in folders)
    raise WeightsNotAvailableError(
        f"{method}: weights not available: no {relative} in {looked}; put the pretrained file there, "
        f"or point {WEIGHTS_ENV} (or weights_dir=) at a folder holding {relative}"
    )
