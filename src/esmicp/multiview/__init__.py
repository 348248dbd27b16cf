"""Many scans into one model: :func:`register_scans` (pairwise global registration, a robust
pose graph, a joint multi-view refinement). See docs/merge.md."""

from .scans import Edge, MultiRegistrationResult, register_scans

__all__ = ["Edge", "MultiRegistrationResult", "register_scans"]
