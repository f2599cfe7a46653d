"""Which equalities of docs/members.md hold on this CPU at the small preset's widths (the tests use
tiny widths): a group of 2 members of each method against 2 separate agents, ``--updates`` updates
on the same batches and streams, in float32; prints, per method, the tensors that differ, by how
many ulps at most, and the CPU's vector extensions.

    python scripts/members_equality.py --agents fb,dvfb --updates 3
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent.parent / "bench"))

from learner import env_dims, filled_replay, model_config  # noqa: E402

from dvfb.agents import make_agent  # noqa: E402
from dvfb.data import Batch  # noqa: E402
from dvfb.nets.members import member_training_state, stack_agents  # noqa: E402
from dvfb.runs.machine import cpu as cpu_info  # noqa: E402


def ulps(a: torch.Tensor, b: torch.Tensor) -> int:
    """The largest distance in units in the last place between two float32 tensors."""
    ia, ib = a.contiguous().view(torch.int32).long(), b.contiguous().view(torch.int32).long()
    # Map the sign-magnitude bit patterns onto a monotone integer line.
    ia = torch.where(ia < 0, -(ia & 0x7FFFFFFF), ia)
    ib = torch.where(ib < 0, -(ib & 0x7FFFFFFF), ib)
    return int((ia - ib).abs().max()) if a.numel() else 0


def compare(agent_name: str, members: int, updates: int, domain: str) -> list[tuple[str, int, float]]:
    obs_dim, action_dim = env_dims(domain)
    agents, twins, replays = [], [], []
    for k in range(members):
        torch.manual_seed(100 + k)
        config = model_config("small", agent_name)
        agent = make_agent(agent_name, obs_dim, action_dim, config, "cpu")
        agent.use_generator(torch.Generator().manual_seed(1000 + k))
        replays.append(filled_replay(obs_dim, action_dim, agent.skill_dim, torch.device("cpu"), steps=2000, seed=k))
        twin = copy.deepcopy(agent)
        twin.use_generator(torch.Generator().manual_seed(0))
        twin.generator.set_state(agent.generator.get_state())
        agents.append(agent)
        twins.append(twin)
    group = stack_agents(agents)
    needs = group.replay_needs()
    for u in range(updates):
        batches = [needs.sample(r, torch.Generator().manual_seed(7 + k + 10 * u)) for k, r in enumerate(replays)]
        group.update(Batch.stack(batches))
        for twin, batch in zip(twins, batches):
            twin.update(batch)
    differing = []
    for k, twin in enumerate(twins):
        member = member_training_state(group, k)["modules"]
        for key, value in twin.training_state()["modules"].items():
            if isinstance(value, torch.Tensor) and value.dtype == torch.float32 and not torch.equal(member[key], value):
                differing.append((f"member {k} {key}", ulps(member[key], value),
                                  float((member[key] - value).abs().max())))
    return differing


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--agents", default="fb,dvfb")
    p.add_argument("--members", type=int, default=2)
    p.add_argument("--updates", type=int, default=3)
    p.add_argument("--domain", default="walker")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    cpu = cpu_info()
    print(f"CPU: {cpu['model']} ({', '.join(cpu['vector_extensions'])}; torch kernels {cpu['torch_capability']}); "
          f"torch threads {args.threads}")
    for agent in args.agents.split(","):
        differing = compare(agent, args.members, args.updates, args.domain)
        if not differing:
            print(f"{agent}: bit for bit after {args.updates} updates ({args.members} members, small preset, "
                  f"{args.domain})")
        for name, ulp, diff in differing:
            print(f"{agent}: {name} differs by {ulp} ulp (max |diff| {diff:.3g}) after {args.updates} updates")
    return 0


if __name__ == "__main__":
    sys.exit(main())
