"""The benchmark lab of esmicp: the benchmark harness (:mod:`esmicp_lab.bench`, ``esmicp bench``),
the third-party registration methods it compares against (:mod:`esmicp_lab.baselines`) and the
benchmark plots.

A floor above the library: the lab imports :mod:`esmicp`; the library never imports the lab
(only the ``esmicp bench`` command loads it, when it runs). Importing this package loads nothing
else; each part is imported on its own. The scripts that write the results pages
(``benchmarks/*.py`` in the repository) import their harness from here.
"""
