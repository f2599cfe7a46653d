"""Where one DVFB update spends its time: ms per phase of ``agent.update`` (docs/methods.md §7.2).

    python bench/update_phases.py                       # hidden256 config, 1 and 2 torch threads
    python bench/update_phases.py --config small --threads 2

Phases: ``training_z`` (z sampling and mixing), ``_explore`` (RND, NCE and exploration-critic
steps, including the CE reward), ``_fb_step`` (FB, auxiliary-Q and orthonormality losses and
their optimiser step), ``_actor_step``, ``soft_update_targets``; the rest of ``update`` (the next
action and B forwards) is ``update - sum(phases)``. Medians over ``--updates`` updates after 5
warm-up updates, on a fixed walker-sized replay (learner.py's). Prints only.

It answers whether the two independent branches of the update (exploration and FB) would gain
from running concurrently on one core each instead of one after the other on two cores: compare
``max(_explore, _fb_step)`` at 1 thread with ``_explore + _fb_step`` at 2 threads.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import learner  # noqa: E402

PHASES = ("training_z", "_explore", "_fb_step", "_actor_step", "soft_update_targets")


def measure(config: str, threads: int, updates: int) -> dict[str, float]:
    torch.set_num_threads(threads)
    obs_dim, action_dim = learner.env_dims("walker")
    agent, replay = learner.build("dvfb", learner.model_config(config, "dvfb"), torch.device("cpu"), obs_dim,
                                  action_dim)
    needs = agent.replay_needs()
    times: dict[str, list[float]] = defaultdict(list)
    for name in PHASES:  # time each phase through an instance attribute wrapping the method
        method = getattr(agent, name)

        def timed(*args, _method=method, _name=name, **kwargs):
            start = time.perf_counter()
            out = _method(*args, **kwargs)
            times[_name].append(1e3 * (time.perf_counter() - start))
            return out

        setattr(agent, name, timed)
    for i in range(5 + updates):
        if i == 5:
            times.clear()
        batch = needs.sample(replay)
        start = time.perf_counter()
        agent.update(batch)
        times["update"].append(1e3 * (time.perf_counter() - start))
    return {name: statistics.median(values) for name, values in times.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--config", default="hidden256",
                        choices=[c for c in learner.CONFIGS if learner.config_applies(c, "dvfb")])
    parser.add_argument("--threads", default="1,2", help="comma-separated torch thread counts")
    parser.add_argument("--updates", type=int, default=20)
    args = parser.parse_args(argv)
    rows = {int(t): measure(args.config, int(t), args.updates) for t in args.threads.split(",")}
    columns = ("update",) + PHASES
    print(f"# DVFB update phases, config {args.config} ({learner.CONFIG_NOTES[args.config]}), ms (median)")
    print("| threads | " + " | ".join(columns) + " | rest |")
    print("|---:|" + "---:|" * (len(columns) + 1))
    for threads, m in rows.items():
        rest = m["update"] - sum(m[p] for p in PHASES)
        print(f"| {threads} | " + " | ".join(f"{m[c]:.1f}" for c in columns) + f" | {rest:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
