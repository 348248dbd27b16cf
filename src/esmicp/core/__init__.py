"""Numerical building blocks shared by every method: correspondences, weighted Procrustes,
Gaussian kernels and scale estimates. Pure numpy/scipy; no I/O, no printing."""
