"""Milliseconds per agent update of the exact preset configs (not a test).

One ``agent.update`` on a fixed walker-sized batch (obs 24, action 6), median over several updates,
for FB and DVFB by default (``--agents``: a comma list of registered agents, or ``all``) at the
``small`` preset (1 and 2 torch threads) and the ``paper`` preset (2 threads). Each agent is built
by ``make_agent`` from ``preset_config(preset, agent)``; the batch size is its
``replay_needs().batch_size`` and ``hidden`` the ``hidden_dim`` of its first config section that has
one (``fb`` for FB/DVFB, ``ddpg`` for the URLB-style baselines). ``--quick``: the small preset at
1 thread, 3 updates (a smoke check, not a measurement).
Run it on an otherwise idle machine:  python bench/preset_update_ms.py
"""
import argparse
import time

import torch

from dvfb.agents import agent_names, make_agent
from dvfb.data import Batch
from dvfb.runs.presets import preset_config
from dvfb.runs.run_config import agent_sections

O, U = 24, 6


def first_hidden(config) -> int | None:
    for section in agent_sections(config).values():
        if isinstance(section, dict) and "hidden_dim" in section:
            return section["hidden_dim"]
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", default="fb,dvfb", help="comma-separated agents, or 'all' (every registered)")
    parser.add_argument("--quick", action="store_true", help="small preset, 1 thread, 3 updates (smoke check)")
    args = parser.parse_args(argv)
    agents = list(agent_names()) if args.agents == "all" else [a for a in args.agents.split(",") if a]
    unknown = [a for a in agents if a not in agent_names()]
    if unknown:
        parser.error(f"unknown agent(s) {unknown}; choose from {', '.join(agent_names())}")
    runs = [("small", 1, 3)] if args.quick else [("small", 1, 20), ("small", 2, 20), ("paper", 2, 3)]
    for preset, threads, reps in runs:
        torch.set_num_threads(threads)
        for agent in agents:
            cfg = preset_config(preset, agent=agent)
            torch.manual_seed(0)
            ag = make_agent(agent, O, U, cfg, "cpu")
            N = ag.replay_needs().batch_size
            z = ag.sample_skill(N)  # the stored rollout skill (None for agents without one)
            b = Batch(obs=torch.randn(N, O), action=torch.rand(N, U) * 2 - 1, reward=torch.rand(N, 1),
                      discount=torch.full((N, 1), .99), next_obs=torch.randn(N, O), future_obs=None,
                      z=None if z is None else z.cpu())
            ag.update(b)
            times = []
            for _ in range(reps):
                t = time.perf_counter(); ag.update(b); times.append(time.perf_counter() - t)
            times.sort()
            print(f"{preset:6s} threads={threads} {agent:12s} batch={N} hidden={first_hidden(cfg)}: "
                  f"median {times[len(times)//2]*1e3:8.1f} ms/update (min {times[0]*1e3:.1f}, n={reps})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
