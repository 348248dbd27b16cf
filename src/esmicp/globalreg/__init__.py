"""Global registration: a pose from anywhere, no initial guess needed.

:mod:`.search` runs the strategies and verifies every candidate the same way;
:mod:`.rotation_search` (a rotation grid, batched ESM) and :mod:`.feature_matching` (FPFH
features from :mod:`esmicp.core.features`, RANSAC / clique matching) propose the candidates.
"""

#: Two poses are distinct when their rotations differ by more than this (degrees): the runner-up
#: of an ambiguous search, and two feature hypotheses.
DISTINCT_ROTATION_DEG = 10.0
