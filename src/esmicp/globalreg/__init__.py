"""Global registration: a pose from anywhere, no initial guess needed.

:mod:`.search` runs the strategies and verifies every candidate the same way;
:mod:`.rotation_search` (a rotation grid, batched ESM) and :mod:`.feature_matching` (FPFH
features from :mod:`esmicp.core.features`, RANSAC / clique matching) propose the candidates. Every
tuned value is in :class:`.config.SearchConfig`.
"""
