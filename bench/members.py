"""The members section of bench/learner.py (docs/members.md): N seeds of one method in one process
on stacked parameters, against the best schedule of N separate processes on the same cores.

* ``learner`` rows -- for every agent and N in ``--members`` (default 1,2,5,10): ms per stacked
  update of the group (``Batch.stack`` of N batches, one per member replay; sampling excluded) and
  ms per member-update; against the separate-process schedules, measured in the same run: one
  process with all threads, and ``cores`` processes at once with one thread each (each process
  times its own updates while the others run). The best schedule's member-updates/s is the
  reference; ``speed-up`` = group member-updates/s / that.
* ``e2e`` rows -- ``dvfb pretrain --seeds`` (one process, N members) against N separate
  ``dvfb pretrain`` processes in the best schedule (sequential with all threads, or ``cores`` at
  a time with one thread each), wall clock of the whole schedule, process start-up included:
  member-frames/s = N x frames / wall.
* ``func`` row -- the choice between explicit stacked blocks and ``torch.func``, on FB: forward and
  backward of FB's losses (B, F, targets, FB/Q/orthonormality losses) for N members, once through
  the stacked agent and once as ``vmap(functional_call(per-seed agent))`` over the members'
  stacked parameters (autograd through the vmap).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from dvfb.agents import make_agent
from dvfb.data import Batch
from dvfb.nets.members import stack_agents

MEMBER_COUNTS = (1, 2, 5, 10)


def _agents(agent_name, config, obs_dim, action_dim, n, filled_replay, device):
    agents, replays = [], []
    for k in range(n):
        torch.manual_seed(k)
        agent = make_agent(agent_name, obs_dim, action_dim, config, device)
        agent.use_generator(torch.Generator(device=device).manual_seed(k))
        agents.append(agent)
        replays.append(filled_replay(obs_dim, action_dim, agent.skill_dim, device, steps=2000, seed=k))
    return agents, replays


def time_group(agent_name, config, obs_dim, action_dim, n, filled_replay, device, warmup, repeats,
               seconds: float = 0.0) -> dict:
    """ms per stacked update of ``n`` members (sampling excluded): the median of ``repeats`` updates,
    or of as many more as fill ``seconds``."""
    agents, replays = _agents(agent_name, config, obs_dim, action_dim, n, filled_replay, device)
    group = stack_agents(agents)
    needs = group.replay_needs()
    gens = group.generator

    def batch():
        return Batch.stack([needs.sample(r, g) for r, g in zip(replays, gens)])

    for _ in range(warmup):
        group.update(batch())
    times = []
    end = time.perf_counter() + seconds
    while len(times) < repeats or time.perf_counter() < end:
        b = batch()
        t0 = time.perf_counter()
        group.update(b)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - t0)
    ms = 1e3 * statistics.median(times)
    return {"ms_per_group_update": ms, "ms_per_member_update": ms / n}


def separate_probe(spec: dict, filled_replay) -> dict:
    """In a subprocess: ms per update of one ordinary agent at ``spec['threads']`` threads
    (``filled_replay``: bench/learner.py's replay builder); with ``spec['members'] > 1``, ms per
    stacked update of that many members for at least ``spec['seconds']`` (one share of a split
    group, timed while the other shares run)."""
    from dvfb.runs.run_config import run_config_from_dict
    torch.set_num_threads(spec["threads"])
    device = torch.device(spec["device"])
    config = run_config_from_dict(spec["config"], "members probe")
    if spec.get("members", 1) > 1:
        return time_group(spec["agent"], config, spec["obs_dim"], spec["action_dim"], spec["members"], filled_replay,
                          device, spec["warmup"], spec["repeats"], spec["seconds"])
    agents, replays = _agents(spec["agent"], config, spec["obs_dim"], spec["action_dim"], 1, filled_replay, device)
    agent, replay = agents[0], replays[0]
    needs = agent.replay_needs()
    for _ in range(spec["warmup"]):
        agent.update(needs.sample(replay, agent.generator))
    times = []
    end = time.perf_counter() + spec.get("seconds", 0.0)
    while len(times) < spec["repeats"] or time.perf_counter() < end:
        b = needs.sample(replay, agent.generator)
        t0 = time.perf_counter()
        agent.update(b)
        times.append(time.perf_counter() - t0)
    return {"ms_per_update": 1e3 * statistics.median(times)}


def _probe_processes(spec: dict, processes: int | list[dict]) -> list[dict]:
    """``processes`` probes (or one per spec of a list) started together (they contend for the cores
    as separate runs do)."""
    specs = [spec] * processes if isinstance(processes, int) else processes
    learner = str(Path(__file__).resolve().parent / "learner.py")
    env = {**os.environ, "OMP_NUM_THREADS": str(specs[0]["threads"])}
    procs = [subprocess.Popen([sys.executable, learner, "--members-probe", json.dumps(one)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=env)
             for one in specs]
    out = []
    for proc in procs:
        stdout, stderr = proc.communicate()
        if proc.returncode != 0:
            raise RuntimeError(f"members probe failed: {stderr.strip()[-500:]}")
        out.append(json.loads(stdout.strip().splitlines()[-1]))
    return out


def separate_schedules(agent_name, config_dict, obs_dim, action_dim, device, threads, warmup, repeats) -> dict:
    """Member-updates/s of the separate-process schedules: one process with ``threads`` threads;
    ``threads`` processes at once with one thread each."""
    spec = {"agent": agent_name, "config": config_dict, "obs_dim": obs_dim, "action_dim": action_dim,
            "device": str(device), "warmup": warmup, "repeats": repeats}
    one = _probe_processes({**spec, "threads": threads}, 1)[0]["ms_per_update"]
    schedules = {f"1 process x {threads} threads": 1e3 / one}
    if threads > 1:
        many = _probe_processes({**spec, "threads": 1}, threads)
        schedules[f"{threads} processes x 1 thread"] = sum(1e3 / r["ms_per_update"] for r in many)
    best = max(schedules, key=schedules.get)
    return {"schedules_member_updates_per_s": schedules, "best_schedule": best,
            "best_member_updates_per_s": schedules[best], "ms_per_update_1_process": one}


def split_rate(agent_name, config_dict, obs_dim, action_dim, device, n, processes, warmup, repeats,
               seconds) -> float | None:
    """Member-updates/s of a group of ``n`` split over ``processes`` single-thread processes
    (``dvfb pretrain --seeds ... --processes``): each times its share's stacked updates for
    ``seconds`` while the others run; None when ``n`` < 2 or there is one process."""
    from dvfb.workflows.processes import shares

    split = shares(n, processes)
    if len(split) < 2:
        return None
    spec = {"agent": agent_name, "config": config_dict, "obs_dim": obs_dim, "action_dim": action_dim,
            "device": str(device), "warmup": warmup, "repeats": repeats, "threads": 1, "seconds": seconds}
    results = _probe_processes(spec, [{**spec, "members": len(share)} for share in split])
    # a share of one is an ordinary run (its own, unstacked learner), as in dvfb pretrain
    return sum(len(share) * 1e3 / r.get("ms_per_group_update", r.get("ms_per_update")) for share, r in zip(split, results))


def run_members(args, device, obs_dim, action_dim, model_config, filled_replay) -> dict:
    threads = torch.get_num_threads()
    warmup, repeats = (2, 5) if args.quick else (3, 10)
    counts = [int(n) for n in args.members.split(",")]
    rows = []
    from dvfb.core.config import to_dict
    for agent_name in args.agent_list:
        config = model_config("small", agent_name)
        separate = separate_schedules(agent_name, to_dict(config), obs_dim, action_dim, device, threads, warmup, repeats)
        for n in counts:
            group = time_group(agent_name, config, obs_dim, action_dim, n, filled_replay, device, warmup, repeats)
            member_rate = 1e3 / group["ms_per_member_update"]
            row = {"agent": agent_name, "config": "small", "members": n, "device": str(device), "threads": threads,
                   **group, "member_updates_per_s": member_rate,
                   "separate_best_schedule": separate["best_schedule"],
                   "separate_member_updates_per_s": separate["best_member_updates_per_s"],
                   "separate_ms_per_update_1_process": separate["ms_per_update_1_process"],
                   "separate_schedules": separate["schedules_member_updates_per_s"],
                   "speedup_vs_separate": member_rate / separate["best_member_updates_per_s"]}
            split = split_rate(agent_name, to_dict(config), obs_dim, action_dim, device, n, threads, warmup, repeats,
                               2.0 if args.quick else 6.0) if device.type == "cpu" else None
            if split is not None:
                row.update({"split_processes": min(threads, n), "split_member_updates_per_s": split,
                            "split_speedup_vs_separate": split / separate["best_member_updates_per_s"]})
            rows.append(row)
            print(f"  members {agent_name} N={n}: {group['ms_per_group_update']:.1f} ms/group update, "
                  f"{group['ms_per_member_update']:.2f} ms/member, x{row['speedup_vs_separate']:.2f} vs "
                  f"{separate['best_schedule']}" + (f"; split over {threads} processes x{split / separate['best_member_updates_per_s']:.2f}"
                                                   if split is not None else ""), file=sys.stderr)
    report = {"learner": rows}
    if "fb" in args.agent_list:
        report["func"] = [func_row(model_config("small", "fb"), obs_dim, action_dim, n, filled_replay, device,
                                   warmup, repeats) for n in counts if n > 1]
    if args.members_e2e_agents:
        report["e2e"] = [e2e_row(agent, n, args, device, threads)
                         for agent in args.members_e2e_agents.split(",") for n in args.members_e2e_counts]
    return report


# torch.func against the stacked blocks, on FB's losses ------------------------------------------------

class _LossOfOneSeed(torch.nn.Module):
    """FB's losses of one member as a module call, so that ``functional_call`` can swap its parameters."""

    def __init__(self, agent):
        super().__init__()
        self.agent = agent

    def forward(self, obs, action, next_obs, discount, z, next_action):
        batch = Batch(obs, action, discount, discount, next_obs, None, z)
        online, target = self.agent.backward_inputs(batch)
        backward = self.agent.backward_map(online)
        return self.agent.fb_losses(batch, z, next_action, backward, target)["fb_total"]


def func_row(config, obs_dim, action_dim, n, filled_replay, device, warmup, repeats) -> dict:
    from torch.func import functional_call, stack_module_state, vmap

    agents, replays = _agents("fb", config, obs_dim, action_dim, n, filled_replay, device)
    wrappers = [_LossOfOneSeed(a) for a in agents]
    params, buffers = stack_module_state(wrappers)
    template = _LossOfOneSeed(make_agent("fb", obs_dim, action_dim, config, device)).to("meta")
    needs = agents[0].replay_needs()
    batches = [needs.sample(r, a.generator) for r, a in zip(replays, agents)]
    stacked_batch = Batch.stack(batches)
    z = torch.randn(n, len(batches[0]), agents[0].config.z_dim, device=device)
    next_action = torch.rand(n, len(batches[0]), action_dim, device=device) * 2 - 1

    def one_seed(p, b, obs, action, next_obs, discount, zz, na):
        return functional_call(template, (p, b), (obs, action, next_obs, discount, zz, na))

    def by_func():
        losses = vmap(one_seed)(params, buffers, stacked_batch.obs, stacked_batch.action, stacked_batch.next_obs,
                                stacked_batch.discount, z, next_action)
        losses.sum().backward()

    group = stack_agents(agents)
    group_wrapper = _LossOfOneSeed(group)

    def by_stacked():
        group_wrapper(stacked_batch.obs, stacked_batch.action, stacked_batch.next_obs, stacked_batch.discount, z,
                      next_action).sum().backward()

    out = {"agent": "fb", "members": n, "what": "FB losses forward + backward"}
    for name, fn in (("stacked_ms", by_stacked), ("torch_func_ms", by_func)):
        for _ in range(warmup):
            fn()
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        out[name] = 1e3 * statistics.median(times)
    print(f"  func N={n}: stacked {out['stacked_ms']:.1f} ms, torch.func {out['torch_func_ms']:.1f} ms",
          file=sys.stderr)
    return out


# End to end ----------------------------------------------------------------------------------------

def _pretrain_cmd(agent, args, frames, threads, run_dir, seeds=None, processes=1):
    cmd = [sys.executable, "-m", "dvfb", "pretrain", "--agent", agent, "--domain", args.e2e_domain,
           "--preset", "small", "--frames", str(frames), "--seed-frames", str(args.members_e2e_seed_frames),
           "--no-progress", "--log-every", "500", "--torch-threads", str(threads), "--device", "cpu"]
    if seeds is None:
        return cmd + ["--run-dir", str(run_dir)]
    return cmd + ["--seeds", ",".join(map(str, seeds)), "--run-dir", str(run_dir), "--processes", str(processes)]


def _timed(cmds: list[list[str]], at_once: int, threads: int | None) -> float:
    """Wall clock of the commands, ``at_once`` at a time, with ``OMP_NUM_THREADS`` = ``threads``;
    None: without it (a user's shell, the threads are the commands' own flags)."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    if threads is not None:
        env["OMP_NUM_THREADS"] = str(threads)
    start = time.perf_counter()
    pending = list(cmds)
    running: list[subprocess.Popen] = []
    while pending or running:
        while pending and len(running) < at_once:
            running.append(subprocess.Popen(pending.pop(0), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                            text=True, env=env))
        proc = running.pop(0)
        _out, err = proc.communicate()
        if proc.returncode != 0:
            raise RuntimeError(f"pretrain failed: {err.strip()[-500:]}")
    return time.perf_counter() - start


def e2e_row(agent, n, args, device, threads) -> dict:
    frames = args.members_e2e_frames
    seeds = list(range(n))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        group_cmd = _pretrain_cmd(agent, args, frames, threads, tmp / "group_s{seed}", seeds)
        group_wall = _timed([group_cmd], 1, threads)
        split_cmd = _pretrain_cmd(agent, args, frames, 1, tmp / "split_s{seed}", seeds, processes=threads)
        split_wall = _timed([split_cmd], 1, 1) if threads > 1 and n > 1 else None
        schedules = {}
        sequential = [_pretrain_cmd(agent, args, frames, threads, tmp / f"seq_{s}") for s in seeds]
        schedules[f"1 at a time x {threads} threads"] = _timed(sequential, 1, threads)
        if threads > 1:
            parallel = [_pretrain_cmd(agent, args, frames, 1, tmp / f"par_{s}") for s in seeds]
            schedules[f"{threads} at a time x 1 thread"] = _timed(parallel, threads, 1)
    best = min(schedules, key=schedules.get)
    row = {"agent": agent, "members": n, "frames": frames, "seed_frames": args.members_e2e_seed_frames,
           "domain": args.e2e_domain, "preset": "small", "group_wall_s": group_wall,
           "group_member_frames_per_s": n * frames / group_wall, "separate_wall_s": schedules,
           "separate_best_schedule": best, "separate_member_frames_per_s": n * frames / schedules[best],
           "speedup_vs_separate": schedules[best] / group_wall, "group_command": " ".join(group_cmd)}
    if split_wall is not None:
        row.update({"split_wall_s": split_wall, "split_member_frames_per_s": n * frames / split_wall,
                    "split_speedup_vs_separate": schedules[best] / split_wall, "split_command": " ".join(split_cmd)})
    print(f"  e2e {agent} N={n}: group {group_wall:.0f} s, separate best ({best}) {schedules[best]:.0f} s, "
          f"x{row['speedup_vs_separate']:.2f}" + (f"; split {split_wall:.0f} s, x{row['split_speedup_vs_separate']:.2f}"
                                                  if split_wall is not None else ""), file=sys.stderr)
    return row


MEMBER_COLUMNS = [("agent", "agent", "<", "{}"), ("N", "members", ">", "{}"), ("ms/group update", "ms_per_group_update", ">", "{:.1f}"),
                  ("ms/member", "ms_per_member_update", ">", "{:.2f}"), ("member-updates/s", "member_updates_per_s", ">", "{:.0f}"),
                  ("separate best", "separate_best_schedule", "<", "{}"),
                  ("separate member-updates/s", "separate_member_updates_per_s", ">", "{:.0f}"),
                  ("speed-up", "speedup_vs_separate", ">", "{:.2f}x"),
                  ("split member-updates/s", "split_member_updates_per_s", ">", "{:.0f}"),
                  ("split speed-up", "split_speedup_vs_separate", ">", "{:.2f}x")]
FUNC_COLUMNS = [("N", "members", ">", "{}"), ("stacked ms", "stacked_ms", ">", "{:.1f}"), ("torch.func ms", "torch_func_ms", ">", "{:.1f}")]
E2E_COLUMNS = [("agent", "agent", "<", "{}"), ("N", "members", ">", "{}"), ("frames", "frames", ">", "{}"),
               ("group s", "group_wall_s", ">", "{:.0f}"), ("group member-frames/s", "group_member_frames_per_s", ">", "{:.1f}"),
               ("separate best", "separate_best_schedule", "<", "{}"),
               ("separate member-frames/s", "separate_member_frames_per_s", ">", "{:.1f}"),
               ("speed-up", "speedup_vs_separate", ">", "{:.2f}x"),
               ("split s", "split_wall_s", ">", "{:.0f}"),
               ("split member-frames/s", "split_member_frames_per_s", ">", "{:.1f}"),
               ("split speed-up", "split_speedup_vs_separate", ">", "{:.2f}x")]
