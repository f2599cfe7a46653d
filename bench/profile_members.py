"""Where a group update's time goes (issue: seeds together faster than apart): one stacked update of
N members of a method at the small preset, walker's sizes, under torch.profiler, with the operator
time summed by kind (matrix products, element-wise and reductions, autograd bookkeeping, optimiser,
copies) and the Python that the profiler does not attribute to an operator.

    python bench/profile_members.py --agents dvfb,fb --members 1,2,5 --threads 2 --matmuls

Prints one table per agent and N; --output writes the rows as JSON. Figures, not tests.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))

from learner import env_dims, filled_replay, model_config  # noqa: E402
from members import _agents  # noqa: E402

from dvfb.data import Batch  # noqa: E402
from dvfb.nets.members import stack_agents  # noqa: E402

MATMUL = ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm", "aten::matmul", "aten::linear")
OPTIM = ("Optimizer.step", "aten::_foreach", "aten::lerp", "aten::addcdiv", "aten::addcmul", "aten::sqrt")
COPY = ("aten::copy_", "aten::cat", "aten::stack", "aten::index", "aten::gather", "aten::clone", "aten::to",
        "aten::contiguous", "aten::_to_copy", "aten::index_select", "aten::scatter")


def kind(name: str) -> str:
    if name.startswith(MATMUL) or "Mm" in name and "Backward" in name:
        return "matmul"
    if name.startswith(OPTIM):
        return "optimiser"
    if name.startswith(COPY):
        return "copies"
    if "Backward" in name or name.startswith(("autograd::", "torch::autograd")):
        return "autograd"
    return "element-wise"


def profile(agent_name: str, n: int, warmup: int, repeats: int) -> dict:
    obs_dim, action_dim = env_dims("walker")
    config = model_config("small", agent_name)
    device = torch.device("cpu")
    agents, replays = _agents(agent_name, config, obs_dim, action_dim, n, filled_replay, device)
    group = stack_agents(agents)
    needs = group.replay_needs()

    def batch():
        return Batch.stack([needs.sample(r, g) for r, g in zip(replays, group.generator)])

    for _ in range(warmup):
        group.update(batch())
    batches = [batch() for _ in range(repeats)]
    times = []
    for b in batches[: repeats // 2]:
        t0 = time.perf_counter()
        group.update(b)
        times.append(time.perf_counter() - t0)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        for b in batches[repeats // 2:]:
            group.update(b)
    profiled = repeats - repeats // 2
    by_kind: dict[str, float] = defaultdict(float)
    ops = 0
    for event in prof.key_averages():
        # self time: each microsecond counted once, in the operator that spent it
        by_kind[kind(event.key)] += event.self_cpu_time_total / 1e3 / profiled
        ops += event.count
    wall = 1e3 * statistics.median(times)
    in_ops = sum(by_kind.values())
    return {"agent": agent_name, "members": n, "threads": torch.get_num_threads(), "ms_per_group_update": wall,
            "ms_per_member_update": wall / n, "operators_per_update": ops / profiled,
            "ms_by_kind": dict(sorted(by_kind.items())), "ms_outside_operators": max(0.0, wall - in_ops)}


def _gflops(fn, flop: float, reps: int) -> float:
    for _ in range(5):
        fn()
    t0 = time.perf_counter()
    for _ in range(reps):
        fn()
    return flop * reps / (time.perf_counter() - t0) / 1e9


def _one_thread_mm(_) -> float:
    torch.set_num_threads(1)
    a, b = torch.randn(256, 256), torch.randn(256, 512)
    return _gflops(lambda: a @ b, 2 * 256 * 256 * 512, 2000)


def matmul_rates(members: int = 5) -> dict:
    """GFLOP/s of the small preset's typical product (256 x 256 by 256 x 512): one product on 1 and
    2 threads, the members' batched product on 2 threads, and one product in each of 2 processes
    at once (1 thread each), the schedule separate runs get."""
    import multiprocessing

    a, b = torch.randn(256, 256), torch.randn(256, 512)
    am, bm = torch.randn(members, 256, 256), torch.randn(members, 256, 512)
    rates = {}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        rates[f"mm, {threads} thread(s)"] = _gflops(lambda: a @ b, 2 * 256 * 256 * 512, 1000)
    rates[f"bmm of {members} members, 2 threads"] = _gflops(lambda: torch.bmm(am, bm),
                                                            members * 2 * 256 * 256 * 512, 200)
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        rates["mm, 2 processes x 1 thread (sum)"] = sum(pool.map(_one_thread_mm, [0, 1]))
    return rates


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--agents", default="dvfb,fb")
    p.add_argument("--members", default="1,2,5")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--output", type=Path, default=None)
    p.add_argument("--matmuls", action="store_true", help="also the product rates of the schedules (GFLOP/s)")
    args = p.parse_args(argv)
    rows = []
    if args.matmuls:
        for name, rate in matmul_rates().items():
            print(f"{name}: {rate:.0f} GFLOP/s", flush=True)
    torch.set_num_threads(args.threads)
    for agent in args.agents.split(","):
        for n in map(int, args.members.split(",")):
            row = profile(agent, n, args.warmup, args.repeats)
            rows.append(row)
            kinds = ", ".join(f"{k} {v:.1f}" for k, v in row["ms_by_kind"].items())
            print(f"{agent} N={n}: {row['ms_per_group_update']:.1f} ms/group update "
                  f"({row['ms_per_member_update']:.2f} ms/member, {1e3 / row['ms_per_member_update']:.0f} "
                  f"member-updates/s), {row['operators_per_update']:.0f} ops; ms: {kinds}; outside operators "
                  f"{row['ms_outside_operators']:.1f}", flush=True)
    if args.output:
        args.output.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
