"""Run every atheris target (or some) for a bounded time each and print a Markdown table.

Usage (from the repository root)::

    python fuzz/run_all.py --seconds 600                    # every target, 10 minutes each
    python fuzz/run_all.py --seconds 60 --targets npy off   # some targets
    python fuzz/run_all.py --seconds 600 --keep-going       # restart a target after a crash

Each target runs in its own process (``fuzz/fuzz_reader.py``); an input that breaks the readers'
contract is saved as ``<artifacts>/<target>/crash-<sha1>`` and its violation printed. With
``--keep-going`` a target that crashed is restarted (from its grown corpus, ``<artifacts>/<target>/corpus``)
until its time is used up, so one run can find several distinct problems. Exit status 1 if anything
was found.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import harness  # noqa: E402

_DONE = re.compile(r"Done (\d+) runs in (\d+) second")
_PROGRESS = re.compile(r"^#(\d+)\s", re.MULTILINE)
_COVERAGE = re.compile(r"cov: (\d+) ft: (\d+)")
_VIOLATION = re.compile(r"CONTRACT VIOLATION \([^)]*\): (.*)")


@dataclass
class Outcome:
    """What one target's fuzzing did."""

    target: str
    runs: int = 0
    seconds: float = 0.0
    coverage: int = 0
    features: int = 0
    crashes: list[Path] = field(default_factory=list)
    violations: list[str] = field(default_factory=list)
    failed: str | None = None  # the fuzzer itself did not run properly


def fuzz_target(
    name: str, seconds: float, artifacts: Path, *, corpus: Path | None = None, keep_going: bool = False,
    timeout_s: int = 10, rss_limit_mb: int = 2048, extra: list[str] | None = None, light: bool = False,
) -> Outcome:
    """Fuzz target ``name`` for about ``seconds`` seconds (several processes with ``keep_going``)."""
    outcome = Outcome(name)
    artifacts.mkdir(parents=True, exist_ok=True)
    corpus = corpus or artifacts / "corpus"
    corpus.mkdir(parents=True, exist_ok=True)
    if not any(corpus.iterdir()):
        for index, data in enumerate(harness.seeds(name)):
            (corpus / f"seed{index}").write_bytes(data)
    deadline = time.monotonic() + seconds
    while True:
        remaining = int(deadline - time.monotonic())
        if remaining < 1:
            break
        before = set(artifacts.glob("crash-*")) | set(artifacts.glob("timeout-*")) | set(artifacts.glob("oom-*"))
        command = [
            sys.executable, str(HERE / "fuzz_reader.py"), "--target", name, *(["--light"] if light else []),
            f"-max_total_time={remaining}", f"-timeout={timeout_s}", f"-rss_limit_mb={rss_limit_mb}",
            f"-artifact_prefix={artifacts}/", "-print_final_stats=1", *(extra or []), str(corpus),
        ]
        started = time.monotonic()
        environment = {**os.environ, "ESMICP_FUZZ_WORKDIR": str(artifacts / "work")}
        process = subprocess.run(command, capture_output=True, text=True, errors="replace", env=environment)
        outcome.seconds += time.monotonic() - started
        log = process.stdout + process.stderr
        done = _DONE.search(log)
        if done:
            outcome.runs += int(done.group(1))
        else:  # a crash ends the run without the "Done" line: take the last progress count
            counts = _PROGRESS.findall(log)
            outcome.runs += int(counts[-1]) if counts else 0
        coverage = _COVERAGE.findall(log)
        if coverage:
            outcome.coverage, outcome.features = map(int, coverage[-1])
        found = sorted((set(artifacts.glob("crash-*")) | set(artifacts.glob("timeout-*")) | set(artifacts.glob("oom-*"))) - before)
        outcome.crashes += found
        outcome.violations += _VIOLATION.findall(log)
        if process.returncode != 0 and not found:
            outcome.failed = log[-2000:]
            break
        if not found or not keep_going:
            break
    return outcome


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="fuzzing time per target (default 60)")
    parser.add_argument("--targets", nargs="*", default=list(harness.TARGETS), choices=list(harness.TARGETS))
    parser.add_argument("--artifacts", type=Path, default=None, help="where crashes go (default: a temp dir)")
    parser.add_argument("--keep-going", action="store_true", help="restart a target after a crash")
    parser.add_argument("--light", action="store_true", help="instrument esmicp only (quick start-up)")
    args = parser.parse_args(argv)
    artifacts = args.artifacts or Path(tempfile.mkdtemp(prefix="esmicp-fuzz-artifacts-"))
    print(f"| target | inputs tried | seconds | coverage (edges / features) | violations |")
    print(f"|---|---|---|---|---|")
    total_runs, found_any = 0, False
    for name in args.targets:
        outcome = fuzz_target(name, args.seconds, artifacts / name, keep_going=args.keep_going, light=args.light)
        total_runs += outcome.runs
        found_any |= bool(outcome.crashes or outcome.failed)
        summary = "; ".join(dict.fromkeys(outcome.violations)) or ("FUZZER FAILED" if outcome.failed else "none")
        print(f"| {name} | {outcome.runs} | {outcome.seconds:.0f} | {outcome.coverage} / {outcome.features} | {summary} |", flush=True)
        for crash in outcome.crashes:
            print(f"  input saved: {crash}", flush=True)
        if outcome.failed:
            print(outcome.failed, file=sys.stderr)
    print(f"\n{total_runs} inputs in total; artifacts in {artifacts}")
    return 1 if found_any else 0


if __name__ == "__main__":
    sys.exit(main())
