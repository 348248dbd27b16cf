"""Sparse clouds: how often ``RegistrationResult.trusted`` is wrong when the clouds are too sparse
to resolve the pose.

Each shape of a ModelNet40 folder is sampled twice, independently, to N points (N = 21 ... 1,000);
the source sample is turned by a random rotation of 30 degrees; the pair is registered from the
identity and with the global search (``esmicp.register``, every other option default,
``workers=1``). A result is right when its placement is within 2% of the shape's diagonal up to
the shape's symmetry (:func:`esmicp.metrics.up_to_symmetry_success`, on the whole shape).
``--min-coincident`` sets :attr:`esmicp.trust.policy.TrustPolicy.min_coincident` for the run (to
compare values; the library's default is what ships).

    python benchmarks/sparse_trust.py --folder modelnet40                 # the 12 shapes (choice)
    python benchmarks/sparse_trust.py --folder modelnet40_extra           # the 69 (confirmation)
    python benchmarks/sparse_trust.py --folder modelnet40 --min-coincident 3

Prints a Markdown table per start: per N, trials, right, trusted, trusted and wrong.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

import esmicp
from esmicp.config import RegistrationConfig
from esmicp.trust.policy import TrustPolicy
from esmicp.metrics import random_rotation, up_to_symmetry_success

DATA = Path(os.environ.get("ESMICP_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
SIZES = (21, 40, 60, 100, 150, 300, 1000)


def trials(folder: Path, config: RegistrationConfig):
    """(size, start, right, trusted) of every registration, with ``config``."""
    for number, path in enumerate(sorted(folder.glob("*/*.txt"))):
        shape = np.loadtxt(path, delimiter=",")[:, :3]
        diagonal = float(np.linalg.norm(np.ptp(shape, axis=0)))
        for size in SIZES:
            rng = np.random.default_rng(number * 100 + size)
            count = min(size, len(shape))
            first = shape[rng.choice(len(shape), count, replace=False)]
            second = shape[rng.choice(len(shape), count, replace=False)]
            truth = np.eye(4)
            truth[:3, :3] = random_rotation(rng, 30.0)
            source = first @ truth[:3, :3]  # target = truth applied to source
            for start in ("identity", None):
                result = esmicp.register(source, second, init=start, workers=1, config=config)
                right = up_to_symmetry_success(shape @ truth[:3, :3], result.transformation, truth, diagonal)
                yield size, start or "global", bool(right), result.trusted


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", default="modelnet40", help="a ModelNet40 folder of ../shared/data")
    parser.add_argument("--min-coincident", type=int, help="TrustPolicy.min_coincident for this run")
    args = parser.parse_args()
    policy = TrustPolicy() if args.min_coincident is None else TrustPolicy(min_coincident=args.min_coincident)
    rows = list(trials(DATA / args.folder, RegistrationConfig(trust=policy)))
    print(f"{args.folder}, min_coincident = {policy.min_coincident}\n")
    for start in ("identity", "global"):
        print(f"| {start}: points | trials | right | trusted | trusted and wrong |\n|---|---|---|---|---|")
        for size in SIZES:
            chosen = [row for row in rows if row[0] == size and row[1] == start]
            trusted = [row for row in chosen if row[3]]
            print(f"| {size} | {len(chosen)} | {sum(row[2] for row in chosen)} | {len(trusted)} | "
                  f"{sum(not row[2] for row in trusted)} |")
        print()


if __name__ == "__main__":
    main()
