"""The ESM-ICP paper's protocol and the transforms printed in its tables and figures.

The paper's trial: the target is a cloud; the source is the *same points in the same order*
moved by ``G``: roll, pitch, yaw each uniform in ``[-pi, pi]``, composed ``R = Rz(yaw) Ry(pitch)
Rx(roll)`` (the paper's sampling: Euler angles drawn uniformly are NOT uniform rotations), and
each translation component uniform in ``[-range, range]`` (cloud units: ModelNet objects are about
2 units across, so ranges of 100 and 1000 put the source 50-500 object sizes away). Optionally
30 % / 60 % of the source points get the paper's noise (:func:`esmicp_lab.bench.protocols.paper_noise`,
scaled by the object's half-diagonal) in the object's frame, before the move. The truth is
``T_target_source = G^-1``.

Every transform here is ``T_target_source`` (``target ~= source @ R.T + t``) unless named ``G``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from esmicp.core.procrustes import apply, bounding_box_diagonal, rigid_inverse, to_matrix
from .protocols import Trial, paper_noise

#: Fraction of noisy source points of each paper protocol (the 1,000-transform ones included).
PAPER_NOISE_FRACTIONS = {"paper": 0.0, "paper-noise-30": 0.3, "paper-noise-60": 0.6,
                         "paper-1000": 0.0, "paper-1000-noise-30": 0.3}

#: Iterations the paper's tables give every method.
PAPER_ITERATIONS = 40

#: The paper's translation ranges (cloud units).
PAPER_TRANSLATION_RANGES = (1.0, 100.0, 1000.0)

#: The paper's two 1,000-transform tables (ESM-ICP against KISS-Matcher), as groups of trials:
#: ``(table id in paper_tables.json, ModelNet40 class, protocol)``. Each group is
#: :data:`PAPER_1000_TRIALS` trials of the paper's motion (Euler angles uniform in [-pi, pi],
#: translations uniform in [-1000, 1000]) on that one object, the noisy one with
#: :func:`esmicp_lab.bench.protocols.paper_noise` on 30 % of the source, as ``paper-noise-30`` does.
PAPER_1000_GROUPS = (
    ("kiss-matcher-1000", "airplane", "paper-1000"),
    ("kiss-matcher-1000", "person", "paper-1000"),
    ("kiss-matcher-1000", "stool", "paper-1000"),
    ("kiss-matcher-1000-stool-outliers-30", "stool", "paper-1000-noise-30"),
)
#: Trials per group, iterations and translation range of the 1,000-transform tables.
PAPER_1000_TRIALS = 1000
PAPER_1000_ITERATIONS = 100
PAPER_1000_TRANSLATION_RANGE = 1000.0


def euler_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (radians), the paper's composition."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def paper_motion_parameters(rng: np.random.Generator, translation_range: float) -> tuple[np.ndarray, np.ndarray]:
    """The draws of :func:`paper_motion`: ``(roll, pitch, yaw)`` each uniform in [-pi, pi], then
    ``(tx, ty, tz)`` each uniform in ``[-translation_range, translation_range]``."""
    angles = rng.uniform(-np.pi, np.pi, size=3)
    translation = rng.uniform(-translation_range, translation_range, size=3)
    return angles, translation


def paper_motion(rng: np.random.Generator, translation_range: float) -> np.ndarray:
    """The paper's random ``G`` (4x4): Euler angles uniform in [-pi, pi], ZYX; translation
    components uniform in ``[-translation_range, translation_range]``
    (:func:`paper_motion_parameters`)."""
    (roll, pitch, yaw), translation = paper_motion_parameters(rng, translation_range)
    return to_matrix(euler_zyx(roll, pitch, yaw), translation)


def paper_trial(
    protocol: str, cloud: np.ndarray, moved_by: np.ndarray, rng: np.random.Generator, *, name: str = "", seed=None
) -> Trial:
    """A paper trial on ``cloud`` (the target) with the source = the cloud, noisy per
    ``protocol`` (:data:`PAPER_NOISE_FRACTIONS`), moved by ``moved_by``; truth ``moved_by^-1``.

    The source keeps the target's point order (index-aligned), as in the paper.
    """
    cloud = np.asarray(cloud, dtype=np.float64)
    fraction = PAPER_NOISE_FRACTIONS[protocol] if protocol in PAPER_NOISE_FRACTIONS else 0.0
    clean = None
    source_object = cloud
    if fraction > 0:
        source_object, corrupted = paper_noise(cloud, fraction, rng, 0.5 * bounding_box_diagonal(cloud))
        clean = ~corrupted
    source = apply(moved_by, source_object)
    truth = rigid_inverse(np.asarray(moved_by, dtype=np.float64))
    return Trial(
        protocol=protocol, cloud=name, source=_frozen(source), target=_frozen(cloud),
        T_target_source=_frozen(truth), seed=seed, diagonal=bounding_box_diagonal(cloud),
        clean=None if clean is None else _frozen_bool(clean),
    )


def _frozen(array) -> np.ndarray:
    array = np.array(array, dtype=np.float64, copy=True)
    array.setflags(write=False)
    return array


def _frozen_bool(array) -> np.ndarray:
    array = np.array(array, dtype=bool, copy=True)
    array.setflags(write=False)
    return array


@dataclass(frozen=True)
class PaperCase:
    """One transform printed in the paper (a table row's setting or a figure's).

    ``euler`` is ``(roll, pitch, yaw, tx, ty, tz)`` (radians, cloud units) of ``G``; ``figure_file``
    names a 4x4 ``G`` in ``<data>/esm_icp_paper`` instead. ``cloud`` is the ModelNet40 class.
    """

    name: str
    cloud: str
    noise_fraction: float = 0.0
    euler: tuple[float, ...] | None = None
    figure_file: str | None = None

    def motion(self, data_dir) -> np.ndarray:
        """``G``, the transform that moves the target's points onto the source."""
        if self.euler is not None:
            roll, pitch, yaw, tx, ty, tz = self.euler
            return to_matrix(euler_zyx(roll, pitch, yaw), np.array([tx, ty, tz]))
        from esmicp.io import read_transform
        from pathlib import Path

        return read_transform(Path(data_dir) / "esm_icp_paper" / self.figure_file)


#: The paper's printed transforms: its tables' settings, then its figures'.
PAPER_CASES = (
    PaperCase("airplane", "airplane", euler=(2.58175, -2.16765, 0.711617, 11.0585, 16.2285, -17.0047)),
    PaperCase("person", "person", euler=(-2.56814, 1.15753, 1.92252, 0.0635863, 0.0883894, 0.0158466)),
    PaperCase("vase-outliers-30", "vase", 0.3, euler=(-2.51358, 0.916596, 1.10051, 105.383, -53.3576, -16.489)),
    PaperCase("bottle-outliers-60", "bottle", 0.6, euler=(2.82862, -0.905772, 1.88224, -62.3639, -31.1694, -56.1162)),
    PaperCase("fig1-airplane", "airplane", figure_file="fig1_airplane_transform.txt"),
    PaperCase("fig1-person", "person", figure_file="fig1_person_transform.txt"),
    PaperCase("fig-piano", "piano", figure_file="fig_piano_transform.txt"),
)


def case_protocol(case: PaperCase) -> str:
    """The paper protocol whose noise ``case`` uses."""
    return {0.0: "paper", 0.3: "paper-noise-30", 0.6: "paper-noise-60"}[case.noise_fraction]
