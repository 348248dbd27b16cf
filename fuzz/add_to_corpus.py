"""Keep a fuzzer's finding as a regression test: copy it into ``tests/corpus/<target>/``.

Usage (after the bug is fixed)::

    python fuzz/add_to_corpus.py --target npy --name deprecated-type-alias CRASH_FILE

The copy is named ``<name>--<outcome><extension>``, where ``<outcome>`` is how the input ends
now (``points`` or ``error``); ``tests/test_fuzz_corpus.py`` replays every file and checks both the
readers' contract and that outcome. Keep the files tiny (the fuzzer's inputs are; ``-minimize_crash=1``
shrinks one further).
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import harness  # noqa: E402

CORPUS = HERE.parent / "tests" / "corpus"
MAX_BYTES = 4096


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--target", required=True, choices=list(harness.TARGETS))
    parser.add_argument("--name", required=True, help="what the input exercises, e.g. huge-count")
    parser.add_argument("input", type=Path)
    args = parser.parse_args(argv)
    if not re.fullmatch(r"[a-z0-9][a-z0-9-]*", args.name):
        parser.error("--name: lower-case letters, digits and dashes only")
    data = args.input.read_bytes()
    if len(data) > MAX_BYTES:
        parser.error(f"{args.input}: {len(data)} bytes; minimise it below {MAX_BYTES} first")
    extension = harness.TARGETS[args.target].extension
    with tempfile.TemporaryDirectory() as directory:
        probe = Path(directory) / f"probe{extension}"
        probe.write_bytes(data)
        outcome = harness.check_file(probe)  # raises while the bug is still there
    destination = CORPUS / args.target / f"{args.name}--{outcome}{extension}"
    destination.parent.mkdir(parents=True, exist_ok=True)
    if destination.exists():
        parser.error(f"{destination} already exists: choose another --name")
    shutil.copyfile(args.input, destination)
    print(destination)
    return 0


if __name__ == "__main__":
    sys.exit(main())
