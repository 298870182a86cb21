"""``python -m bench``: list the benchmarks (each is its own module with --help)."""

BENCHES = {
    "bench.policies": "episodes until all workers solve, per federation policy and seed (JSON + PNG)",
}

if __name__ == "__main__":
    print("benchmarks (run with python -m <name> --help):")
    for name, what in BENCHES.items():
        print(f"  {name:<18} {what}")
