"""Mistakes ``mypy --strict`` must report (tests/test_typing.py): each line marked ``# error``
is one, so the public names are typed, not ``Any``."""

from __future__ import annotations

import numpy as np

import esmicp

points = np.zeros((10, 3))
result = esmicp.register(points, points, method=3)  # error
esmicp.register(points, points, tolerence=1e-6)  # error
size: str = result.num_iterations  # error
esmicp.write_points("out.ply", points, overwrite="yes")  # error
esmicp.register(points, points, method="esm-fast")  # error
esmicp.register(points, points, init="globl")  # error
