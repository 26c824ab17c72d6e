"""Benchmark scripts (not part of the installed package); shared pieces in :mod:`benchmarks.common`."""
