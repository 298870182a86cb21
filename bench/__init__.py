"""Benchmarks and the paper's experiments; each writes JSON (and a PNG) into bench/results/."""
