"""The tuned values of the global search, in one frozen, documented object.

:class:`SearchConfig` holds every value of the global search that was chosen by measurement (a
bar, a ratio, a count whose value trades accuracy for time). The other numbers of
:mod:`esmicp.globalreg` are fixed design values (a grid's resolution, a cap on the work of one
stage) or derived from these. ``register(..., config=SearchConfig(...))`` runs the search with
other values; the default is :data:`DEFAULT`.

"Development set" below means the 12 ModelNet40 shapes of ``modelnet40/`` (object protocols and
halves cut to 70% / 50%), the Stanford bunny's scan pairs and the 3DMatch / LiDAR pairs of
``real_pairs/`` with their crops to 15-25% overlap; the confirmation set is ``modelnet40_extra/``
and frame pairs of the kitchen walk (``docs/measured-global.md``).
"""

from __future__ import annotations

import dataclasses
import numbers
from dataclasses import dataclass
from typing import Any

from ..errors import InvalidInputError


@dataclass(frozen=True)
class SearchConfig:
    """Tuned values of the global search (:func:`esmicp.globalreg.search.global_estimate`).

    Attributes
    ----------
    search_rotations : int
        Starting rotations of the rotation search, spread over SO(3) (count). More reach more
        starts within ESM's basin (64: at most 58 degrees from any rotation) at a linear cost.
        Measured on the development object protocols.
    search_points : int
        Source points (a random subsample) refined from every starting rotation (count).
    verify_candidates : int
        Distinct rotation-search poses passed on to the verification (count).
    score_width_spacings : float
        Width of the verifier's Gaussian overlap score, and floor of its annealed sigma, in target
        point spacings.
    ambiguity_ratio : float
        A clearly different pose (rotation more than
        :data:`~esmicp.globalreg.DISTINCT_ROTATION_DEG` away) scoring at least this fraction of
        the best makes the result ambiguous (0-1). Measured on the symmetric development shapes
        (bottle, cup, vase, lamp, flower pot), whose twins score within 3%.
    decide_ratio : float
        The full-resolution decision (both ways, up to 2,000 points of each cloud) runs when the
        runner-up scores at least this fraction of the best on the subsample (0-1): the one early
        exit of the verification, for cost.
    confident_score : float
        ``"auto"`` stops after the rotation search when its best pose puts at least this soft
        fraction of the source on the target (0-1; above 1: never) and is unambiguous and
        confident on the overlap or covers the target. Measured on outliers-30 / outliers-60 of
        the development shapes (the right poses scored 0.58-0.78, 5th percentile 0.63; wrong ones
        reached 0.62 once).
    full_cover : float
        Such a pose is also final when at least this fraction (0-1) of the target's points lie
        within two score widths of the placed source: the full overlap the score assumes holds
        (objects under 30% outliers: 1.0; cut halves and bunny scan pairs: at most 0.96).
    settle_from : float
        A rotation-search pose scoring at least this fraction of ``confident_score`` is refined a
        little further ("settled") and final when it then reaches ``confident_score`` and
        ``confident`` on the overlap (a LiDAR pair ending 2.6 degrees short scored 0.597).
    scan_margin : float
        The scan strategy's confident pose wins before the feature strategy runs when its overlap
        score is above this many times the rotation search's pose's (ratio, >= 1).
    sharper_score_ratio : float
        ... or when it overlaps at least this fraction as much (0-1) and its overlap confidence is
        higher by ``sharper_by``: a pose slid along a wall can overlap a little more, while only
        the true one makes the overlap coincide.
    sharper_by : float
        See ``sharper_score_ratio`` (confidence units, 0-1).
    sharper_than_chosen : float
        A chosen pose not ``confident`` on the overlap gives way to the scan strategy's pose most
        confident there when that is higher by at least this much (confidence units, 0-1); the
        result is then ambiguous. Measured on the development halves (a cut object's flip lies on
        more of the other part than the truth).
    scan_candidates : int
        The scan strategy's best poses (count) that join the verification when its best is not
        ``confident``.
    confident : float
        The search's own bar on the overlap confidence (0-1): a scan search reaching it ends the
        scan searches, and a pose reaching it may win over the other strategies'. Below
        :attr:`~esmicp.trust.policy.TrustPolicy.trusted`, the bar a result must reach to be trusted.
    scan_searches : int or None
        At most this many searches of the scan strategy in one ``"auto"`` search (count; None:
        each setting and voxel of :func:`~esmicp.globalreg.scan.scan_estimate_until_confident`
        in turn until one is confident, which a pair that cannot be registered runs to the end).
        A caller with a second chance at a pair (the merge searches an untrusted pair again on
        other points) can stop sooner: :attr:`esmicp.config.MergeConfig.pair_scan_searches`.
    keypoints : int
        Occupied voxels of the target the scan strategy's keypoint voxel aims at (count): the
        one length scale of the scan strategy and of the confidence.
    sharpness_range : tuple of float
        The overlap confidence's sharpness (of the keypoints within 3 voxels of the other cloud,
        the fraction within 1 voxel, the worse direction) mapped linearly from this range onto
        0-1. Measured on the 3DMatch crops and the development halves.
    spread_range : tuple of float
        The middle eigenvalue of the coincident part's normal moments (0 for one plane) mapped
        from this range onto 0-1 (the confidence is the smaller term) when less than half of
        either cloud coincides. Measured on the 3DMatch crops: wrong flat-on-flat poses
        0.014-0.083, right poses 0.11-0.38.
    third_range : tuple of float
        The smallest eigenvalue of the same (0 for a floor and one wall, which leave a slide free)
        mapped from this range onto 0-1. Measured on the 3DMatch crops: wrong poses 0.001-0.003,
        every ground truth 0.010-0.19.
    """

    search_rotations: int = 64
    search_points: int = 200
    verify_candidates: int = 16
    score_width_spacings: float = 2.0
    ambiguity_ratio: float = 0.97
    decide_ratio: float = 0.9
    confident_score: float = 0.6
    full_cover: float = 0.99
    settle_from: float = 0.9
    scan_margin: float = 1.1
    sharper_score_ratio: float = 0.8
    sharper_by: float = 0.2
    sharper_than_chosen: float = 0.1
    scan_candidates: int = 3
    confident: float = 0.5
    scan_searches: int | None = None
    keypoints: int = 5000
    sharpness_range: tuple[float, float] = (0.5, 0.8)
    spread_range: tuple[float, float] = (0.05, 0.15)
    third_range: tuple[float, float] = (0.003, 0.009)

    def __post_init__(self) -> None:
        for name in ("search_rotations", "search_points", "verify_candidates", "keypoints"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
                raise InvalidInputError(f"config.{name}: expected an integer >= 1, got {value!r}")
        if isinstance(self.scan_candidates, bool) or not isinstance(self.scan_candidates, numbers.Integral) \
                or self.scan_candidates < 0:
            raise InvalidInputError(f"config.scan_candidates: expected an integer >= 0, got {self.scan_candidates!r}")
        if self.scan_searches is not None and (isinstance(self.scan_searches, bool) or not isinstance(
                self.scan_searches, numbers.Integral) or self.scan_searches < 1):
            raise InvalidInputError(f"config.scan_searches: expected None or an integer >= 1, got {self.scan_searches!r}")
        for name in ("ambiguity_ratio", "decide_ratio", "full_cover", "sharper_score_ratio", "confident"):
            value = getattr(self, name)
            if not _is_number(value) or not 0.0 <= value <= 1.0:
                raise InvalidInputError(f"config.{name}: expected a number in [0, 1], got {value!r}")
        for name in ("confident_score", "settle_from", "sharper_by", "sharper_than_chosen"):  # above 1: never
            value = getattr(self, name)
            if not _is_number(value) or not 0.0 <= value < float("inf"):
                raise InvalidInputError(f"config.{name}: expected a finite number >= 0, got {value!r}")
        for name in ("score_width_spacings", "scan_margin"):
            value = getattr(self, name)
            if not _is_number(value) or not 0.0 < value < float("inf"):
                raise InvalidInputError(f"config.{name}: expected a finite number > 0, got {value!r}")
        for name in ("sharpness_range", "spread_range", "third_range"):
            value = getattr(self, name)
            if not (isinstance(value, (tuple, list)) and len(value) == 2 and all(map(_is_number, value))
                    and value[0] < value[1]):
                raise InvalidInputError(f"config.{name}: expected (low, high) with low < high, got {value!r}")
            object.__setattr__(self, name, (float(value[0]), float(value[1])))

    def to_dict(self) -> dict:
        """A JSON-ready dict of every field (ranges as two-element lists)."""
        return {field.name: list(value) if isinstance(value := getattr(self, field.name), tuple) else value
                for field in dataclasses.fields(self)}

    @classmethod
    def from_dict(cls, data: dict) -> "SearchConfig":
        """The config of ``data`` (as :meth:`to_dict` writes it; missing fields keep their default).

        Raises
        ------
        InvalidInputError
            On an unknown field or an invalid value.
        """
        known = {field.name for field in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise InvalidInputError(f"config: unknown field(s) {', '.join(map(repr, unknown))}; "
                                    f"known: {', '.join(sorted(known))}")
        values: dict[str, Any] = {name: tuple(value) if isinstance(value, list) else value
                                  for name, value in data.items()}
        return cls(**values)


def _is_number(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and value == value


#: The configuration :func:`esmicp.register` uses unless given another.
DEFAULT = SearchConfig()


def as_config(config) -> SearchConfig:
    """``config`` checked: None gives :data:`DEFAULT`; a :class:`SearchConfig` is kept; a dict is
    read by :meth:`SearchConfig.from_dict`; anything else raises :class:`InvalidInputError`."""
    if config is None:
        return DEFAULT
    if isinstance(config, SearchConfig):
        return config
    if isinstance(config, dict):
        return SearchConfig.from_dict(config)
    raise InvalidInputError(f"config: expected an esmicp.globalreg.config.SearchConfig or a dict, "
                            f"got {type(config).__name__}")
