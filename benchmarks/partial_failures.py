"""Why the default register() fails on the partial-overlap protocol: a decomposition per trial.

For each trial of ``esmicp bench --datasets partial-overlap`` (same seeds, same objects), runs the
default ``register`` and, when it fails (placement up to symmetry >= 2% of the diagonal), asks:

- *candidates*: is any pose proposed by the global search's strategies (the rotation search's
  verified contenders, the scan strategy's poses, the feature hypotheses) within 5% of the
  diagonal of the truth (up to symmetry)? If none, the pose was never proposed.
- *overlap*: refined by the same short ESM at one target spacing, does the true pose put more of
  the clouds on each other (mean of the two Gaussian overlap scores, source on target and target
  on source, width two spacings, the decision's score) than the returned pose? If not, no
  overlap-based verification can prefer the truth.

Prints a Markdown section; figures are measured in the run:

    nice -n 5 python benchmarks/partial_failures.py --trials 24 > /tmp/partial-failures.md
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import esmicp
from esmicp_lab.bench.real_pairs import partial_trial
from esmicp_lab.bench.scans import PARTIAL_KEEPS, _modelnet_clouds, _seed_of
from esmicp.core.correspondence import NearestNeighbors
from esmicp.core.procrustes import bounding_box_diagonal, to_matrix
from esmicp.globalreg import search
from esmicp.globalreg.config import DEFAULT
from esmicp.globalreg.rotation_search import batched_esm, gaussian_overlap_score
from esmicp.metrics import symmetric_placement_error

SUCCESS = 0.02
NEAR = 0.05


def both_ways_overlap(source, target, transformation, spacing) -> float:
    """The decision's score of ``transformation`` after 10 ESM steps at one target spacing."""
    rotations, translations, forward = batched_esm(
        source, NearestNeighbors(target), transformation[None, :3, :3], transformation[None, :3, 3],
        iterations=10, sigma_floor=spacing, fine_iterations=10,
    )
    refined = to_matrix(rotations[0], translations[0])
    backward, _ = NearestNeighbors(source).query((target - refined[:3, 3]) @ refined[:3, :3])
    width = DEFAULT.verification.score_width_spacings * spacing
    return float(0.5 * (gaussian_overlap_score(forward, width)[0] + gaussian_overlap_score(backward, width)))


def candidates(source, target, seed) -> dict[str, list[np.ndarray]]:
    """Every strategy's proposals, as the default ``"auto"`` search would make them."""
    index = NearestNeighbors(target)
    spacing = index.spacing()
    work = search._Workspace(source, target, np.random.default_rng(seed), index, index, spacing,
                             DEFAULT.verification.score_width_spacings * spacing)
    proposed = search._rotation_candidates(work)
    verified = search._verify(work, proposed, ["rotation-search"] * len(proposed))
    return {
        "rotation-search": list(verified.transformations),
        "scan": list(search._scan(source, target, index, spacing).transformations),
        "features": search._feature_candidates(work),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[1] / ".." / "shared" / "data"))
    parser.add_argument("--trials", type=int, default=24)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    clouds = _modelnet_clouds(Path(args.data))
    names = list(clouds)
    lines = ["| protocol | trials | successes | failures: truth never proposed | failures: proposed, but the returned pose "
             "overlaps more | failures: proposed and the truth overlaps more | failures where the returned pose overlaps "
             "more than the truth (proposed or not) |", "|---|---|---|---|---|---|---|"]
    details = []
    for number, keep in enumerate(PARTIAL_KEEPS):
        counts = dict(ok=0, never=0, proposed_lower=0, proposed_higher=0, lower=0)
        for index in range(args.trials):
            name = names[index % len(names)]
            rng = np.random.default_rng(np.random.SeedSequence(args.seed, spawn_key=(1, number, index)))
            trial = partial_trial(clouds[name], keep, rng)
            seed = _seed_of(args.seed, 1, number, index)
            diagonal = bounding_box_diagonal(trial.target)

            def error(transformation, trial=trial, diagonal=diagonal):
                return symmetric_placement_error(trial.source, transformation, trial.T_target_source) / diagonal

            result = esmicp.register(trial.source, trial.target, rng=seed)
            if error(result.transformation) < SUCCESS:
                counts["ok"] += 1
                continue
            found = {strategy: sum(error(pose) < NEAR for pose in poses)
                     for strategy, poses in candidates(trial.source, trial.target, seed).items()}
            spacing = NearestNeighbors(trial.target).spacing()
            truth_score = both_ways_overlap(trial.source, trial.target, trial.T_target_source, spacing)
            returned_score = both_ways_overlap(trial.source, trial.target, result.transformation, spacing)
            proposed = any(found.values())
            lower = truth_score <= returned_score
            counts["lower"] += lower
            if not proposed:
                counts["never"] += 1
            else:
                counts["proposed_lower" if lower else "proposed_higher"] += 1
            details.append(
                f"| partial-{round(100 * keep)} | {index} | {name} | {trial.overlap:.2f} | {error(result.transformation):.3f} | "
                f"{result.init} | {', '.join(f'{k} {v}' for k, v in found.items())} | {truth_score:.3f} | {returned_score:.3f} |"
            )
        failures = args.trials - counts["ok"]
        lines.append(f"| partial-{round(100 * keep)} | {args.trials} | {counts['ok']} | {counts['never']} | "
                     f"{counts['proposed_lower']} | {counts['proposed_higher']} | {counts['lower']}/{failures} |")
    print("\n".join(lines))
    print()
    print("Each failure: the placement error (fraction of the diagonal, up to symmetry), where the returned pose came "
          "from, how many proposals of each strategy lie within 5% of the truth, and the both-ways overlap score of the "
          "truth and of the returned pose (each refined the same way).\n")
    print("| protocol | trial | object | overlap | error | returned by | proposals near the truth | truth's score | "
          "returned pose's score |")
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(details))


if __name__ == "__main__":
    main()
