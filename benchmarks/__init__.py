"""Benchmarks: environment, loader, training and evaluation throughput (`make bench`), each writing JSON."""
