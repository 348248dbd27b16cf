"""Saving the pictures: atomically, never over an existing file unless asked."""

from __future__ import annotations

from pathlib import Path

from ..errors import InvalidInputError
from ..io.atomic import atomic_write

#: Image formats :func:`save_figure` writes, by extension.
IMAGE_EXTENSIONS = (".png", ".svg", ".pdf")


def check_extension(path, allowed: tuple[str, ...], what: str) -> Path:
    """``path`` as a Path, or :class:`~esmicp.errors.InvalidInputError` when its extension is not
    one of ``allowed``."""
    path = Path(path)
    if path.suffix.lower() not in allowed:
        shown = repr(path.suffix) if path.suffix else "no extension"
        raise InvalidInputError(f"{path}: unsupported {what} file ({shown}); use {', '.join(allowed)}")
    return path


def save_figure(figure, path, *, overwrite: bool = False, dpi: int | None = None) -> None:
    """Save a matplotlib Figure atomically; the format follows the extension (png, svg, pdf)."""
    path = check_extension(path, IMAGE_EXTENSIONS, "image")
    with atomic_write(path, overwrite) as handle:
        figure.savefig(handle, format=path.suffix.lower().lstrip("."), dpi=dpi)
