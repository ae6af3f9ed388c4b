"""Benchmarks (not part of the test suite): python -m bench.accuracy, python -m bench.speed."""
