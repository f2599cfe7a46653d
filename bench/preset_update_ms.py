"""Milliseconds per agent update of the exact preset configs (not a test).

One ``agent.update`` on a fixed walker-sized batch (obs 24, action 6), median over several updates,
for FB and DVFB at the ``small`` preset (1 and 2 torch threads) and the ``paper`` preset (2 threads).
Run it on an otherwise idle machine:  python bench/preset_update_ms.py
"""
import time

import torch

from dvfb.agents import make_agent
from dvfb.replay import Batch
from dvfb.workflows.config import preset_config

O, U = 24, 6
for preset, threads, reps in [("small", 1, 20), ("small", 2, 20), ("paper", 2, 3)]:
    torch.set_num_threads(threads)
    for agent in ("fb", "dvfb"):
        cfg = preset_config(preset, agent=agent)
        N = cfg.fb.batch_size
        torch.manual_seed(0)
        ag = make_agent(agent, O, U, cfg.fb, cfg.exploration, "cpu")
        b = Batch(obs=torch.randn(N, O), action=torch.rand(N, U) * 2 - 1, reward=torch.rand(N, 1),
                  discount=torch.full((N, 1), .99), next_obs=torch.randn(N, O), future_obs=None, z=None)
        ag.update(b)
        times = []
        for _ in range(reps):
            t = time.perf_counter(); ag.update(b); times.append(time.perf_counter() - t)
        times.sort()
        print(f"{preset:6s} threads={threads} {agent:5s} batch={N} hidden={cfg.fb.hidden_dim}: "
              f"median {times[len(times)//2]*1e3:8.1f} ms/update (min {times[0]*1e3:.1f}, n={reps})", flush=True)
