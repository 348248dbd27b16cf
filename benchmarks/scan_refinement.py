"""Local refinement on the real scan pairs: ``esm``, ``esm-plane``, ``icp`` against Open3D
point-to-plane ICP and small_gicp GICP, same starts, same iteration cap, one run; writes the
section "Refinement on scans" of ``docs/scans-refinement.md`` (``--doc``) and prints it.

Starts, per pair of ``pairs.csv``:

- ``perturbed``: the ground truth moved by a seeded rigid offset about the placed source's centroid
  (random axis and direction): LiDAR 5-10 deg and 0.2-0.5 m (uniform), 3DMatch 5 deg and 0.1 m;
  ``--seeds`` seeds per pair (``SeedSequence(seed, spawn_key=(pair, k))``).
- ``global``: the start the default global search gives
  (:func:`esmicp.globalreg.search.global_estimate`, ``"auto"``, in :func:`esmicp.register`'s
  working frame), once per pair.

Methods: ``esmicp.register(source, target, method=m, init=start, max_iterations=N)`` for ``esm``,
``esm-plane``, ``icp`` (every other default); ``open3d-icp-p2l`` and ``small-gicp`` adapters from
the same start with ``max_iterations=N`` and the voxel their documentation recommends for the
kind (0.05 m indoor, 0.3 m LiDAR; normals / covariances and small_gicp's downsampling use it).
``global+esm`` / ``global+esm-plane`` (global starts only): the whole
``esmicp.register(source, target, method=m, rng=seed)``, the same global search and then ``m`` as
``register`` runs it after a search; their time includes the search. ``global+esm`` is
``register()`` with every default, and runs by default: handed the search's pose as a given
start (``init=start``), ``esm`` begins in its coarse phase and without the ``esm-plane`` stage that
``register()`` runs on a large source after its own search, so the two rows can differ.
Errors in the pair's frame, success by the kind's criteria (:mod:`esmicp_lab.bench.real_pairs`).
Only the registration call is timed (esmicp: ``result.runtime_s``; peers: their
``runtime_s``, normals and covariances included); one untimed warm-up per method first.

    nice -n 5 python benchmarks/scan_refinement.py --seeds 3 --rows rows.jsonl --doc docs/scans-refinement.md \
        --picture docs/images/scans-refinement.png      # the page's notes kept (--notes FILE: replaced)
    python benchmarks/scan_refinement.py --from-rows rows.jsonl --picture docs/images/scans-refinement.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from esmicp_lab.bench.scan_refinement import OURS, PEERS, markdown, picture, rows_for, write_section

DEFAULT_FOLDER = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_pairs"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--folder", type=Path, default=DEFAULT_FOLDER)
    parser.add_argument("--seeds", type=int, default=3, help="perturbed starts per pair")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-iterations", type=int, default=50)
    parser.add_argument("--methods", default=",".join((*OURS, *PEERS, "global+esm")))
    parser.add_argument("--no-global", action="store_true", help="skip the global-search starts")
    parser.add_argument("--rows", type=Path, help="write the rows as JSON lines here")
    parser.add_argument("--from-rows", type=Path, nargs="+", help="only rebuild the tables from these rows")
    parser.add_argument("--doc", type=Path, help="write the section into this Markdown file")
    parser.add_argument("--notes", type=Path, help="Markdown appended to the section (the decision); default: "
                        "the notes the page already has after its tables")
    parser.add_argument("--picture", type=Path, help="draw the page's picture from the rows (PNG, replaced if it "
                        "exists; needs matplotlib): right results per kind of pair, start and method")
    args = parser.parse_args()
    command = ("python benchmarks/scan_refinement.py --seeds {} --seed {} --max-iterations {}{}"
               .format(args.seeds, args.seed, args.max_iterations, " --no-global" if args.no_global else ""))
    if args.from_rows:
        rows = [json.loads(line) for path in args.from_rows for line in path.read_text().splitlines() if line.strip()]
    else:
        def progress(row):
            print(f"{row['pair']:28s} {row['start']:9s} {row['seed']} {row['method']:15s} "
                  f"{'ok' if row['success'] else 'no'} {row['rotation_deg']:7.3f} deg {row['translation_m']:7.3f} m "
                  f"{row['time_s']:6.2f} s", flush=True)

        rows = list(rows_for(args.folder, args.seeds, args.seed, args.max_iterations, args.methods.split(","),
                             not args.no_global, progress))
        if args.rows:
            args.rows.write_text("".join(json.dumps(row) + "\n" for row in rows))
    section = markdown(rows, command, args.max_iterations)
    print(section)
    if args.doc:
        write_section(args.doc, section, args.notes.read_text(encoding="utf-8") if args.notes else None)
    if args.picture:
        print(picture(rows, args.picture))


if __name__ == "__main__":
    main()
