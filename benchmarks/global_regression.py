"""A fixed sample of global registrations, recorded row by row, so that two versions or settings of
the global search can be compared on the same trials (``--compare``); ``benchmarks/global_doc.py``
makes the results pages' tables of one run.

Sets (``--sets``, comma-separated):

``objects``
    the five object protocols (:data:`esmicp_lab.bench.protocols.PROTOCOLS`) on the 12 ModelNet40
    shapes of ``modelnet40/``, ``--trials`` trials each (round-robin over the shapes).
``halves``
    ModelNet40 halves cut to 70% and 50% (:func:`esmicp_lab.bench.real_pairs.partial_trial`),
    ``--trials`` each; success up to symmetry on the whole half.
``real``
    every pair of ``real_pairs/pairs.csv`` as recorded, and the 3DMatch pairs turned.
``crops``
    the 3DMatch pairs cropped to 25% and 15% overlap (:func:`esmicp_lab.bench.real_pairs.crop_to_overlap`),
    turned.
``extra-halves``, ``extra-objects``
    as ``halves`` / the ``outliers-60`` protocol, on the shapes of ``modelnet40_extra/`` (a
    confirmation set: nothing is tuned on it).
``kitchen``
    frame pairs 10-50 frames apart of the kitchen walk (``sequences/redkitchen_seq01_every10``),
    as recorded: a confirmation set for the scan thresholds (success: rotation < 5 deg and
    translation < 0.1 m, the depth camera's walk).
``kitchen-far``
    frame pairs 60-150 frames apart of the same walk, the source turned about its camera by a
    random rotation (``--kitchen-pairs`` per gap, same success). Some share little or no surface:
    each row also records ``truth_overlap``, the overlap score
    (:func:`esmicp.globalreg.scan.overlap_score`) of the ground-truth pose refined from itself, so
    that "no pose was there to find" can be told apart from "the search chose the wrong one".
    Registered with ``range_images=True`` (both frames stay range images): each row records
    ``free_space`` (the free-space test, :func:`esmicp.trust.free_space.free_space_fraction`)
    and ``trusted_without_free_space``.

Each registration is ``esmicp.register(source, target, rng=seed)`` with every default (``workers=1``)
but for ``kitchen-far``'s ``range_images=True``.
Writes one JSON line per registration (pose, success, rotation error against the truth (degrees; on
the object sets right up to symmetry may still be far from it), converged, confidence, trusted, ambiguous,
runner_up_ratio, where the pose came from, time) to ``--out``. ``--compare BEFORE.jsonl`` instead
compares two such files: the rows whose pose moved, whose success changed, and the totals
(successes, trusted and trusted-and-wrong, time). With ``--peer NAME[,NAME...]`` each row also runs
those baselines right after esmicp on the same clouds (the voxel their documentation gives for the
data: 0.05 m indoor, 0.3 m LiDAR, their object default on the ModelNet40 sets), and ``--compare``
and ``global_doc.py groups`` report the median of the per-row time ratios esmicp / peer: a ratio
measured in one process holds under a machine's changing load, which absolute times do not.

    python benchmarks/global_regression.py --out /tmp/runs/a.jsonl
    python benchmarks/global_regression.py --out /tmp/runs/b.jsonl --compare /tmp/runs/a.jsonl
    python benchmarks/global_regression.py --sets real,crops --peer kiss-matcher-gicp,kiss-matcher-icp --out /tmp/runs/peer.jsonl
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import esmicp
from esmicp_lab.bench.protocols import PROTOCOLS, make_trials
from esmicp_lab.bench.real_pairs import (
    criteria_for, crop_to_overlap, estimate_in_pair_frame, load_pair, pair_errors, partial_trial, read_pairs,
    turn_source,
)
from esmicp_lab.bench.sequences import read_frame, read_poses
from esmicp.core.correspondence import NearestNeighbors
from esmicp.core.procrustes import bounding_box_diagonal, rotation_angle
from esmicp.core.keypoints import Keypoints
from esmicp.globalreg.config import DEFAULT
from esmicp.globalreg.scan import overlap_score
from esmicp.metrics import rotation_error_deg, strict_success, up_to_symmetry_success

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SETS = ("objects", "halves", "real", "crops", "extra-halves", "extra-objects", "kitchen", "kitchen-far")
KITCHEN_GAPS = (10, 20, 30, 40, 50)
KITCHEN_FAR_GAPS = tuple(range(60, 160, 10))


def _clouds(folder: Path) -> dict[str, np.ndarray]:
    return {path.stem: esmicp.read_points(path) for path in sorted(folder.glob("*/*.txt"))}


def _seed(*key) -> int:
    return int(np.random.SeedSequence(list(key)).generate_state(1)[0])


#: ``--peer``: the baselines of :data:`esmicp_lab.baselines.BASELINES` run right after each
#: registration, in this order, on the same clouds, judged the same way (empty: none).
PEERS: tuple[str, ...] = ()


def _peer(name: str, source, target, seed: int, judge, voxel: float | None) -> dict:
    """One peer's time (seconds) and verdict on one row (a ``peers`` entry); its voxel: the one
    its documentation gives for the data (``voxel``; None: the adapter's object default)."""
    from esmicp_lab.baselines import get_baseline

    started = time.perf_counter()
    result = get_baseline(name)(source, target, voxel_size=voxel, rng=seed)
    elapsed = time.perf_counter() - started
    verdict = judge(np.asarray(result.transformation, dtype=np.float64))
    return {"time_s": elapsed, "success": verdict["success"]}


def peer_times(row: dict) -> dict[str, dict]:
    """A row's peers, name -> ``{"time_s", "success"}`` (also read from the single-peer fields
    ``peer``, ``peer_time_s``, ``peer_success`` of older files)."""
    if "peers" in row:
        return row["peers"]
    if "peer_time_s" in row:
        return {row["peer"]: {"time_s": row["peer_time_s"], "success": row["peer_success"]}}
    return {}


def _record(name: str, source, target, seed: int, judge, peer_voxel: float | None = None, **options) -> dict:
    started = time.perf_counter()
    result = esmicp.register(source, target, rng=seed, workers=1, **options)
    elapsed = time.perf_counter() - started
    row = {"row": name, "seed": seed, "time_s": elapsed, "init": result.init, "converged": result.converged,
           "iterations": result.num_iterations, "confidence": result.confidence, "trusted": result.trusted,
           "ambiguous": result.ambiguous,
           "runner_up_ratio": result.runner_up_ratio, "candidates": result.global_candidates,
           "transformation": result.transformation.tolist(),
           "degenerate": len(result.degenerate_directions)}
    if options.get("range_images"):
        row["free_space"] = result.free_space
        row["trusted_without_free_space"] = not result.doubts(ignore=("free space",))
    row.update({key: value for key, value in result.to_dict().items() if key.startswith("std_")})
    row.update(judge(result.transformation))
    if PEERS:
        row["peers"] = {name: _peer(name, source, target, seed, judge, peer_voxel) for name in PEERS}
    return row


def object_rows(data: Path, trials: int, seed: int, folder: str = "modelnet40", protocols=PROTOCOLS):
    clouds = _clouds(data / folder)
    for protocol in protocols:
        for trial in make_trials(protocol, clouds, trials, seed):
            pivot = trial.source.mean(axis=0)

            def judge(estimate, trial=trial, pivot=pivot):
                truth = trial.T_target_source
                return {"success": bool(up_to_symmetry_success(trial.clean_source, estimate, truth, trial.diagonal)),
                        "strict": bool(strict_success(estimate, truth, trial.diagonal, pivot=pivot)),
                        "rotation_error_deg": rotation_error_deg(estimate, truth)}

            yield _record(f"{folder}/{protocol}/{trial.seed[1]}/{trial.cloud}", trial.source, trial.target,
                          _seed(seed, 0, PROTOCOLS.index(protocol), trial.seed[1]), judge)


def half_rows(data: Path, trials: int, seed: int, folder: str = "modelnet40"):
    clouds = _clouds(data / folder)
    names = list(clouds)
    for number, keep in enumerate((0.7, 0.5)):
        for index in range(trials):
            name = names[index % len(names)]
            rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1, number, index)))
            trial = partial_trial(clouds[name], keep, rng)
            diagonal = bounding_box_diagonal(trial.target)

            def judge(estimate, trial=trial, diagonal=diagonal):
                return {"success": bool(up_to_symmetry_success(trial.source_half, estimate, trial.T_target_source,
                                                               diagonal)),
                        "overlap": trial.overlap,
                        "rotation_error_deg": rotation_error_deg(estimate, trial.T_target_source)}

            yield _record(f"{folder}/half-{round(100 * keep)}/{index}/{name}", trial.source, trial.target,
                          _seed(seed, 1, number, index), judge)


def _pair_judge(truth, moved_by, kind):
    criteria = criteria_for(kind)

    def judge(estimate):
        rotation, translation = pair_errors(estimate_in_pair_frame(estimate, moved_by), truth)
        return {"success": bool(criteria.success(rotation, translation)), "rotation_error_deg": rotation,
                "translation_error": translation}

    return judge


def real_rows(data: Path, seed: int):
    for number, pair in enumerate(read_pairs(data / "real_pairs")):
        source, target, truth = load_pair(pair, bin_columns=3)
        voxel = criteria_for(pair.kind).voxel_m
        yield _record(f"real/{pair.name}/as-recorded", source, target, _seed(seed, 2, number),
                      _pair_judge(truth, None, pair.kind), voxel)
        if pair.kind == "3DMatch":
            rng = np.random.default_rng(_seed(seed, 3, number))
            turned, _, moved_by = turn_source(source, truth, rng)
            yield _record(f"real/{pair.name}/turned", turned, target, _seed(seed, 3, number),
                          _pair_judge(truth, moved_by, pair.kind), voxel)


def crop_rows(data: Path, seed: int, crops: int = 1):
    pairs = [pair for pair in read_pairs(data / "real_pairs") if pair.kind == "3DMatch"]
    cases = [(overlap_number, overlap, crop) for overlap_number, overlap in enumerate((0.25, 0.15))
             for crop in range(crops)]
    for number, pair in enumerate(pairs):
        source, target, truth = load_pair(pair, bin_columns=3)
        for overlap_number, overlap, crop in cases:
            rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(number, overlap_number, crop)))
            cropped = crop_to_overlap(source, target, truth, overlap, rng)
            turned, _, moved_by = turn_source(cropped.source, truth, rng)
            key = (number, overlap_number) if crop == 0 else (number, overlap_number, crop)
            row = _record(f"crop/{pair.name}/{round(100 * overlap)}" + (f"/{crop}" if crop else ""), turned,
                          cropped.target, _seed(seed, 4, *key), _pair_judge(truth, moved_by, "3DLoMatch"),
                          criteria_for("3DLoMatch").voxel_m)
            row["overlap"] = cropped.source_overlap
            yield row


KITCHEN = Path("sequences") / "redkitchen_seq01_every10"
#: The peer's voxel on the kitchen's depth frames: the indoor one of the 3DMatch criteria (metres).
INDOOR_VOXEL = criteria_for("3DMatch").voxel_m


def _kitchen_pairs(data: Path, gaps, pairs_per_gap: int):
    """``(gap index, gap, start, target name, source name, target, source, T_target_source)`` of
    ``pairs_per_gap`` pairs ``gap`` frames apart, their starts spread evenly over the walk."""
    folder = data / KITCHEN
    poses = read_poses(folder)
    names = sorted(poses)
    for gap_index, gap in enumerate(gaps):
        steps = gap // 10
        for start in np.linspace(0, len(names) - 1 - steps, pairs_per_gap).round().astype(int):
            target_name, source_name = names[start], names[start + steps]
            truth = np.linalg.inv(poses[target_name]) @ poses[source_name]
            yield (gap_index, gap, int(start), target_name, source_name, read_frame(folder, target_name),
                   read_frame(folder, source_name), truth)


def _kitchen_success(rotation: float, translation: float) -> bool:
    return rotation < 5.0 and translation < 0.1


def kitchen_rows(data: Path, seed: int, pairs_per_gap: int = 3):
    for gap_index, gap, start, target_name, source_name, target, source, truth in _kitchen_pairs(
            data, KITCHEN_GAPS, pairs_per_gap):

        def judge(estimate, truth=truth):
            rotation, translation = pair_errors(estimate, truth)
            return {"success": _kitchen_success(rotation, translation), "rotation_error_deg": rotation,
                    "translation_error": translation}

        yield _record(f"kitchen/gap{gap}/{target_name}-{source_name}", source, target,
                      _seed(seed, 5, gap_index, start), judge, INDOOR_VOXEL)


def kitchen_far_rows(data: Path, seed: int, pairs_per_gap: int = 3):
    for gap_index, gap, start, target_name, source_name, target, source, truth in _kitchen_pairs(
            data, KITCHEN_FAR_GAPS, pairs_per_gap):
        rng = np.random.default_rng(_seed(seed, 6, gap_index, start))
        # turned about the sensor (the origin), so that both clouds stay range images: the
        # free-space test (range_images=True) is measured on every pair
        turned, turned_truth, moved_by = turn_source(source, truth, rng, about=np.zeros(3))
        refined = esmicp.register(turned, target, init=turned_truth, workers=1).transformation
        keypoints = Keypoints.of(turned, target, NearestNeighbors(target, workers=1).spacing(),
                                 DEFAULT.keypoints, DEFAULT.scan.keypoint.min_voxel_spacings)
        truth_overlap = overlap_score(refined, keypoints, workers=1)

        def judge(estimate, truth=truth, moved_by=moved_by, truth_overlap=truth_overlap):
            rotation, translation = pair_errors(estimate_in_pair_frame(estimate, moved_by), truth)
            return {"success": _kitchen_success(rotation, translation), "rotation_error_deg": rotation,
                    "translation_error": translation, "truth_overlap": truth_overlap}

        yield _record(f"kitchen-far/gap{gap}/{target_name}-{source_name}", turned, target,
                      _seed(seed, 7, gap_index, start), judge, INDOOR_VOXEL, range_images=True)


def compare(before_path: Path, after_path: Path) -> str:
    def load(path):
        return {row["row"]: row for row in map(json.loads, path.read_text().splitlines())}

    before, after = load(before_path), load(after_path)
    lines, moved = [], 0
    for name, old in before.items():
        new = after.get(name)
        if new is None:
            continue
        a, b = np.array(old["transformation"]), np.array(new["transformation"])
        turn = float(np.degrees(rotation_angle(a[:3, :3].T @ b[:3, :3])))
        shift = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
        if turn > 1e-6 or shift > 1e-9 * max(1.0, float(np.abs(a[:3, 3]).max())) or old["success"] != new["success"] \
                or old["trusted"] != new["trusted"]:
            moved += 1
            lines.append(f"{name}: pose moved {turn:.3g} deg / {shift:.3g}; success {old['success']} -> "
                         f"{new['success']}; confidence {old['confidence']:.3f} -> {new['confidence']:.3f}; "
                         f"trusted {old['trusted']} -> {new['trusted']}")
    groups: dict[str, list] = {}
    for name in after:
        if name in before:
            groups.setdefault("/".join(name.split("/")[:2]), []).append(name)
    lines.append("")
    lines.append("| group | rows | success before | success after | trusted (wrong) before | trusted (wrong) after "
                 "| time after / before | median time after / before |")
    lines.append("|---|---|---|---|---|---|---|---|")

    def trusted(rows, names):
        return (f"{sum(bool(rows[n]['trusted']) for n in names)} "
                f"({sum(bool(rows[n]['trusted']) and not rows[n]['success'] for n in names)})")

    for group, names in groups.items():
        ok_before = sum(before[n]["success"] for n in names)
        ok_after = sum(after[n]["success"] for n in names)
        ratio = sum(after[n]["time_s"] for n in names) / max(sum(before[n]["time_s"] for n in names), 1e-12)
        median = (float(np.median([after[n]["time_s"] for n in names]))
                  / max(float(np.median([before[n]["time_s"] for n in names])), 1e-12))
        lines.append(f"| {group} | {len(names)} | {ok_before} | {ok_after} | {trusted(before, names)} "
                     f"| {trusted(after, names)} | {ratio:.2f} | {median:.2f} |")
    peers = list(dict.fromkeys(name for n in after for name in peer_times(after[n])))
    if peers:
        lines.append("")
        lines.append("| group | rows | peer | peer success | esmicp success after | median of per-row time ratios "
                     "esmicp / peer: before | after |")
        lines.append("|---|---|---|---|---|---|---|")
        for group, names in groups.items():
            for peer in peers:
                rows = [n for n in names if peer in peer_times(after[n])]
                if not rows:
                    continue

                def ratio(run, rows=rows, peer=peer):
                    known = [run[n]["time_s"] / peer_times(run[n])[peer]["time_s"] for n in rows
                             if peer in peer_times(run[n])]
                    return f"{float(np.median(known)):.2f}" if known else "-"

                lines.append(f"| {group} | {len(rows)} | {peer} "
                             f"| {sum(bool(peer_times(after[n])[peer]['success']) for n in rows)} "
                             f"| {sum(bool(after[n]['success']) for n in rows)} | {ratio(before)} | {ratio(after)} |")
    ratios = [after[n]["runner_up_ratio"] for n in after if after[n]["runner_up_ratio"] is not None]
    lines.append(f"\nrows moved: {moved} of {len(after)}; largest runner_up_ratio after: "
                 f"{max(ratios) if ratios else None}")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--sets", default="objects,halves,real,crops")
    parser.add_argument("--trials", type=int, default=12, help="trials per object protocol / per half keep")
    parser.add_argument("--crops", type=int, default=1, help="seeded crops per 3DMatch pair and overlap")
    parser.add_argument("--kitchen-pairs", type=int, default=3, help="kitchen frame pairs per gap")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path)
    parser.add_argument("--compare", type=Path, help="a JSON-lines file of an earlier run to compare --out with "
                        "(an existing --out is compared as it is, not run again)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing --out")
    parser.add_argument("--peer", help="baselines (esmicp_lab.baselines, comma-separated) run after each registration "
                        "on the same clouds, at the voxel their documentation gives for the data (e.g. "
                        "kiss-matcher-gicp,kiss-matcher-icp): --compare and global_doc.py groups then report the "
                        "median per-row time ratio to each")
    args = parser.parse_args()
    global PEERS
    PEERS = tuple(name for name in (args.peer or "").split(",") if name)
    if PEERS:
        from esmicp_lab.baselines import BASELINES

        unknown = [name for name in PEERS if name not in BASELINES]
        if unknown:
            parser.error(f"--peer: unknown baseline(s) {', '.join(unknown)}")
    if args.out is not None and args.out.exists() and not args.compare and not args.force:
        parser.error(f"{args.out} exists: pass --force to overwrite it, or --compare to compare it")
    if args.out is not None and not (args.compare and args.out.exists()):
        args.out.parent.mkdir(parents=True, exist_ok=True)
        makers = {
            "objects": lambda: object_rows(args.data, args.trials, args.seed),
            "halves": lambda: half_rows(args.data, args.trials, args.seed),
            "real": lambda: real_rows(args.data, args.seed),
            "crops": lambda: crop_rows(args.data, args.seed, args.crops),
            "extra-halves": lambda: half_rows(args.data, args.trials, args.seed, "modelnet40_extra"),
            "extra-objects": lambda: object_rows(args.data, args.trials, args.seed, "modelnet40_extra",
                                                 ("outliers-60",)),
            "kitchen": lambda: kitchen_rows(args.data, args.seed, args.kitchen_pairs),
            "kitchen-far": lambda: kitchen_far_rows(args.data, args.seed, args.kitchen_pairs),
        }
        with open(args.out, "w", encoding="utf-8") as handle:
            for name in args.sets.split(","):
                for row in makers[name]():
                    handle.write(json.dumps(row) + "\n")
                    handle.flush()
                    print(f"{row['row']}: {'ok' if row['success'] else 'FAIL'} confidence {row['confidence']:.2f} "
                          f"{row['time_s']:.2f}s", flush=True)
    if args.compare is not None:
        print(compare(args.compare, args.out))


if __name__ == "__main__":
    main()
