"""Judging a pose: is it to be trusted?

:mod:`.confidence` measures how sharply two clouds coincide where they overlap under a pose;
:mod:`.uncertainty` gives a pose's covariance and the directions the data barely constrain;
:mod:`.free_space` tests a pose against the space each sensor saw empty; :mod:`.policy` holds the
bars a result must pass to be trusted and the values of these measures; :mod:`.judge` judges a
registered pose with them in one call (:func:`~esmicp.trust.judge.judge`, a
:class:`~esmicp.trust.judge.Verdict`). This package sits one floor below the global search and the merge, which
both use it; it imports neither of them.
"""
