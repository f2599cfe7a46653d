"""Parameter hashes after three updates of every registered method on a fixed replay (fp32).

Before and after a refactor, the same method must print the same hash: its update is then
bit-identical on the same batch and random draws. Run from the repository root:

    python scripts/update_hashes.py [AGENT ...]

It uses the tiny test configs (tests/tiny.py) on point_mass_maze: a replay of 400 uniform-action
steps with skills from the method's prior, torch seed 0, three updates.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from dvfb import envs  # noqa: E402
from dvfb.agents import agent_names, make_agent  # noqa: E402
from tiny import filled_replay, tiny_run_config  # noqa: E402


def update_hash(name: str) -> str:
    torch.manual_seed(0)
    env = envs.make("point_mass_maze_reach_top_left")
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    agent = make_agent(name, obs_dim, action_dim, tiny_run_config(name), "cpu")
    replay = filled_replay(agent)
    needs = agent.replay_needs()
    for _ in range(3):
        agent.update(needs.sample(replay))
    digest = hashlib.sha256()
    for key, tensor in sorted(agent.state_dict().items()):
        digest.update(key.encode())
        if isinstance(tensor, torch.Tensor):
            digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
        else:  # extra state (Proto's queue pointer)
            digest.update(repr(tensor).encode())
    return digest.hexdigest()[:16]


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("agents", nargs="*", metavar="AGENT", help="registered methods (default: every one)")
    args = parser.parse_args()
    unknown = [name for name in args.agents if name not in agent_names()]
    if unknown:
        parser.exit(2, f"update_hashes.py: unknown agent(s) {', '.join(unknown)}; "
                       f"choose from {', '.join(agent_names())}\n")
    torch.set_num_threads(1)
    for agent_name in args.agents or agent_names():
        print(f"{agent_name:14s} {update_hash(agent_name)}")
