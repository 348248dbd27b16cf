"""Child process of the ``go-icp`` adapter: ``python -m esmicp_lab.baselines._goicp_child IN OUT``.

Reads the normalised clouds and settings from the ``.npz`` file IN, runs py-goicp (which prints its
progress to stdout: the parent discards it) and writes the optimal rotation, translation and the
registration's time to the ``.npz`` file OUT. Not part of the public API.
"""

from __future__ import annotations

import sys
import time

import numpy as np


def main(argv: list[str]) -> int:
    from py_goicp import POINT3D, ROTNODE, TRANSNODE, GoICP

    source_path, result_path = argv
    with np.load(source_path) as inputs:
        model, data = inputs["model"], inputs["data"]
        mse_threshold = float(inputs["mse_threshold"])
        dt_size = int(inputs["dt_size"])
        dt_factor = float(inputs["dt_factor"])
        trim_fraction = float(inputs["trim_fraction"])
        translation_half_width = float(inputs["translation_half_width"])

    goicp = GoICP()
    goicp.loadModelAndData(
        len(model), [POINT3D(*map(float, p)) for p in model], len(data), [POINT3D(*map(float, p)) for p in data]
    )
    goicp.MSEThresh = mse_threshold
    goicp.trimFraction = trim_fraction
    goicp.doTrim = trim_fraction > 0.0
    goicp.setDTSizeAndFactor(dt_size, dt_factor)
    rotation_node = ROTNODE()
    rotation_node.a = rotation_node.b = rotation_node.c = -np.pi
    rotation_node.w = 2.0 * np.pi
    translation_node = TRANSNODE()
    translation_node.x = translation_node.y = translation_node.z = -translation_half_width
    translation_node.w = 2.0 * translation_half_width
    goicp.setInitNodeRot(rotation_node)
    goicp.setInitNodeTrans(translation_node)

    start = time.perf_counter()
    goicp.BuildDT()
    goicp.Register()
    runtime = time.perf_counter() - start
    np.savez(
        result_path,
        rotation=np.array(goicp.optimalRotation(), dtype=np.float64),
        translation=np.array(goicp.optimalTranslation(), dtype=np.float64).reshape(3),
        runtime_s=runtime,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
