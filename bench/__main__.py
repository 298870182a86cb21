"""``python -m bench``: list the benchmarks (each is its own module with --help)."""

BENCHES = {
    "bench.policies": "episodes until all workers solve, per federation policy and seed (JSON + PNG)",
    "bench.latency": "state-to-action and read-to-motor latency through the real-time bridge loop, per broker",
    "bench.reset": "swing-up reset success over pendulum damping x rig spread x Coulomb friction",
    "bench.loop_cost": "per-tick cost of the bridge loop (SPI transfer, sense, publish, wait, write)",
    "bench.soak": "16 workers over Mosquitto to the end: broker and chief memory over time, round latency",
}

if __name__ == "__main__":
    print("benchmarks (run with python -m <name> --help):")
    for name, what in BENCHES.items():
        print(f"  {name:<18} {what}")
