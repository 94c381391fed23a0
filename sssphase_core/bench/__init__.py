"""Benchmarks: error against run time, each compared to a baseline measured in the same run."""
