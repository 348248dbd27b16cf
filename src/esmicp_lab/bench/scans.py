"""The scan benchmark: every global method on the real pairs of a folder (as recorded, turned, and
on request cropped to a low overlap) and on the partial-overlap object protocol, in one run, one JSON row per (trial, method).

Methods (:data:`SCAN_METHODS`): ``esm-global`` (``esmicp.register(source, target, rng=seed)``,
every default, no voxel), and the peers with the voxel their documentation recommends for the
pair's kind (:class:`~esmicp_lab.bench.real_pairs.Criteria`; 0.05 m indoor, 0.3 m LiDAR), each
refined by point-to-point ICP: ``kiss-matcher-icp``, ``open3d-ransac-fpfh-icp`` and ``fgr-icp``
(Open3D FGR, then the same ICP as RANSAC's: 2 voxels, 64 iterations); and ``kiss-matcher-gicp``,
KISS-Matcher refined by small_gicp's GICP as both projects' documentation runs them. On the partial-overlap
objects the peers get their object default (1/40 of the target's diagonal), as in the other
object protocols. Each method is warmed up once (untimed) on a small cloud, so imports are not
counted; only the registration call is timed. Methods take turns pair by pair.

The ``cropped`` variant (not run unless asked for) crops pair ``k`` by a plane slab
(:func:`~esmicp_lab.bench.real_pairs.crop_to_overlap`) so that ``CROPPED_OVERLAP`` of the kept source
lies on the kept target (3DLoMatch's range); its rows report the overlap measured after the crop.

Seeds: the turned variant of pair ``k`` draws its rotation from ``SeedSequence(seed,
spawn_key=(0, k))``; the cropped variant its plane from ``SeedSequence(seed, spawn_key=(2, k))``; partial trial ``i`` at keep fraction number ``j`` from ``SeedSequence(seed,
spawn_key=(1, j, i))``; every method gets the same per-trial seed.
"""

from __future__ import annotations

import json
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from esmicp.errors import InvalidInputError
from esmicp.metrics import rotation_error_deg, strict_success, translation_error, up_to_symmetry_success
from .real_pairs import crop_to_overlap, estimate_in_pair_frame, load_pair, pair_errors, partial_trial, read_pairs, turn_source

__all__ = [
    "PARTIAL_KEEPS",
    "CROPPED_OVERLAP",
    "DEFAULT_VARIANTS",
    "SCAN_METHODS",
    "VARIANTS",
    "ScanBenchConfig",
    "partial_markdown",
    "real_pairs_markdown",
    "run_scan_bench",
]

#: The global methods of the scan benchmark.
SCAN_METHODS = ("esm-global", "kiss-matcher-icp", "kiss-matcher-gicp", "open3d-ransac-fpfh-icp", "fgr-icp")
#: Variants of each real pair, and those run unless others are asked for.
VARIANTS = ("as-recorded", "turned", "cropped")
DEFAULT_VARIANTS = ("as-recorded", "turned")
#: The ``cropped`` variant keeps this fraction of the source on the target (3DLoMatch: 10-30%).
CROPPED_OVERLAP = 0.2
#: Fractions of each half the partial-overlap protocol keeps.
PARTIAL_KEEPS = (0.7, 0.5)
#: ICP iterations after FGR (the other peers' default).
FGR_ICP_ITERATIONS = 64


@dataclass(frozen=True)
class ScanBenchConfig:
    """What the scan benchmark runs.

    ``real_pairs_dir``: a folder with a ``pairs.csv`` (None: no real pairs); ``partial_trials``:
    trials per keep fraction on the ModelNet40 objects of ``data_dir`` (0: none).
    """

    real_pairs_dir: str | None
    data_dir: str = ""
    methods: tuple[str, ...] = SCAN_METHODS
    variants: tuple[str, ...] = DEFAULT_VARIANTS
    partial_keeps: tuple[float, ...] = PARTIAL_KEEPS
    partial_trials: int = 24
    partial_points: int = 2000
    seed: int = 0
    bin_columns: int | None = 3
    pairs: tuple[str, ...] = field(default=())  # only these pair names (dataset/pair); empty: all

    def __post_init__(self):
        for name in self.methods:
            if name not in SCAN_METHODS:
                raise InvalidInputError(f"methods: {name!r} is not a scan-benchmark method; choose from {', '.join(SCAN_METHODS)}")
        for name in self.variants:
            if name not in VARIANTS:
                raise InvalidInputError(f"variants: unknown variant {name!r}; choose from {', '.join(VARIANTS)}")
        if not self.methods:
            raise InvalidInputError("methods: give at least one method")


def run_global(name: str, source, target, voxel: float | None, seed: int):
    """Run one global method; returns ``(T_target_source, notes, ambiguous, confidence, trusted)``:
    esmicp's ``ambiguous`` flag, overlap ``confidence`` (0-1, :attr:`esmicp.RegistrationResult.confidence`)
    and ``trusted`` verdict, None for the peers, which report none of them."""
    if name == "esm-global":
        from esmicp.api import register

        result = register(source, target, rng=seed)
        note = f"init={result.init} fitness={result.fitness:.3f} iterations={result.num_iterations}"
        return result.transformation, note, bool(result.ambiguous), result.confidence, bool(result.trusted)
    from .. import baselines

    if name == "fgr-icp":
        from ..baselines._common import o3d_cloud, refine, require, voxel_for

        coarse = baselines.get_baseline("fgr")(source, target, voxel_size=voxel, rng=seed)
        o3d = require("open3d", "open3d")
        used = voxel_for(np.asarray(target, dtype=np.float64), voxel)  # the voxel FGR used
        fine, note = refine(o3d, o3d_cloud(o3d, np.asarray(source, dtype=np.float64)),
                            o3d_cloud(o3d, np.asarray(target, dtype=np.float64)), coarse.transformation, used,
                            FGR_ICP_ITERATIONS, "point-to-point")
        return fine, f"{coarse.notes}; {note}", None, None, None
    result = baselines.get_baseline(name)(source, target, voxel_size=voxel, rng=seed)
    return np.asarray(result.transformation, dtype=np.float64), result.notes, None, None, None


def _timed(name, source, target, voxel, seed) -> dict:
    start = time.perf_counter()
    try:
        estimate, notes, ambiguous, confidence, trusted = run_global(name, source, target, voxel, seed)
    except Exception as exc:  # noqa: BLE001 - a method's failure is a row, not the end of the run
        return {"status": "failed", "reason": f"{type(exc).__name__}: {exc}", "time_s": time.perf_counter() - start}
    return {"status": "ok", "time_s": time.perf_counter() - start, "estimate": np.asarray(estimate, dtype=np.float64),
            "notes": notes, "ambiguous": ambiguous, "confidence": confidence, "trusted": trusted}


def _warm_up(methods) -> None:
    from esmicp.shapes import asymmetric_shape

    cloud = asymmetric_shape(500, np.random.default_rng(0))
    for name in methods:
        _timed(name, cloud, cloud, None, 0)


def _seed_of(*key) -> int:
    return int(np.random.SeedSequence(list(key)).generate_state(1)[0])


def real_pair_rows(config: ScanBenchConfig, emit) -> None:
    """Run every method on every pair and variant; ``emit(row)`` each row as it is made."""
    from .protocols import scan_overlap

    folder = Path(config.real_pairs_dir)
    pairs = read_pairs(folder)
    if config.pairs:
        unknown = sorted(set(config.pairs) - {p.name for p in pairs})
        if unknown:
            raise InvalidInputError(f"pairs: {', '.join(unknown)} not in {folder / 'pairs.csv'}")
        pairs = [p for p in pairs if p.name in config.pairs]
    for index, pair in enumerate(pairs):
        source, target, truth = load_pair(pair, config.bin_columns)
        overlap = scan_overlap(source, target, truth)
        criteria = pair.criteria
        for variant in config.variants:
            moved_by = None
            trial_source, trial_target, trial_truth, trial_overlap = source, target, truth, overlap
            if variant == "turned":
                rng = np.random.default_rng(np.random.SeedSequence(config.seed, spawn_key=(0, index)))
                trial_source, trial_truth, moved_by = turn_source(source, truth, rng)
            elif variant == "cropped":
                rng = np.random.default_rng(np.random.SeedSequence(config.seed, spawn_key=(2, index)))
                cropped = crop_to_overlap(source, target, truth, CROPPED_OVERLAP, rng)
                trial_source, trial_target, trial_overlap = cropped.source, cropped.target, cropped.source_overlap
            seed = _seed_of(config.seed, 0, index, VARIANTS.index(variant))
            for method in config.methods:
                row = {"protocol": "real-pairs", "pair": pair.name, "kind": pair.kind, "variant": variant,
                       "method": method, "seed": seed, "points_source": len(trial_source),
                       "points_target": len(trial_target), "overlap": trial_overlap, "voxel": criteria.voxel_m if method != "esm-global" else None,
                       "criteria": [criteria.rotation_deg, criteria.translation_m],
                       "initial_rotation_deg": rotation_error_deg(np.eye(4), trial_truth)}
                outcome = _timed(method, trial_source, trial_target, row["voxel"], seed)
                estimate = outcome.pop("estimate", None)
                row.update(outcome)
                if estimate is not None:
                    rotation, translation = pair_errors(estimate_in_pair_frame(estimate, moved_by), truth)
                    row.update(rotation_error_deg=rotation, translation_error_m=translation,
                               success=criteria.success(rotation, translation), transformation=estimate.tolist())
                else:
                    row.update(rotation_error_deg=None, translation_error_m=None, success=False)
                emit(row)


def _modelnet_clouds(data_dir: Path) -> dict:
    from esmicp import io

    files = sorted((data_dir / "modelnet40").glob("*/*.txt"))
    if not files:
        raise InvalidInputError(f"partial-overlap protocol: no ModelNet40 objects in {data_dir / 'modelnet40'} "
                                "(give the shared data folder with --data)")
    return {path.stem: io.read_points(path) for path in files}


def partial_rows(config: ScanBenchConfig, emit) -> None:
    """The partial-overlap protocol: ``partial_trials`` trials per keep fraction, round-robin
    over the ModelNet40 objects; every method on each trial."""
    from .datasets import default_data_dir

    data_dir = Path(config.data_dir) if config.data_dir else default_data_dir()
    clouds = _modelnet_clouds(data_dir)
    names = list(clouds)
    for number, keep in enumerate(config.partial_keeps):
        for index in range(config.partial_trials):
            name = names[index % len(names)]
            rng = np.random.default_rng(np.random.SeedSequence(config.seed, spawn_key=(1, number, index)))
            trial = partial_trial(clouds[name], keep, rng, config.partial_points)
            seed = _seed_of(config.seed, 1, number, index)
            diagonal = float(np.linalg.norm(trial.target.max(axis=0) - trial.target.min(axis=0)))
            pivot = trial.source.mean(axis=0)
            for method in config.methods:
                row = {"protocol": f"partial-{round(100 * keep)}", "cloud": name, "trial_index": index,
                       "method": method, "seed": seed, "keep": keep, "overlap": trial.overlap,
                       "points_source": len(trial.source), "points_target": len(trial.target)}
                outcome = _timed(method, trial.source, trial.target, None, seed)
                estimate = outcome.pop("estimate", None)
                row.update(outcome)
                if estimate is not None:
                    truth = trial.T_target_source
                    row.update(
                        rotation_error_deg=rotation_error_deg(estimate, truth),
                        translation_error=translation_error(estimate, truth, pivot),
                        success_strict=strict_success(estimate, truth, diagonal, pivot=pivot),
                        # Up to the object's symmetry (the whole half placed), and judged on
                        # the kept points alone (see PartialTrial).
                        success=up_to_symmetry_success(trial.source_half, estimate, truth, diagonal),
                        success_kept_points=up_to_symmetry_success(trial.source, estimate, truth, diagonal),
                    )
                else:
                    row.update(rotation_error_deg=None, translation_error=None, success_strict=False, success=False,
                               success_kept_points=False)
                emit(row)


def run_scan_bench(config: ScanBenchConfig, rows_path: Path | None = None, progress=None) -> list[dict]:
    """Run the scan benchmark; each row is appended to ``rows_path`` (JSON lines) as it is made.
    ``progress(row)`` is called after each row."""
    rows = []
    handle = open(rows_path, "w", encoding="utf-8") if rows_path is not None else None

    def emit(row):
        rows.append(row)
        if handle is not None:
            handle.write(json.dumps(row) + "\n")
            handle.flush()
        if progress is not None:
            progress(row)

    try:
        _warm_up(config.methods)
        if config.real_pairs_dir is not None:
            real_pair_rows(config, emit)
        if config.partial_trials:
            partial_rows(config, emit)
    finally:
        if handle is not None:
            handle.close()
    return rows


# ---- tables ---------------------------------------------------------------------------------------

METHOD_LABELS = {"esm-global": "esmicp default", "kiss-matcher-icp": "KISS-Matcher + ICP",
                 "kiss-matcher-gicp": "KISS-Matcher + small_gicp GICP",
                 "open3d-ransac-fpfh-icp": "Open3D RANSAC+FPFH + ICP", "fgr-icp": "FGR + ICP"}


def _methods(rows) -> list[str]:
    present = {row["method"] for row in rows}
    return [m for m in SCAN_METHODS if m in present]


def _cell(row) -> str:
    if row is None:
        return "-"
    if row["status"] != "ok":
        return f"failed ({row['time_s']:.2f} s)"
    mark = "**ok**" if row["success"] else "no"
    return f"{mark} {row['rotation_error_deg']:.2f}° {row['translation_error_m']:.3f} m {row['time_s']:.2f} s"


def real_pairs_markdown(rows: list[dict]) -> str:
    """Per pair and variant: each method's success, rotation / translation error and time; then
    per variant and kind: successes, median errors, median time and the time ratios to each peer
    of :data:`RATIO_REFERENCES` run on the same pairs."""
    rows = [r for r in rows if r["protocol"] == "real-pairs"]
    if not rows:
        return ""
    methods = _methods(rows)
    lines = ["| pair | kind | overlap | variant | " + " | ".join(METHOD_LABELS[m] for m in methods) + " |",
             "|---|---|---|---|" + "---|" * len(methods)]
    keys = []
    for row in rows:
        key = (row["pair"], row["variant"])
        if key not in keys:
            keys.append(key)
    index = {(r["pair"], r["variant"], r["method"]): r for r in rows}
    for pair, variant in keys:
        first = next(r for r in rows if r["pair"] == pair and r["variant"] == variant)
        cells = [_cell(index.get((pair, variant, m))) for m in methods]
        lines.append(f"| {pair} | {first['kind']} | {first['overlap']:.2f} | {variant} | " + " | ".join(cells) + " |")
    lines += ["", "Cells: success, rotation error, translation error, time of the registration call.", ""]
    lines += _summary(rows, methods, lambda r: (r["kind"].replace("-coarse-GT", ""), r["variant"]),
                      "kind, variant", "translation_error_m", " m")
    return "\n".join(lines) + "\n"


#: The peers every method's time is divided by in the summary tables (those present in the rows):
#: KISS-Matcher refined by Open3D's ICP and by small_gicp's GICP, the fastest pipeline measured.
RATIO_REFERENCES = ("kiss-matcher-icp", "kiss-matcher-gicp")


def _summary(rows, methods, group_of, group_label, translation_key, unit) -> list[str]:
    groups = []
    for row in rows:
        if group_of(row) not in groups:
            groups.append(group_of(row))
    references = [m for m in RATIO_REFERENCES if m in methods]
    header = "".join(f" time / {METHOD_LABELS[m]} (median of per-trial ratios) |" for m in references)
    lines = [f"| {group_label} | method | success | median rotation error | median translation error | "
             f"median time |{header}", "|---|---|---|---|---|---|" + "---|" * len(references)]
    for group in groups:
        members = [r for r in rows if group_of(r) == group]
        times = {m: {_trial_key(r): r["time_s"] for r in members if r["method"] == m} for m in references}
        for method in methods:
            mine = [r for r in members if r["method"] == method]
            ok = [r for r in mine if r["status"] == "ok"]
            wins = sum(bool(r["success"]) for r in mine)
            rot = statistics.median(r["rotation_error_deg"] for r in ok) if ok else float("nan")
            tra = statistics.median(r[translation_key] for r in ok) if ok else float("nan")
            time_s = statistics.median(r["time_s"] for r in mine)
            cells = []
            for reference in references:
                ratios = [r["time_s"] / times[reference][_trial_key(r)] for r in mine
                          if times[reference].get(_trial_key(r))]
                cells.append(f"{statistics.median(ratios):.2f}" if ratios and method != reference else "-")
            label = " / ".join(str(g) for g in group) if isinstance(group, tuple) else str(group)
            lines.append(f"| {label} | {METHOD_LABELS[method]} | {wins}/{len(mine)} ({100 * wins / len(mine):.0f}%) | "
                         f"{rot:.2f}° | {tra:.3g}{unit} | {time_s:.2f} s |" + "".join(f" {c} |" for c in cells))
    return lines


def _trial_key(row):
    return (row.get("pair"), row.get("variant"), row.get("cloud"), row.get("trial_index"), row["protocol"])


#: :func:`partial_markdown` also counts the successes on the trials overlapping by at least this
#: fraction, where a registration is expected to succeed (below it a cut can leave two parts that
#: barely overlap).
COUNTED_OVERLAP = 0.3


def partial_markdown(rows: list[dict]) -> str:
    """Per keep fraction: each method's success up to the object's symmetry, strict and on the kept
    points (see :class:`~esmicp_lab.bench.real_pairs.PartialTrial`), median errors and time, the
    overlap the trials had, and the success on those overlapping by at least
    :data:`COUNTED_OVERLAP`."""
    rows = [r for r in rows if r["protocol"].startswith("partial-")]
    if not rows:
        return ""
    methods = _methods(rows)
    lines = []
    for protocol in sorted({r["protocol"] for r in rows}, reverse=True):
        members = [r for r in rows if r["protocol"] == protocol and r["method"] == methods[0]]
        overlaps = [r["overlap"] for r in members]
        lines.append(f"- {protocol}: {len(members)} trials, overlap (fraction of the source on the target's part) "
                     f"median {statistics.median(overlaps):.2f}, range {min(overlaps):.2f}-{max(overlaps):.2f}")
    lines.append("")
    lines += _summary(rows, methods, lambda r: r["protocol"], "protocol", "translation_error", "")
    lines.append("")
    lines.append("Success here is up to the object's symmetry: the source's whole half, before its cut, placed "
                 "within 2% of the diagonal of where the truth puts it, as point sets. Stricter criteria: strict "
                 "(rotation < 2°, translation < 2% of the diagonal), and up to symmetry judged on the kept points "
                 "only (which fails a pose turned by the object's symmetry when the cut does not share it):")
    lines.append("")
    lines.append("| protocol | criterion | " + " | ".join(METHOD_LABELS[m] for m in methods) + " |")
    lines.append("|---|---|" + "---|" * len(methods))
    for protocol in sorted({r["protocol"] for r in rows}, reverse=True):
        members = [r for r in rows if r["protocol"] == protocol]
        for label, key in (("strict", "success_strict"), ("kept points", "success_kept_points")):
            lines.append(f"| {protocol} | {label} | " + " | ".join(_success_counts(members, methods, key)) + " |")
    lines.append("")
    lines.append(f"Success up to symmetry on the trials whose overlap is at least {COUNTED_OVERLAP:.0%} (a cut "
                 "can leave two parts that barely overlap):")
    lines.append("")
    lines.append("| protocol | trials | " + " | ".join(METHOD_LABELS[m] for m in methods) + " |")
    lines.append("|---|---|" + "---|" * len(methods))
    for protocol in sorted({r["protocol"] for r in rows}, reverse=True):
        counted = [r for r in rows if r["protocol"] == protocol and r["overlap"] >= COUNTED_OVERLAP]
        cells = _success_counts(counted, methods, "success")
        lines.append(f"| {protocol} | {len(counted) // len(methods)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _success_counts(rows: list[dict], methods: list[str], key: str) -> list[str]:
    """``successes/trials`` of each of ``methods`` among ``rows``, a success being a true ``key``."""
    cells = []
    for method in methods:
        mine = [r for r in rows if r["method"] == method]
        cells.append(f"{sum(bool(r[key]) for r in mine)}/{len(mine)}")
    return cells
