"""Learner, collector and end-to-end throughput of dvfb, with FLOPs and the machine's matmul peak.

Sections (``--only`` picks a subset; all run by default):

* ``peak``      -- this machine's matrix-multiply peak, measured in the same run: the best of a few
  square products (2048^3 on CPU, 8192^3 on CUDA) in fp32, and in bf16 when bf16 learner rows are
  requested (``--precisions``). Every GFLOP/s figure below is also given as a fraction of this
  fp32 (or, for bf16 rows, bf16) peak. Always measured.
* ``learner``   -- ms per ``agent.update(batch)`` for every registered agent (``--agents``; default
  all of ``dvfb.agents.agent_names()``: fb, dvfb and the URLB-style baselines rnd, disagreement,
  icm_apt, proto), each built by ``make_agent`` from its run config ``preset_config(preset, agent)``
  and fed batches drawn as its ``replay_needs()`` says (batch size, discount, n-step, s_{t+2}).
  Configurations (see CONFIGS): the ``paper`` preset (H=1024, N=1024) and the ``small`` preset
  apply to every agent; the FB configurations ``hidden256`` and ``hidden256_wide`` override the
  ``fb`` / ``exploration`` sections and apply only to agents that have one of them (FB, DVFB; the
  others are skipped with a one-line note). In fp32 and bf16 (``--precisions``); FLOPs of one
  real update counted with ``torch.utils.flop_counter``; achieved GFLOP/s; the replay sampling
  time (not included in ms/update); peak memory (see MEMORY below). ``--compile`` adds
  torch.compile rows for the small preset, with the compile time. A row records the agent's
  config sections; its ``H`` is the ``hidden_dim`` of the first section that has one (``fb`` for
  FB/DVFB, ``ddpg`` for the baselines), ``N`` the batch size of ``replay_needs()``, and ``E`` /
  ``Hb`` the FB feature and B hidden widths (``-`` for agents without them).
* ``scaling``   -- ms/update of DVFB over a grid of hidden widths x batch sizes (paper widths
  otherwise, see CONFIGS); ``--scaling-hidden`` / ``--scaling-batch`` limit the grid.
* ``collector`` -- (DVFB) environment steps/s of the pre-training loop without updates, against raw
  dm_control stepping in the same process, in alternating chunks (as bench/env_throughput.py):
  ``seed phase`` = uniform actions + dvfb env step + replay add; ``acting`` = ``agent.act`` (actor
  forward + rollout noise) + dvfb env step + replay add, for the small and paper actors. Both
  replicate the loop body of dvfb.workflows.pretrain (z resampling and its host copy, non-finite
  action check, episode resets) minus the update. Also: microseconds per ``agent.act``.
* ``members``   -- N seeds as one stacked group against N separate processes (bench/members.py,
  docs/members.md); only when asked for (``--only members``).
* ``e2e``       -- frames/s of ``python -m dvfb pretrain --agent E2E_AGENT`` (``--e2e-agent``,
  default dvfb) at the small preset (default 6000 frames
  of which 2000 seed frames), as a subprocess into a temporary run directory: the run's own
  figure over all frames (process start-up excluded), and the steady-state rate of the training
  phase from its fps logged every 500 frames.

MEMORY. CPU: each configuration runs in a fresh subprocess (so no earlier allocation is reused),
rebuilt there from the row's whole run config (``run_config_from_dict``), which reports its
resident set size (RSS) just before the first update and the peak RSS (Linux VmHWM, reset
through /proc/self/clear_refs just before the first update) during the warm-up and two further
updates. ``peak RSS`` is the whole process (torch runtime, replay buffer, networks,
optimiser states, autograd buffers); ``update +`` is the peak minus the RSS before the first
update: what the updates add (Adam states created at the first step, gradients, activations,
temporaries, allocator slack). ``state MB`` is computed exactly from the tensors: parameters of
all networks (targets included) plus Adam's two moments. CUDA: ``torch.cuda.max_memory_allocated``
during the updates (the caching allocator's live tensors), same columns.

Usage: python bench/learner.py [--quick] [--only learner,scaling,collector,e2e] [--threads N]
       [--device auto|cpu|cuda] [--agents fb,dvfb,...] [--configs paper,small,...]
       [--precisions fp32,bf16] [--compile] [--output PATH]
Writes bench/results/learner.json (``--output``). ``python bench/run.py`` (``make bench``) runs this,
bench/env_throughput.py and bench/preset_update_ms.py.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.metadata
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# isort: off
import dvfb.envs as envs  # before dm_control: sets the headless MUJOCO_GL default
# isort: on

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from dvfb.agents import agent_names, get_spec, make_agent
from dvfb.core.config import merge, replace, to_dict
from dvfb.data import ReplayBuffer
from dvfb.nets.execution import PerfConfig, bf16_matmul_is_fast
from dvfb.runs import read_metrics
from dvfb.runs.presets import preset_config
from dvfb.runs.run_config import PretrainConfig, agent_sections, run_config_from_dict
from dvfb.training.observers import ReplayWriter
from dvfb.training.rollout import Lane, Policy, rollout

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import members as members_bench  # noqa: E402 - bench/members.py, the members section
RESULTS_PATH = HERE / "results" / "learner.json"
SECTIONS = ("learner", "scaling", "collector", "e2e", "members")
DEFAULT_SECTIONS = ("learner", "scaling", "collector", "e2e")


def paper_widths_at(hidden: int, batch: int) -> dict:
    """Overrides of the paper preset: H = ``hidden`` wherever the paper uses H (actor, F, critics,
    RND and contrastive encoders), batch ``batch``; E, Hb and the RND output stay the paper's."""
    return {"fb": {"hidden_dim": hidden, "batch_size": batch}, "exploration": {"contrastive_hidden_dim": hidden}}


# The configurations of the learner rows: name -> (preset, overrides of the run config).
# ``paper`` and ``small`` are the presets of every agent (preset_config(preset, agent)). The others
# override the FB sections (``fb``, ``exploration``): they apply to an agent only in the sections
# it has, and not at all to an agent that has none of them (see config_applies).
# "hidden256" is the performance issue's "hidden 256, batch 256" row: every width the paper ties
# to the network size at 256 (H, the feature width E, the B hidden width Hb, the contrastive
# encoders) and the batch at 256; the RND output stays 512. Its FLOP count (3.91 GFLOP per DVFB
# update) times the authors'/ours FLOP ratio at the paper config (175 / 142.8) is 4.79 GFLOP, the
# issue's 4.8 GFLOP for the authors' update, so the two configurations match in size.
# "hidden256_wide" keeps the paper's E = 512 and Hb = 526 (6.21 GFLOP, more than the authors' row,
# so not their configuration); it is also the scaling grid's 256 x 256 point.
CONFIGS = {
    "paper": ("paper", {}),
    "small": ("small", {}),
    "hidden256": ("paper", {"fb": {"hidden_dim": 256, "feature_dim": 256, "backward_hidden_dim": 256,
                                   "batch_size": 256},
                            "exploration": {"contrastive_hidden_dim": 256}}),
    "hidden256_wide": ("paper", paper_widths_at(256, 256)),
}
CONFIG_NOTES = {
    "paper": "preset paper, every agent. FB/DVFB: H=1024, E=512, Hb=526, N=1024, contrastive H=1024, RND out "
             "512; DDPG baselines: H=1024, N=1024, n-step 3, reward modules 1024 wide (RND/ICM-APT out 512, "
             "Disagreement 5 models, Proto 512 prototypes)",
    "small": "preset small, every agent. FB/DVFB: H=256, E=128, Hb=256, N=256, contrastive H=256, RND out 128; "
             "DDPG baselines: H=256, N=256, n-step 3, reward modules 256 wide (RND/ICM-APT out 128; Proto "
             "keeps its paper sizes)",
    "hidden256": "FB/DVFB only: the issue's hidden 256 row: H=E=Hb=256, N=256, contrastive H=256, RND out 512",
    "hidden256_wide": "FB/DVFB only: paper widths with H=256 and N=256: E=512, Hb=526, contrastive H=256, "
                      "RND out 512",
}


# ---------------------------------------------------------------------------------------------
# Helpers


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def config_applies(name: str, agent: str) -> bool:
    """Whether the learner configuration ``name`` applies to ``agent``: the presets apply to every
    agent; a configuration overriding sections applies to agents that have at least one of them."""
    changes = CONFIGS[name][1]
    return not changes or bool(set(changes) & set(get_spec(agent).sections))


def own_sections(agent: str, changes: dict) -> dict:
    """The part of section overrides that concerns ``agent`` (e.g. FB has ``fb`` but no ``exploration``)."""
    sections = get_spec(agent).sections
    return {k: v for k, v in changes.items() if k in sections}


def model_config(name: str, agent: str, overrides: dict | None = None) -> PretrainConfig:
    """The run config of learner configuration ``name`` for ``agent`` (its preset, then the
    configuration's overrides of the agent's own sections, then ``overrides``)."""
    preset, changes = CONFIGS[name]
    config = preset_config(preset, agent)
    changes = own_sections(agent, changes)
    config = merge(config, changes) if changes else config
    if overrides:
        config = merge(config, overrides)
    return config


def scaling_config(hidden: int, batch: int, agent: str = "dvfb") -> PretrainConfig:
    """Paper widths with H = ``hidden`` wherever the paper uses H, and batch ``batch``."""
    return merge(preset_config("paper", agent), own_sections(agent, paper_widths_at(hidden, batch)))


def first_field(sections: dict, name: str):
    """``name`` from the first of the agent's sections (registry order) that has it, else None."""
    for section in sections.values():
        if isinstance(section, dict) and name in section:
            return section[name]
    return None


def env_dims(domain: str) -> tuple[int, int]:
    env = envs.make(envs.pretrain_task(domain), seed=0)
    return env.observation_space.shape[0], env.action_space.shape[0]


def filled_replay(obs_dim: int, action_dim: int, z_dim: int, device: torch.device, steps: int = 10_000,
                  episode_length: int = 1000, seed: int = 0) -> ReplayBuffer:
    """A buffer of ``steps`` random transitions (the learner's cost does not depend on the values)."""
    replay = ReplayBuffer(max(steps, episode_length), obs_dim, action_dim, z_dim,
                          max_episode_length=episode_length, device=device)
    rng = np.random.default_rng(seed)
    obs = rng.standard_normal((steps + 1, obs_dim)).astype(np.float32)
    actions = rng.uniform(-1, 1, (steps, action_dim)).astype(np.float32)
    zs = rng.standard_normal((steps, z_dim)).astype(np.float32) if z_dim else None
    for t in range(steps):
        if t % episode_length == 0:
            replay.start_episode(obs[t])
        replay.add(actions[t], 0.0, 1.0, obs[t + 1], zs[t] if zs is not None else None)
    return replay


def build(agent_name: str, config: PretrainConfig, device: torch.device, obs_dim: int, action_dim: int,
          seed: int = 0, perf: PerfConfig | None = None):
    """The agent from its run config (``perf`` replaces the config's), and a filled replay with
    the agent's skill width."""
    if perf is not None:
        config = replace(config, perf=perf)
    torch.manual_seed(seed)
    agent = make_agent(agent_name, obs_dim, action_dim, config, device)
    return agent, filled_replay(obs_dim, action_dim, agent.skill_dim, device)


def state_bytes(agent) -> int:
    """Parameters of every network (targets included) plus Adam's moments, from the tensors."""
    total = sum(p.numel() * p.element_size() for p in agent.parameters())
    for opt in agent.optimizers().values():
        for state in opt.state.values():
            total += sum(v.numel() * v.element_size() for v in state.values()
                         if torch.is_tensor(v) and v.dim() > 0)
    return total


def time_updates(agent, replay: ReplayBuffer, warmup: int, repeats: int, device: torch.device) -> dict:
    """Median / min ms per update and per replay sample, over ``repeats`` timed updates."""
    needs = agent.replay_needs()
    for _ in range(warmup):
        agent.update(needs.sample(replay))
    sync(device)
    update_s, sample_s = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        batch = needs.sample(replay)
        sync(device)
        t1 = time.perf_counter()
        agent.update(batch)
        sync(device)
        t2 = time.perf_counter()
        sample_s.append(t1 - t0)
        update_s.append(t2 - t1)
    return {"ms_per_update": 1e3 * statistics.median(update_s), "ms_per_update_min": 1e3 * min(update_s),
            "ms_per_update_runs": [1e3 * s for s in update_s],
            "ms_per_sample": 1e3 * statistics.median(sample_s)}


MATMUL_OPS = ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm")


def matmul_breakdown(agent, replay: ReplayBuffer, updates: int, device: torch.device) -> dict | None:
    """Per update under torch.profiler (CPU only): the wall time, and the self time of the matrix
    products (the operations the FLOP count covers). The rest of the update (element-wise work,
    optimiser, autograd and Python) is the difference. The profiler adds a little overhead."""
    if device.type != "cpu":
        return None
    from torch.profiler import ProfilerActivity, profile

    needs = agent.replay_needs()
    batches = [needs.sample(replay) for _ in range(updates)]
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        start = time.perf_counter()
        for batch in batches:
            agent.update(batch)
        wall = time.perf_counter() - start
    matmul_us = sum(e.self_cpu_time_total for e in prof.key_averages() if e.key in MATMUL_OPS)
    return {"profiled_ms_per_update": 1e3 * wall / updates, "matmul_ms_per_update": matmul_us / 1e3 / updates}


def count_flops(agent, replay: ReplayBuffer) -> int:
    batch = agent.replay_needs().sample(replay)
    with FlopCounterMode(display=False) as counter:
        agent.update(batch)
    return int(counter.get_total_flops())


# ---------------------------------------------------------------------------------------------
# Peak


def matmul_peak(device: torch.device, dtype: torch.dtype, quick: bool, rounds: int | None = None) -> dict:
    n = 8192 if device.type == "cuda" else 2048
    a = torch.randn(n, n, device=device).to(dtype)
    b = torch.randn(n, n, device=device).to(dtype)
    out = torch.empty(n, n, device=device, dtype=dtype)
    torch.mm(a, b, out=out)
    sync(device)
    best = float("inf")
    for _ in range(rounds or (3 if quick else 5)):
        reps = 3
        start = time.perf_counter()
        for _ in range(reps):
            torch.mm(a, b, out=out)
        sync(device)
        best = min(best, (time.perf_counter() - start) / reps)
    return {"n": n, "dtype": str(dtype).replace("torch.", ""), "gflops": 2 * n ** 3 / best / 1e9,
            "statistic": "best of repeated runs"}


# ---------------------------------------------------------------------------------------------
# Memory (fresh subprocess per configuration)


def _rss_kb(field: str) -> int:
    status = Path("/proc/self/status").read_text()
    return int(re.search(rf"{field}:\s+(\d+)", status).group(1))


def memory_probe(spec: dict) -> dict:
    """Run in a fresh process: build from the run config, then measure RSS (or CUDA memory) over
    three updates."""
    device = torch.device(spec["device"])
    torch.set_num_threads(spec["threads"])
    config = run_config_from_dict(spec["config"], "memory probe spec")
    agent, replay = build(spec["agent"], config, device, spec["obs_dim"], spec["action_dim"])
    needs = agent.replay_needs()
    result: dict = {}
    if device.type == "cuda":
        sync(device)
        before = torch.cuda.memory_allocated(device)
        torch.cuda.reset_peak_memory_stats(device)
    else:
        before = _rss_kb("VmRSS") * 1024
        try:
            Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current RSS
            result["method"] = "VmHWM after /proc/self/clear_refs reset"
        except OSError:
            result["method"] = "ru_maxrss (not resettable: includes set-up)"
    for _ in range(3):
        agent.update(needs.sample(replay))
    sync(device)
    if device.type == "cuda":
        peak = torch.cuda.max_memory_allocated(device)
        result["method"] = "torch.cuda.max_memory_allocated"
    elif result["method"].startswith("VmHWM"):
        peak = _rss_kb("VmHWM") * 1024
    else:
        import resource

        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    result.update(before_first_update_mb=before / 2 ** 20, peak_mb=peak / 2 ** 20,
                  update_added_mb=(peak - before) / 2 ** 20, state_mb=state_bytes(agent) / 2 ** 20)
    return result


def measure_memory(agent_name, config: PretrainConfig, device, threads, obs_dim, action_dim) -> dict:
    """:func:`memory_probe` in a fresh subprocess, given the whole run config as JSON."""
    spec = {"agent": agent_name, "config": to_dict(config), "device": str(device), "threads": threads,
            "obs_dim": obs_dim, "action_dim": action_dim}
    proc = subprocess.run([sys.executable, __file__, "--memory-probe", json.dumps(spec)],
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "failed"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ---------------------------------------------------------------------------------------------
# Learner and scaling


def learner_row(agent_name, config_name, config: PretrainConfig, perf, device, args, obs_dim, action_dim,
                peaks, memory: bool, breakdown: bool = True) -> dict:
    """One row: ``agent_name`` built from the run ``config`` with execution options ``perf``."""
    config = replace(config, perf=perf)
    sections = agent_sections(config)
    hidden = first_field(sections, "hidden_dim")
    start = time.perf_counter()
    # The peak right before and after the row's timing: on a shared (virtual) machine the matmul
    # speed drifts by tens of percent within minutes, so the row is compared with its own moment.
    dtypes = (torch.float32, torch.bfloat16) if perf.precision == "bf16" else (torch.float32,)
    local_peaks = {d: [matmul_peak(device, d, True, rounds=2)["gflops"]] for d in dtypes}
    agent, replay = build(agent_name, config, device, obs_dim, action_dim)
    needs = agent.replay_needs()
    heavy = (hidden or 0) * needs.batch_size >= 1024 * 1024
    warmup, repeats = (1, 2) if args.quick and heavy else (1, 3) if heavy else (2, 5) if args.quick else (3, 10)
    compile_s = None
    if perf.compile or perf.cuda_graphs:
        t0 = time.perf_counter()
        agent.update(needs.sample(replay))  # compiles
        sync(device)
        compile_s = time.perf_counter() - t0
    timing = time_updates(agent, replay, warmup, repeats, device)
    for d in dtypes:
        local_peaks[d].append(matmul_peak(device, d, True, rounds=2)["gflops"])
    flops = count_flops(agent, replay)
    breakdown = matmul_breakdown(agent, replay, 1 if heavy else 3, device) if breakdown else None
    threads = torch.get_num_threads()
    fp32_peak = max(local_peaks[torch.float32])
    dtype_peak = max(local_peaks[torch.bfloat16]) if perf.precision == "bf16" else fp32_peak
    run_fp32_peak = peaks[(device.type, "float32", threads)]
    gflops = flops / (timing["ms_per_update"] * 1e-3) / 1e9
    row = {
        "section": "learner", "agent": agent_name, "config": config_name, "device": str(device),
        "threads": torch.get_num_threads(),
        "precision": perf.precision, "compile": perf.compile, "cuda_graphs": perf.cuda_graphs,
        # Sizes for the table, read generically from the agent's own sections (None where the
        # agent has no such field); "sections" keeps them all.
        "hidden_dim": hidden, "feature_dim": first_field(sections, "feature_dim"),
        "backward_hidden_dim": first_field(sections, "backward_hidden_dim"),
        "batch_size": needs.batch_size, "nstep": needs.nstep, "skill_dim": agent.skill_dim,
        "contrastive_hidden_dim": first_field(sections, "contrastive_hidden_dim"),
        "rnd_rep_dim": first_field(sections, "rnd_rep_dim"), "sections": sections,
        "warmup": warmup, "repeats": repeats,
        **timing, "gflop_per_update": flops / 1e9, "gflops": gflops,
        "fraction_of_fp32_peak": gflops / fp32_peak, "fraction_of_dtype_peak": gflops / dtype_peak,
        "fp32_peak_local_gflops": fp32_peak, "dtype_peak_local_gflops": dtype_peak,
        "local_peak_runs": {str(d).replace("torch.", ""): v for d, v in local_peaks.items()},
        "fraction_of_run_start_fp32_peak": gflops / run_fp32_peak,
        "compile_s": compile_s, "compiled": agent.net_runner.compiled if compile_s is not None else None,
        "state_mb": state_bytes(agent) / 2 ** 20,
    }
    if breakdown is not None:
        row.update(breakdown)
        row["matmul_gflops"] = flops / (breakdown["matmul_ms_per_update"] * 1e-3) / 1e9
        row["matmul_share"] = breakdown["matmul_ms_per_update"] / breakdown["profiled_ms_per_update"]
    del agent, replay
    if memory:
        row["memory"] = measure_memory(agent_name, config, device, torch.get_num_threads(), obs_dim, action_dim)
    row["wall_s"] = time.perf_counter() - start
    return row


def skipped_configs(args) -> dict[str, list[str]]:
    """Learner configurations (rows and --compile rows) that do not apply to some of ``--agents``:
    config -> those agents (see :func:`config_applies`)."""
    names = args.configs.split(",") + (args.compile_configs.split(",") if args.compile else [])
    skipped = {}
    for name in dict.fromkeys(names):
        agents = [a for a in args.agent_list if not config_applies(name, a)]
        if agents:
            skipped[name] = agents
    return skipped


def skipped_note(skipped: dict[str, list[str]]) -> str | None:
    if not skipped:
        return None
    return "note: not run (the configuration overrides sections the agent lacks): " + "; ".join(
        f"{name} for {', '.join(agents)}" for name, agents in skipped.items())


def run_learner(args, devices, peaks, obs_dim, action_dim) -> list[dict]:
    """Every learner row, ``--rounds`` times round-robin (see :func:`merge_rounds`). A configuration
    runs only for the agents it applies to (:func:`config_applies`)."""
    specs = []
    precisions = [p for p in args.precisions.split(",") if p]
    for device in devices:
        for config_name in args.configs.split(","):
            for precision in precisions:
                for agent_name in args.agent_list:
                    if not config_applies(config_name, agent_name):
                        continue
                    for threads in args.thread_counts:
                        specs.append((device, config_name, PerfConfig(precision=precision), agent_name, threads))
        if args.compile:
            for config_name in args.compile_configs.split(","):
                for agent_name in args.agent_list:
                    if not config_applies(config_name, agent_name):
                        continue
                    perf = PerfConfig(compile=True, cuda_graphs=device.type == "cuda" and args.cuda_graphs)
                    specs.append((device, config_name, perf, agent_name, args.thread_counts[0]))
    note = skipped_note(skipped_configs(args))
    if note:
        print(f"  {note}", file=sys.stderr)
    rounds: dict[int, list[dict]] = {i: [] for i in range(len(specs))}
    for r in range(args.rounds):
        for i, (device, config_name, perf, agent_name, threads) in enumerate(specs):
            if r > 0 and perf.compile:
                continue  # compiled rows: one round (each round recompiles from scratch)
            torch.set_num_threads(threads)
            row = learner_row(agent_name, config_name, model_config(config_name, agent_name), perf, device, args,
                              obs_dim, action_dim, peaks, memory=r == 0 and not args.no_memory and not perf.compile,
                              breakdown=r == 0)
            rounds[i].append(row)
            print_progress(row)
    torch.set_num_threads(args.thread_counts[0])
    return [merge_rounds(rows) for rows in rounds.values()]


def merge_rounds(rows: list[dict]) -> dict:
    """One row from the rounds of a configuration: median over rounds of each round's median
    ms/update, the fastest update of any round, and the median of the per-round fractions of the
    local peak. The memory and profiler columns come from the first round."""
    row = dict(rows[0])
    row["rounds"] = len(rows)
    if len(rows) == 1:
        return row
    row["ms_per_update"] = statistics.median(r["ms_per_update"] for r in rows)
    row["ms_per_update_min"] = min(r["ms_per_update_min"] for r in rows)
    row["ms_per_sample"] = statistics.median(r["ms_per_sample"] for r in rows)
    row["ms_per_update_rounds"] = [r["ms_per_update"] for r in rows]
    row["ms_per_update_runs"] = [t for r in rows for t in r["ms_per_update_runs"]]
    row["gflops"] = row["gflop_per_update"] / (row["ms_per_update"] * 1e-3)
    for key in ("fraction_of_fp32_peak", "fraction_of_dtype_peak", "fp32_peak_local_gflops",
                "dtype_peak_local_gflops", "fraction_of_run_start_fp32_peak"):
        row[key] = statistics.median(r[key] for r in rows)
    row["local_peak_runs"] = [r["local_peak_runs"] for r in rows]
    row["wall_s"] = sum(r["wall_s"] for r in rows)
    return row


def run_scaling(args, devices, peaks, obs_dim, action_dim) -> list[dict]:
    rows = []
    hidden = [int(x) for x in args.scaling_hidden.split(",") if x]
    batches = [int(x) for x in args.scaling_batch.split(",") if x]
    for device in devices:
        for h in hidden:
            for n in batches:
                row = learner_row("dvfb", f"H{h}_N{n}", scaling_config(h, n, "dvfb"), PerfConfig(), device, args,
                                  obs_dim, action_dim, peaks, memory=False)
                row["section"] = "scaling"
                rows.append(row)
                print_progress(row)
    return rows


def print_progress(row: dict) -> None:
    print(f"  {row['section']} {row['agent']} {row['config']} {row['precision']} {row['threads']} threads"
          f"{' compiled' if row.get('compile') else ''} on {row['device']}: {row['ms_per_update']:.1f} ms/update, "
          f"{row['gflops']:.1f} GFLOP/s ({100 * row['fraction_of_fp32_peak']:.0f}% of fp32 peak)", file=sys.stderr)


# ---------------------------------------------------------------------------------------------
# Collector


def collector_runner(env, agent, replay: ReplayBuffer, action_dim: int, seed_phase: bool, seed: int,
                     update_z_every: int = 300, act=None):
    """Pre-training's rollout without the update (the one rollout loop with pre-training's replay
    writer and skill rule), as a function of n steps.

    ``act`` replaces ``agent.act`` (to time the torch-module acting path against the default).
    """
    act = agent.act if act is None else act
    lanes = [Lane(env, np.random.default_rng(seed), reward_key="task_reward")]

    def skill_rule(step: int, episode_start: bool, current):
        return agent.sample_skill(1)[0] if episode_start or step % update_z_every == 0 else current

    policy = Policy(lambda obs, skills: act(obs, skills, explore=True), [skill_rule],
                    (lambda step: True) if seed_phase else None)
    observers = [ReplayWriter(lanes, [replay])]
    state = {"step": 0}

    def run(n_steps: int) -> None:
        state["step"] = rollout(lanes, policy, observers, start=state["step"], stop=state["step"] + n_steps)

    return run


def run_collector(args, device) -> dict:
    sys.path.insert(0, str(HERE))
    import env_throughput  # noqa: E402  (bench/env_throughput.py)

    task = args.collector_task
    domain = envs.TASKS[task].domain
    obs_dim, action_dim = env_dims(domain)
    seconds = 1.0 if args.quick else 3.0
    repeats = 2 if args.quick else 3

    raw_env, raw_source = env_throughput.build_raw(task, 0)
    raw_env.reset()
    rng = np.random.default_rng(0)
    raw_actions = np.ascontiguousarray(rng.uniform(-1.0, 1.0, (4096, action_dim)))
    runners = {"raw dm_control": env_throughput.raw_runner(raw_env, raw_actions)}
    act_us = {}
    for name, preset in (("small", "small"), ("paper", "paper")):
        torch.manual_seed(0)
        agent = make_agent("dvfb", obs_dim, action_dim, model_config(preset, "dvfb"), device)
        z_dim = agent.skill_dim
        if name == "small":
            replay = ReplayBuffer(100_000, obs_dim, action_dim, z_dim,
                                  max_episode_length=envs.TASKS[task].episode_length, device=device)
            runners["seed phase (uniform action + env + replay)"] = collector_runner(
                envs.make(task, seed=0), agent, replay, action_dim, True, 0)
        replay = ReplayBuffer(100_000, obs_dim, action_dim, z_dim,
                              max_episode_length=envs.TASKS[task].episode_length, device=device)
        runners[f"acting, {name} actor (act + env + replay)"] = collector_runner(
            envs.make(task, seed=0), agent, replay, action_dim, False, 0)
        if name == "small" and device.type == "cpu":
            # The same loop with the actor run through its torch modules (the path before
            # HostActor, and still the path on CUDA), for a before/after in the same run.
            replay = ReplayBuffer(100_000, obs_dim, action_dim, z_dim,
                                  max_episode_length=envs.TASKS[task].episode_length, device=device)
            runners["acting, small actor, torch modules"] = collector_runner(
                envs.make(task, seed=0), agent, replay, action_dim, False, 0, act=agent.model._act_torch)
        obs = np.zeros((1, obs_dim), np.float32)
        z = agent.sample_skill(1)
        reps = 300 if args.quick else 1000
        paths = {f"{name} actor": agent.act}
        if device.type == "cpu":
            paths[f"{name} actor, torch modules"] = agent.model._act_torch
        for label, act in paths.items():
            for _ in range(50):
                act(obs, z, explore=True)
            start = time.perf_counter()
            for _ in range(reps):
                act(obs, z, explore=True)
            act_us[label] = 1e6 * (time.perf_counter() - start) / reps

    for run in runners.values():  # warm-up, and size the chunks from the raw speed
        run(200)
    start = time.perf_counter()
    runners["raw dm_control"](500)
    raw_rate = 500 / (time.perf_counter() - start)
    chunk = max(50, round(0.1 * raw_rate))
    total = max(1, round(seconds * raw_rate / chunk)) * chunk
    rates: dict[str, list[float]] = {k: [] for k in runners}
    for _ in range(repeats):
        for name, rate in env_throughput.matched_rates(runners, total, chunk).items():
            rates[name].append(rate)
    raw = statistics.median(rates["raw dm_control"])
    rows = [{"path": name, "steps_per_s": statistics.median(r), "ratio_to_raw": statistics.median(r) / raw,
             "runs": r} for name, r in rates.items()]
    return {"task": task, "raw_source": raw_source, "steps_per_repeat": total, "repeats": repeats,
            "device": str(device), "rows": rows, "act_us": act_us,
            "note": "raw dm_control is stepped with uniform random actions; the acting rows follow the "
                    "policy's trajectory, so physics cost can differ slightly between rows"}


# ---------------------------------------------------------------------------------------------
# End to end


def run_e2e(args, device) -> dict:
    frames, seed_frames = args.e2e_frames, args.e2e_seed_frames
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "run"
        cmd = [sys.executable, "-m", "dvfb", "pretrain", "--agent", args.e2e_agent, "--domain", args.e2e_domain,
               "--preset", "small", "--frames", str(frames), "--seed-frames", str(seed_frames),
               "--run-dir", str(run_dir), "--no-progress", "--log-every", "500",
               "--torch-threads", str(torch.get_num_threads()), "--device", device.type]
        start = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        wall = time.perf_counter() - start
        if proc.returncode != 0:
            return {"error": proc.stderr.strip()[-2000:], "command": " ".join(cmd)}
        summary = json.loads((run_dir / "pretrain_summary.json").read_text())
        lines = read_metrics(run_dir, "train")
    # train.jsonl's fps is cumulative since the start: t(step) = step / fps(step).
    times = {r["step"]: r["step"] / r["fps"] for r in lines if "fps" in r}
    steady = None
    logged = sorted(times)
    if len(logged) >= 2:
        first, last = logged[0], logged[-1]
        steady = (last - first) / (times[last] - times[first])
    updates = max(0, (frames - seed_frames + 1) // 2)
    return {"agent": args.e2e_agent, "domain": args.e2e_domain, "preset": "small", "frames": frames,
            "seed_frames": seed_frames, "updates": updates, "device": str(device),
            "frames_per_s": summary["frames_per_s"], "wall_clock_s_run": summary["wall_clock_s"],
            "wall_clock_s_process": wall, "training_phase_frames_per_s": steady,
            "training_phase_window": [logged[0], logged[-1]] if len(logged) >= 2 else None,
            "command": " ".join(cmd)}


# ---------------------------------------------------------------------------------------------
# Output


def table(rows: list[dict], columns) -> str:
    header = "| " + " | ".join(f"{t:{a}}" for t, _, a, _ in columns) + " |"
    widths = [len(f"{t:{a}}") for t, _, a, _ in columns]
    lines = [header, "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    for r in rows:
        cells = []
        for _, key, align, fmt in columns:
            value = key(r) if callable(key) else r.get(key)
            cells.append(f"{'-' if value is None else fmt.format(value):{align}}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def mem(key):
    return lambda r: r.get("memory", {}).get(key)


LEARNER_COLUMNS = (
    ("agent", "agent", "<12", "{}"), ("config", "config", "<14", "{}"), ("dev", "device", "<4", "{}"),
    ("thr", "threads", ">3", "{}"),
    ("prec", lambda r: r["precision"] + ("+compile" if r.get("compile") else ""), "<13", "{}"),
    ("H", "hidden_dim", ">4", "{}"), ("E", "feature_dim", ">3", "{}"), ("Hb", "backward_hidden_dim", ">3", "{}"),
    ("N", "batch_size", ">4", "{}"),
    ("ms/update", "ms_per_update", ">9", "{:.1f}"), ("min ms", "ms_per_update_min", ">7", "{:.1f}"),
    ("rounds: ms", lambda r: (" / ".join(f"{t:.0f}" for t in r["ms_per_update_rounds"])
                              if r.get("ms_per_update_rounds") else None), "<16", "{}"),
    ("sample ms", "ms_per_sample", ">9", "{:.2f}"), ("GFLOP", "gflop_per_update", ">7", "{:.2f}"),
    ("GFLOP/s", "gflops", ">7", "{:.1f}"), ("fp32 peak", "fp32_peak_local_gflops", ">9", "{:.0f}"),
    ("% fp32 peak", lambda r: 100 * r["fraction_of_fp32_peak"], ">11", "{:.0f}"),
    ("% dtype peak", lambda r: 100 * r["fraction_of_dtype_peak"], ">12", "{:.0f}"),
    ("mm ms", "matmul_ms_per_update", ">6", "{:.1f}"), ("mm GFLOP/s", "matmul_gflops", ">10", "{:.1f}"),
    ("mm share", lambda r: 100 * r["matmul_share"] if "matmul_share" in r else None, ">8", "{:.0f}%"),
    ("state MB", "state_mb", ">8", "{:.0f}"), ("peak MB", mem("peak_mb"), ">7", "{:.0f}"),
    ("update + MB", mem("update_added_mb"), ">11", "{:.0f}"), ("compile s", "compile_s", ">9", "{:.0f}"),
)
SCALING_COLUMNS = (
    ("H", "hidden_dim", ">4", "{}"), ("N", "batch_size", ">4", "{}"), ("dev", "device", "<4", "{}"),
    ("ms/update", "ms_per_update", ">9", "{:.1f}"), ("GFLOP", "gflop_per_update", ">7", "{:.2f}"),
    ("GFLOP/s", "gflops", ">7", "{:.1f}"), ("fp32 peak", "fp32_peak_local_gflops", ">9", "{:.0f}"),
    ("% fp32 peak", lambda r: 100 * r["fraction_of_fp32_peak"], ">11", "{:.0f}"),
    ("mm GFLOP/s", "matmul_gflops", ">10", "{:.1f}"),
)
COLLECTOR_COLUMNS = (("path", "path", "<48", "{}"), ("steps/s", "steps_per_s", ">8", "{:,.0f}"),
                     ("ratio to raw", "ratio_to_raw", ">12", "{:.3f}"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--only", default=",".join(DEFAULT_SECTIONS),
                        help="comma-separated sections: " + ", ".join(SECTIONS) + " (default: all but members, "
                             "which takes ~25 minutes on 2 cores)")
    parser.add_argument("--quick", action="store_true", help="fewer repetitions, a 2x2 scaling grid, shorter e2e")
    parser.add_argument("--threads", default=None,
                        help="torch threads (default: torch's default); a comma list (e.g. 1,2) repeats every "
                             "learner row per thread count, the other sections use the first")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"),
                        help="auto: CPU rows, plus CUDA rows when torch sees a GPU")
    parser.add_argument("--domain", default="walker", help="domain whose observation/action sizes the learner uses")
    parser.add_argument("--agents", default=",".join(agent_names()),
                        help="learner agents (default: every registered agent)")
    parser.add_argument("--configs", default="paper,small,hidden256,hidden256_wide",
                        help="learner configurations: " + ", ".join(CONFIGS) + " (paper and small apply to every "
                             "agent, the others only to agents with an fb / exploration section)")
    parser.add_argument("--precisions", default="fp32,bf16", help="learner precisions (fp32, bf16)")
    parser.add_argument("--compile", action="store_true", help="add torch.compile rows (slow to compile)")
    parser.add_argument("--compile-configs", default="small", help="configurations of the --compile rows")
    parser.add_argument("--cuda-graphs", action="store_true", help="with --compile on CUDA: CUDA-graph rows")
    parser.add_argument("--rounds", type=int, default=1,
                        help="time every learner row this many times, round-robin over the rows, and report the "
                             "median over rounds (a shared machine drifts by tens of percent within minutes)")
    parser.add_argument("--no-memory", action="store_true", help="skip the memory subprocesses")
    parser.add_argument("--scaling-hidden", default=None, help="hidden widths of the scaling grid (default 256,512,1024)")
    parser.add_argument("--scaling-batch", default=None, help="batch sizes of the scaling grid (default 256,512,1024,2048)")
    parser.add_argument("--collector-task", default="walker_walk")
    parser.add_argument("--e2e-agent", default="dvfb")
    parser.add_argument("--e2e-domain", default="walker")
    parser.add_argument("--e2e-frames", type=int, default=None, help="default 6000 (--quick: 3000); the "
                        "training-phase rate needs two logs (every 500 frames) after the seed frames")
    parser.add_argument("--e2e-seed-frames", type=int, default=2000)
    parser.add_argument("--output", type=Path, default=RESULTS_PATH, help="JSON output path")
    parser.add_argument("--memory-probe", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--members", default=",".join(map(str, members_bench.MEMBER_COUNTS)),
                        help="members section: group sizes N of the learner rows")
    parser.add_argument("--members-e2e-agents", default="fb,dvfb",
                        help="members section: agents of the end-to-end rows (empty: none)")
    parser.add_argument("--members-e2e-counts", default="5", help="members section: N of the end-to-end rows")
    parser.add_argument("--members-e2e-frames", type=int, default=3000, help="members section: frames per member")
    parser.add_argument("--members-e2e-seed-frames", type=int, default=1000)
    parser.add_argument("--members-probe", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.memory_probe is not None:
        print(json.dumps(memory_probe(json.loads(args.memory_probe))))
        return 0
    if args.members_probe is not None:
        print(json.dumps(members_bench.separate_probe(json.loads(args.members_probe), filled_replay)))
        return 0
    args.members_e2e_counts = [int(n) for n in args.members_e2e_counts.split(",") if n.strip()]

    sections = [s.strip() for s in args.only.split(",") if s.strip()]
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown:
        parser.error(f"unknown section(s) {unknown}; choose from {', '.join(SECTIONS)}")
    for name in args.configs.split(",") + (args.compile_configs.split(",") if args.compile else []):
        if name not in CONFIGS:
            parser.error(f"unknown config {name!r}; choose from {', '.join(CONFIGS)}")
    args.agent_list = [a.strip() for a in args.agents.split(",") if a.strip()]
    unknown = [a for a in args.agent_list if a not in agent_names()]
    if unknown or not args.agent_list:
        parser.error(f"unknown agent(s) {unknown}; choose from {', '.join(agent_names())}")
    try:
        args.thread_counts = [int(t) for t in args.threads.split(",")] if args.threads else [torch.get_num_threads()]
    except ValueError:
        parser.error(f"--threads expects integers, got {args.threads!r}")
    if min(args.thread_counts) < 1:
        parser.error("--threads must be >= 1")
    if args.rounds < 1:
        parser.error("--rounds must be >= 1")
    torch.set_num_threads(args.thread_counts[0])
    if args.scaling_hidden is None:
        args.scaling_hidden = "256,1024" if args.quick else "256,512,1024"
    if args.scaling_batch is None:
        args.scaling_batch = "256,1024" if args.quick else "256,512,1024,2048"
    if args.e2e_frames is None:
        args.e2e_frames = 3000 if args.quick else 6000  # logs every 500 frames after the seed frames
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: torch sees no CUDA device")
    devices = [torch.device("cpu")] if args.device in ("auto", "cpu") else []
    if args.device in ("auto", "cuda") and torch.cuda.is_available():
        devices.append(torch.device("cuda"))

    print(f"threads {args.thread_counts}, devices {[str(d) for d in devices]}, sections {sections}",
          file=sys.stderr)
    peaks, peak_rows = {}, []
    # The bf16 peak only when a bf16 learner row is requested: without bf16 matrix hardware one
    # 2048^3 bf16 product can take minutes.
    bf16_rows = "learner" in sections and "bf16" in args.precisions.split(",")
    peak_dtypes = (torch.float32, torch.bfloat16) if bf16_rows else (torch.float32,)
    for threads in args.thread_counts:  # the matmul peak with every thread count the rows use
        torch.set_num_threads(threads)
        for device in devices:
            for dtype in peak_dtypes:
                peak = matmul_peak(device, dtype, args.quick)
                peak.update(device=str(device), threads=threads)
                peaks[(device.type, str(dtype).replace("torch.", ""), threads)] = peak["gflops"]
                peak_rows.append(peak)
                print(f"  peak {device} {peak['dtype']} {peak['n']}^3 matmul, {threads} threads: "
                      f"{peak['gflops']:.1f} GFLOP/s", file=sys.stderr)
    torch.set_num_threads(args.thread_counts[0])

    obs_dim, action_dim = env_dims(args.domain)
    report: dict = {
        "benchmark": "learner",
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()
                     if k not in ("memory_probe", "agent_list")},
        "threads": args.thread_counts,
        "obs_dim": obs_dim, "action_dim": action_dim, "config_notes": CONFIG_NOTES,
        "machine": {"platform": platform.platform(), "python": platform.python_version(),
                    "cpu_count": os.cpu_count(), "torch": torch.__version__,
                    "bf16_matmul_hardware": {str(d): bf16_matmul_is_fast(d) for d in devices},
                    "cuda_device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None},
        "versions": {n: importlib.metadata.version(n) for n in ("torch", "numpy", "dm_control", "mujoco")},
        "peak": peak_rows,
    }
    out = []
    if "learner" in sections:
        report["learner"] = run_learner(args, devices, peaks, obs_dim, action_dim)
        report["learner_skipped"] = skipped_configs(args)
        note = skipped_note(report["learner_skipped"])
        out += ["## Learner (ms per agent.update; sample ms = replay.sample, not included; H = hidden_dim of "
                "the agent's first section with one, N = its replay_needs().batch_size)",
                table(report["learner"], LEARNER_COLUMNS), ""] + ([note, ""] if note else [])
        out += [f"- {k}: {v}" for k, v in CONFIG_NOTES.items()] + [""]
    if "scaling" in sections:
        report["scaling"] = run_scaling(args, devices, peaks, obs_dim, action_dim)
        out += ["## Scaling (DVFB, fp32; paper widths with H wherever the paper uses 1024)",
                table(report["scaling"], SCALING_COLUMNS), ""]
    if "collector" in sections:
        report["collector"] = run_collector(args, devices[0])
        c = report["collector"]
        out += [f"## Collector ({c['task']}, {c['device']}; pre-training loop body without updates)",
                table(c["rows"], COLLECTOR_COLUMNS),
                "agent.act per call: " + ", ".join(f"{k} {v:.0f} us" for k, v in c["act_us"].items()), ""]
    if "e2e" in sections:
        report["e2e"] = run_e2e(args, devices[0])
        e = report["e2e"]
        if "error" in e:
            out += ["## End to end: FAILED", e["error"], ""]
        else:
            steady = e["training_phase_frames_per_s"]
            out += [f"## End to end (dvfb pretrain, {e['agent']} {e['domain']} small, {e['frames']} frames, "
                    f"{e['seed_frames']} seed frames, {e['updates']} updates)",
                    f"frames/s over the run: {e['frames_per_s']:.1f}; training phase (steps "
                    f"{e['training_phase_window']}): {steady:.1f} frames/s" if steady else
                    f"frames/s over the run: {e['frames_per_s']:.1f}", ""]
    if "members" in sections:
        report["members"] = members_bench.run_members(args, devices[0], obs_dim, action_dim, model_config,
                                                      filled_replay)
        m = report["members"]
        out += ["## Members (small preset; one process with N stacked members against the best schedule of N "
                "separate processes on the same cores; docs/members.md)",
                table(m["learner"], members_bench.MEMBER_COLUMNS), ""]
        if m.get("func"):
            out += ["### Stacked blocks against torch.func (FB losses, forward + backward)",
                    table(m["func"], members_bench.FUNC_COLUMNS), ""]
        if m.get("e2e"):
            out += ["### End to end (dvfb pretrain --seeds against separate dvfb pretrain processes)",
                    table(m["e2e"], members_bench.E2E_COLUMNS), ""]
    peak_line = "; ".join(f"{p['device']} {p['dtype']} {p['threads']} thr: {p['gflops']:.1f} GFLOP/s"
                          for p in peak_rows)
    print(f"# dvfb learner benchmark (threads {args.thread_counts}; peak and sections other than the "
          f"learner with {args.thread_counts[0]})\nmatmul peak: {peak_line}\n")
    print("\n".join(out))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
