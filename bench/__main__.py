"""``python -m bench``: list the benchmarks (each is its own module with --help)."""

BENCHES = {
    "bench.paper": "the paper's Section V experiment (make bench; --quick: make bench-quick): every task and "
                   "strategy, statistics, references, cost, figures, docs/results.md",
    "bench.report": "docs/results.md (--docs) and the README table (--readme) from bench/results/paper.json",
    "bench.figures": "redraw Figures 5 and 7 (episodes and env steps) from a results folder",
    "bench.cost": "bytes per round; chief time per round for 4, 16, 64 workers over Mosquitto and amqtt",
    "bench.latency": "state-to-action latency through the real-time bridge loop, per broker",
    "bench.reset": "swing-up reset success over pendulum damping x rig spread x Coulomb friction",
    "bench.exploration": "how often SAC's untrained policy reaches MountainCarContinuous-v0's goal, per noise colour",
    "bench.loop_cost": "per-tick cost of the bridge loop (SPI transfer, sense, publish, wait, write)",
    "bench.sim2real": "sim-to-real: lab rigs from scratch, warm-started from an ideal or a randomised pretrain, "
                      "zero-shot; the last rig's episodes, balance steps and rig minutes",
    "bench.ood": "out of distribution (also python -m bench.sim2real ood): rigs off lab one parameter at a time; "
                 "self-test, resets, zero-shot and fine-tune, with and without identification",
    "bench.staleness": "idle seconds per rig on qube-local, one rig resetting 3x slower, max staleness 0 and 1",
    "bench.soak": "16 workers over Mosquitto to the end: broker and chief memory over time, round latency",
    "bench.scale": "flat chief against a root fed by edge chiefs, 4 to 1,024 simulated devices (make scale)",
    "bench.stragglers": "one worker in 16 ten times slower: k-of-n rounds (--quorum) against waiting for it "
                        "(--edges E: every run tiered)",
    "bench.matrix": "every task x learner x strategy over MQTT and in process, M = 2: does each run what it says "
                    "and pass its audit",
    "bench.tune": "tuning runs of a learner's preset (--set KEY=VALUE) on tuning seeds only, in process; JSONL",
}

if __name__ == "__main__":
    print("benchmarks (run with python -m <name> --help):")
    for name, what in BENCHES.items():
        print(f"  {name:<15} {what}")
