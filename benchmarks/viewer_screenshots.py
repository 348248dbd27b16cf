"""Screenshots of the viewer (``esmicp.viz.view_html``) in a real browser, for docs/visualisation.md:

    python benchmarks/viewer_screenshots.py docs/images [--data ../shared/data]

Registers four inputs with ``esmicp.register``'s defaults, draws each result with
``view_html(source, target, result)`` (not registered again), writes the page to a temporary
folder and photographs it with headless chromium (Debian's ``apt-get install chromium``;
``ESMICP_CHROMIUM`` overrides its path):

- ``view_object.png``: the Stanford bunny (8,171 points), the source a copy turned 120 degrees;
- ``view_3dmatch.png``: 3DMatch redkitchen fragments 4 -> 0 (313,395 and 258,342 points, each in
  its own camera frame; ``up="-y"``);
- ``view_lidar.png``: KITTI 00 scans 1 -> 0 (124,605 and 124,668 points; a top view);
- ``view_run.png``: the built-in shape from the identity, esm beside esm-paper, with the slider
  over the iterations (``show_run=True``).

Each PNG is reduced to a palette of :data:`PALETTE_COLOURS` colours (a few tens of KB). Prints,
per input, the verdict, the points drawn, and the seconds of ``register`` and of ``view_html``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import esmicp
from esmicp import io, viz

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = Path(os.environ.get("ESMICP_SHARED_DATA", REPO.parent / "shared" / "data"))
#: The browser window photographed (pixels); the page is 720 pixels high.
WINDOW = (1100, 740)
#: Milliseconds of page time chromium lets pass before the screenshot (WebGL draws the points).
PAGE_TIME_MS = 10_000
#: Colours kept in each PNG (a palette image: the pictures stay well under 150 KB).
PALETTE_COLOURS = 96


def chromium() -> str:
    path = os.environ.get("ESMICP_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    if not path:
        sys.exit("chromium not found: apt-get install chromium (or set ESMICP_CHROMIUM)")
    return path


def screenshot(browser: str, page: Path, png: Path) -> None:
    """Open ``page`` in headless chromium (no network, no GPU: software WebGL) and save a palette
    PNG of the window."""
    from PIL import Image

    raw = page.with_suffix(".raw.png")
    subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         f"--window-size={WINDOW[0]},{WINDOW[1]}", f"--virtual-time-budget={PAGE_TIME_MS}",
         f"--screenshot={raw}", page.as_uri()],
        check=True, capture_output=True,
    )
    with Image.open(raw) as image:
        image.convert("RGB").quantize(colors=PALETTE_COLOURS).save(png, optimize=True)


def inputs(data: Path):
    """``(name, title, source, target, truth, view options)`` of the pictures."""
    bunny = io.read_points(data / "bunny" / "bun_zipper_res2.ply")
    pair = viz.moved_copy(bunny, angle_deg=120.0, seed=1, name="bun_zipper_res2.ply")
    yield ("view_object", "Stanford bunny: the source a copy turned 120 deg, registered by default",
           pair.source, pair.target, pair.T_target_source, {"up": "y"})
    kitchen = data / "real_pairs" / "3dmatch_redkitchen"
    yield ("view_3dmatch", "3DMatch redkitchen: cloud_bin_4 -> cloud_bin_0, registered by default",
           io.read_points(kitchen / "cloud_bin_4.ply"), io.read_points(kitchen / "cloud_bin_0.ply"),
           np.loadtxt(kitchen / "t00_s04" / "T_target_source.txt"), {"up": "-y"})
    kitti = data / "real_pairs" / "kitti_00"
    yield ("view_lidar", "KITTI 00: scan 1 -> scan 0 (Velodyne HDL-64), registered by default",
           io.read_points(kitti / "000001.bin", bin_columns=3), io.read_points(kitti / "000000.bin", bin_columns=3),
           np.loadtxt(kitti / "t0_s1" / "T_target_source.txt"), {})


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path, help="folder of the PNGs (docs/images)")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    args = parser.parse_args()
    browser = chromium()
    args.out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        for name, title, source, target, truth, options in inputs(args.data):
            started = time.perf_counter()
            result = esmicp.register(source, target)
            register_s = time.perf_counter() - started
            started = time.perf_counter()
            figure = viz.view_html(source, target, result, title=title, truth=truth, **options)
            view_s = time.perf_counter() - started
            page = scratch / f"{name}.html"
            viz.write_view(figure, page)
            screenshot(browser, page, args.out_dir / f"{name}.png")
            meta = figure.layout.meta
            print(f"{name}: {meta['verdicts'][0]}; drawn {meta['shown_source']:,} / {meta['shown_target']:,} "
                  f"points, {meta['camera']} view; register {register_s:.2f} s, view_html {view_s:.2f} s, "
                  f"{(args.out_dir / f'{name}.png').stat().st_size / 1000:.0f} KB")

        pair = viz.builtin_pair(points=600, angle_deg=40.0)
        figure = viz.view_html(pair.source, pair.target, show_run=True, init="identity", compare="esm-paper",
                               shown_iteration=6, truth=pair.T_target_source,
                               title="built-in shape, source turned 40 deg: esm beside esm-paper from the identity")
        page = scratch / "view_run.html"
        viz.write_view(figure, page)
        screenshot(browser, page, args.out_dir / "view_run.png")
        print(f"view_run: {'; '.join(figure.layout.meta['verdicts'])}; "
              f"{(args.out_dir / 'view_run.png').stat().st_size / 1000:.0f} KB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
