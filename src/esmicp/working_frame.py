"""A well-conditioned working frame for clouds far from the origin.

Coordinates far from the origin relative to the cloud's size (UTM or ECEF coordinates, 1e8 m
away, of a scan 10 m across) carry rounding noise of about ``1e-16 x |coordinate|`` in every
point: larger than the convergence tolerance relative to the cloud, so the iterations could never
settle. :func:`register <esmicp.register>` therefore works in a frame shifted by a point of the
target (its centroid) when the clouds are far from the origin, and maps the result back: rigid
registration is equivariant under a common shift, so only the rounding changes (measured:
docs/reliability.md).

A shift by ``o`` turns a transform ``T_target_source`` into ``Tr(-o) @ T @ Tr(o)`` (same rotation,
translation ``R o + t - o``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .core.procrustes import bounding_box_diagonal, centroid

#: The clouds are registered in a shifted frame when the target's centroid is farther from the
#: origin than this many times the target's bounding-box diagonal (rounding noise then exceeds
#: ~1e-13 of the cloud's size; below, a shift would change nothing measurable).
FAR_FROM_ORIGIN = 1e3


@dataclass(frozen=True, eq=False)
class WorkingFrame:
    """The frame a registration runs in: coordinates ``x - origin`` (``origin`` None: no shift)."""

    origin: np.ndarray | None = None

    @classmethod
    def for_target(cls, target: np.ndarray) -> "WorkingFrame":
        """Shifted onto the target's centroid when it is farther than :data:`FAR_FROM_ORIGIN`
        diagonals from the origin; unshifted otherwise."""
        centre = centroid(target)
        if float(np.linalg.norm(centre)) > FAR_FROM_ORIGIN * bounding_box_diagonal(target):
            return cls(centre)
        return cls(None)

    def points(self, points: np.ndarray) -> np.ndarray:
        """``(N, 3)`` points in the working frame (the same array when unshifted)."""
        return points if self.origin is None else points - self.origin

    def transform_in(self, transform: np.ndarray | None) -> np.ndarray | None:
        """``transform`` (4x4, original coordinates) in the working frame."""
        if transform is None or self.origin is None:
            return transform
        shifted = transform.copy()
        shifted[:3, 3] = transform[:3, :3] @ self.origin + transform[:3, 3] - self.origin
        return shifted

    def transform_out(self, transform: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`transform_in`: back to the original coordinates."""
        if self.origin is None:
            return transform
        original = transform.copy()
        original[:3, 3] = transform[:3, 3] + (self.origin - transform[:3, :3] @ self.origin)
        return original

    def callback(self, callback):
        """``callback`` wrapped so that it sees states in the original coordinates."""
        if callback is None or self.origin is None:
            return callback

        def wrapped(state):
            return callback(
                dataclasses.replace(
                    state,
                    transformation=self.transform_out(state.transformation),
                    moved_source=state.moved_source + self.origin,
                    placement=None if state.placement is None else self.transform_out(state.placement),
                )
            )

        return wrapped

    def outcome(self, outcome):
        """A refinement outcome with its pose and history back in the original coordinates."""
        if self.origin is None:
            return outcome
        history = None if outcome.history is None else tuple(
            dataclasses.replace(record, transformation=self.transform_out(record.transformation))
            for record in outcome.history
        )
        return dataclasses.replace(outcome, transformation=self.transform_out(outcome.transformation), history=history)
