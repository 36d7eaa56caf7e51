"""Experiments over many runs: the paper's tables, sweeps, spectra and benchmarks."""
