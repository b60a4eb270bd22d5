"""Benchmarks behind ``wara bench``."""
