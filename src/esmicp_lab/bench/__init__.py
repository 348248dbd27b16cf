"""``esmicp bench``: the benchmark suite (the paper's protocol and tables, the honest protocols,
every method run the same way), serial or on Dask, resumable. See ``docs/bench.md``.

The suite is a thin layer over the library: trials from :mod:`esmicp_lab.bench.protocols` (and
:mod:`.paper`, :mod:`.trials`), errors from :mod:`esmicp.metrics`, methods from
:func:`esmicp.register` and :mod:`esmicp_lab.baselines`.
"""

from .config import BenchConfig, RunOptions
from .results import read_rows
from .runner import BenchOutcome, Interrupted, run_bench, write_tables

__all__ = ["BenchConfig", "BenchOutcome", "Interrupted", "RunOptions", "read_rows", "run_bench", "write_tables"]
