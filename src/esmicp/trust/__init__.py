"""Judging a pose: is it to be trusted?

:mod:`.uncertainty` gives a pose's covariance and the directions the data barely constrain;
:mod:`.free_space` tests a pose against the space each sensor saw empty. This package sits one
floor below the global search and the merge, which both use it; it imports neither of them.
"""
