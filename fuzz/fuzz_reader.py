"""Coverage-guided fuzzing of one point-cloud reader with atheris (libFuzzer for Python).

Usage (from the repository root; ``pip install atheris``)::

    python fuzz/fuzz_reader.py --target pcd-binary -max_total_time=600 [libFuzzer options] [CORPUS_DIR ...]

``--target`` is one of :data:`harness.TARGETS` (``--list`` prints them). Every input is written to
a file of the target's extension and read with :func:`esmicp.read_points`; an input that breaks
the contract of :mod:`harness` (see there) is a crash: libFuzzer stops and writes it to
``<artifact_prefix>crash-<sha1>``. Without a corpus directory, the target's seed files are used
(written to a fresh temporary directory, which libFuzzer grows). esmicp, plyfile, pypcd4 and (for
meshes) trimesh are instrumented, so coverage inside them guides the mutations.

Useful libFuzzer options: ``-max_total_time=S`` (stop after S seconds), ``-runs=N``,
``-timeout=S`` (an input taking longer is a hang, reported as a crash), ``-rss_limit_mb=M``,
``-artifact_prefix=DIR/``, ``-dict=fuzz/dicts/<format>.dict``, ``-max_len=BYTES``.
``--light`` instruments esmicp only (trimesh takes 10-30 s to instrument): for short runs.
At the end libFuzzer prints ``Done N runs in S second(s)``: the number of inputs tried.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import atheris  # noqa: E402

import harness  # noqa: E402  (not instrumented: it is the oracle, not the code under test)

_INSTRUMENTED = ["esmicp", "plyfile", "pypcd4"]
_DICTIONARIES = {"pcd": "pcd.dict", "ply": "ply.dict", "off": "off.dict", "npy": "npy.dict", "obj": "obj.dict", "stl": "stl.dict"}


def _pop_option(argv: list[str], name: str) -> str | None:
    for index, word in enumerate(argv):
        if word == name and index + 1 < len(argv):
            value = argv[index + 1]
            del argv[index : index + 2]
            return value
        if word.startswith(name + "="):
            del argv[index]
            return word.split("=", 1)[1]
    return None


def main() -> None:
    argv = list(sys.argv)
    if "--list" in argv:
        for target in harness.TARGETS.values():
            print(f"{target.name:16s} {target.extension:5s} {target.description}")
        return
    light = "--light" in argv
    if light:
        argv.remove("--light")
    name = _pop_option(argv, "--target")
    if name not in harness.TARGETS:
        sys.exit(f"fuzz_reader.py: --target must be one of {', '.join(harness.TARGETS)}, got {name!r}")
    target = harness.TARGETS[name]
    mesh = target.extension in (".off", ".obj", ".stl")

    # Instrumenting trimesh takes 10-30 s at start-up; --light (for short runs) instruments esmicp only.
    include = ["esmicp"] if light else _INSTRUMENTED + (["trimesh"] if mesh else [])
    with atheris.instrument_imports(include=include):
        import esmicp.io  # noqa: F401
        if mesh:
            import trimesh  # noqa: F401
        if target.extension == ".pcd":
            import pypcd4  # noqa: F401

    if os.environ.get("ESMICP_FUZZ_BREAK_READER"):
        # Self-test of this set-up (tests/test_fuzz_atheris.py): a reader that always fails wrongly.
        def broken_reader(path, **kwargs):
            raise KeyError("deliberately broken reader")

        esmicp.io.read_points = broken_reader

    # Where each input is written (libFuzzer ends the process without Python's clean-up, so the
    # caller may choose a folder it removes itself: ESMICP_FUZZ_WORKDIR).
    work = Path(os.environ.get("ESMICP_FUZZ_WORKDIR") or tempfile.mkdtemp(prefix=f"esmicp-fuzz-{name}-"))
    work.mkdir(parents=True, exist_ok=True)
    path = work / f"input-{os.getpid()}{target.extension}"

    def test_one_input(data: bytes) -> None:
        path.write_bytes(data)
        try:
            harness.check_file(path)
        except harness.ContractViolation as exc:
            # Print the violation with the input size: libFuzzer then saves the input.
            print(f"\nCONTRACT VIOLATION ({target.name}, {len(data)} bytes): {exc}", file=sys.stderr, flush=True)
            raise

    # Without a corpus directory, start from the seeds (libFuzzer adds what it finds there).
    if not any(not word.startswith("-") for word in argv[1:]):
        corpus = work / "corpus"
        corpus.mkdir(exist_ok=True)
        for index, data in enumerate(harness.seeds(name)):
            (corpus / f"seed{index}").write_bytes(data)
        argv.append(str(corpus))
    dictionary = HERE / "dicts" / _DICTIONARIES.get(target.extension[1:], "")
    if dictionary.is_file() and not any(word.startswith("-dict=") for word in argv):
        argv.append(f"-dict={dictionary}")
    atheris.Setup(argv, test_one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
