"""Env steps per second: dvfb.envs.make versus raw dm_control, measured in the same process.

For each task, the same pre-drawn sequence of uniform random actions drives

* raw: the dm_control environment without any wrapper, stepped with float64 actions already mapped
  to the actuator bounds. For stock (domain, task) pairs this is ``suite.load``; for custom tasks
  (e.g. the maze, which the stock suite lacks) it is dvfb's own dm_control builder, unwrapped.
* dvfb: ``dvfb.envs.make(task)``, stepped with float32 actions in [-1, 1].

Both loops reset when the episode ends (dm_control's LAST step / gymnasium ``truncated``), so reset
cost is included in both. Since actions and seeds match bit for bit, both sides follow the same
trajectory. Each repetition runs the same number of steps (about ``--seconds`` of raw stepping) on
both sides, in alternating chunks of about ``--slice`` seconds, so that neither trajectory-dependent
physics cost nor load from other processes on a shared machine favours one side. Reported: the
median over repetitions of each side's steps/s, and the median of the per-repetition ratios
dvfb / raw. Also reported: the wrapper's own cost per step, timed with the physics stubbed out, and
the ratio that cost alone implies at the raw speed (a noise-free cross-check of the ratio).

Usage: python bench/env_throughput.py [--seconds 1.5] [--repeats 3] [--tasks walker_walk,...]
Writes bench/results/env_throughput.json.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.metadata
import json
import os
import platform
import statistics
import sys
import time
import timeit
from pathlib import Path

# isort: off
import dvfb.envs as envs  # before dm_control: sets the headless MUJOCO_GL default
# isort: on

import numpy as np
from dm_control import suite

from dvfb.envs.registry import domain_module

DEFAULT_TASKS = (
    "walker_walk",
    "quadruped_walk",
    "hopper_hop",
    "cheetah_run",
    "point_mass_maze_reach_top_left",
)
ACTION_POOL = 4096  # pre-drawn actions, cycled
RESULTS_PATH = Path(__file__).resolve().parent / "results" / "env_throughput.json"


def build_raw(task_name: str, seed: int):
    """The unwrapped dm_control env of a task, and where it came from."""
    spec = envs.TASKS[task_name]
    if (spec.domain, spec.task) in suite.ALL_TASKS:
        return suite.load(spec.domain, spec.task, task_kwargs={"random": seed}), "suite.load"
    module = domain_module(spec.domain)
    return module.build_environment(spec.task, seed=seed), "dvfb dm_control builder (unwrapped)"


def raw_runner(raw_env, actions: np.ndarray):
    """A function running n steps of the raw dm_control env, resetting on its LAST step."""
    step, reset = raw_env.step, raw_env.reset
    n_actions = len(actions)
    position = {"index": 0}

    def run(n_steps: int) -> None:
        index = position["index"]
        for _ in range(n_steps):
            if step(actions[index]).last():
                reset()
            index = (index + 1) % n_actions
        position["index"] = index

    return run


def dvfb_runner(env, actions: np.ndarray):
    """A function running n steps of the dvfb env, resetting when it truncates."""
    step, reset = env.step, env.reset
    n_actions = len(actions)
    position = {"index": 0}

    def run(n_steps: int) -> None:
        index = position["index"]
        for _ in range(n_steps):
            if step(actions[index])[3]:
                reset()
            index = (index + 1) % n_actions
        position["index"] = index

    return run


def matched_rates(runners: dict, total_steps: int, chunk_steps: int) -> dict[str, float]:
    """Steps/s of each runner over the same ``total_steps`` steps, run in alternating chunks.

    Every runner executes the same steps of the same trajectory (same seed and actions, so the
    same contacts and resets), chunk by chunk in turn, and the first runner alternates; so neither
    trajectory-dependent physics cost nor load from other processes favours one side.
    """
    elapsed = dict.fromkeys(runners, 0.0)
    names = list(runners)
    done = turn = 0
    while done < total_steps:
        for name in names if turn % 2 == 0 else names[::-1]:
            start = time.perf_counter()
            runners[name](chunk_steps)
            elapsed[name] += time.perf_counter() - start
        done += chunk_steps
        turn += 1
    return {name: done / elapsed[name] for name in names}


def wrapper_overhead_seconds(env, action: np.ndarray, calls: int = 5000) -> float:
    """Seconds per ``env.step`` spent in dvfb's wrapper alone (best of 5 batches).

    The dm_control step is replaced by a stub that returns one fixed time step, so this isolates
    the wrapper's own work (action checks and scaling, flattening, the return tuple) from physics
    and from noise in the physics timing. The stub's own call cost is subtracted.
    """
    dmc_env = env.unwrapped.dmc_env
    env.reset()
    fixed_time_step = dmc_env.step(np.asarray(action, np.float64))

    class FixedStep:
        def step(self, _action):
            return fixed_time_step

    stub = FixedStep()
    env.unwrapped.dmc_env = stub
    try:
        wrapped = min(timeit.repeat(lambda: env.step(action), number=calls, repeat=5)) / calls
        bare = min(timeit.repeat(lambda: stub.step(action), number=calls, repeat=5)) / calls
    finally:
        env.unwrapped.dmc_env = dmc_env
    return max(0.0, wrapped - bare)


def bench_task(
    task_name: str, seconds: float, repeats: int, slice_seconds: float, seed: int
) -> dict:
    env = envs.make(task_name, seed=seed)
    raw_env, raw_source = build_raw(task_name, seed)

    # The same actions for both, bit for bit as MuJoCo receives them: float32 in [-1, 1] for dvfb;
    # for raw, their float64 image under the URLB affine map (docs/tasks.md §3.5), which is the plain
    # float64 value for [-1, 1] actuators. Both sides therefore follow one identical trajectory.
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1.0, 1.0, size=(ACTION_POOL, env.action_space.shape[0]))
    actions = actions.astype(np.float32)
    bounds = raw_env.action_spec()
    low = np.broadcast_to(np.asarray(bounds.minimum, np.float64), actions.shape[1:])
    high = np.broadcast_to(np.asarray(bounds.maximum, np.float64), actions.shape[1:])
    raw_actions = actions.astype(np.float64)
    if not (np.all(low == -1.0) and np.all(high == 1.0)):
        raw_actions = low + (high - low) / 2.0 * (raw_actions + 1.0)
    raw_actions = np.ascontiguousarray(raw_actions)

    env.reset()
    raw_env.reset()
    runners = {"raw": raw_runner(raw_env, raw_actions), "dvfb": dvfb_runner(env, actions)}
    # Warm-up, which also sizes the work: chunks of ~slice_seconds, ~seconds per side per repeat.
    warmup_steps = 200
    start = time.perf_counter()
    runners["raw"](warmup_steps)
    raw_estimate = warmup_steps / (time.perf_counter() - start)
    runners["dvfb"](warmup_steps)
    chunk_steps = max(10, round(slice_seconds * raw_estimate))
    total_steps = max(1, round(seconds * raw_estimate / chunk_steps)) * chunk_steps

    overhead_s = wrapper_overhead_seconds(envs.make(task_name, seed=seed), actions[0])

    raw_rates, dvfb_rates, ratios = [], [], []
    for _ in range(repeats):
        rates = matched_rates(runners, total_steps, chunk_steps)
        raw_rates.append(rates["raw"])
        dvfb_rates.append(rates["dvfb"])
        ratios.append(rates["dvfb"] / rates["raw"])
    return {
        "task": task_name,
        "raw_source": raw_source,
        "steps_per_repeat": total_steps,
        "chunk_steps": chunk_steps,
        "raw_steps_per_s": statistics.median(raw_rates),
        "dvfb_steps_per_s": statistics.median(dvfb_rates),
        "ratio": statistics.median(ratios),
        "wrapper_overhead_us_per_step": overhead_s * 1e6,
        # The ratio the wrapper's own cost alone implies at the median raw speed (noise-free).
        "overhead_implied_ratio": 1.0 / (1.0 + overhead_s * statistics.median(raw_rates)),
        "raw_runs": raw_rates,
        "dvfb_runs": dvfb_rates,
        "ratio_runs": ratios,
    }


def format_table(results: list[dict]) -> str:
    columns = (
        ("task", "task", "<32", "{}"),
        ("raw steps/s", "raw_steps_per_s", ">11", "{:,.0f}"),
        ("dvfb steps/s", "dvfb_steps_per_s", ">12", "{:,.0f}"),
        ("ratio", "ratio", ">5", "{:.3f}"),
        ("wrapper us/step", "wrapper_overhead_us_per_step", ">15", "{:.1f}"),
        ("implied ratio", "overhead_implied_ratio", ">13", "{:.3f}"),
    )
    header = "| " + " | ".join(f"{title:{align}}" for title, _, align, _ in columns) + " |"
    widths = [len(f"{title:{align}}") for title, _, align, _ in columns]
    lines = [header, "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    for r in results:
        cells = [f"{fmt.format(r[key]):{align}}" for _, key, align, fmt in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=1.5, help="seconds per timed run")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per side and task")
    parser.add_argument(
        "--slice", type=float, default=0.1, help="seconds per alternating raw/dvfb chunk of steps"
    )
    parser.add_argument(
        "--tasks",
        default=",".join(DEFAULT_TASKS),
        help="comma-separated task names (default: one per domain)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=RESULTS_PATH, help="JSON output path")
    args = parser.parse_args(argv)

    task_names = [t.strip() for t in args.tasks.split(",") if t.strip()]
    for name in task_names:
        envs.resolve_task(name)  # ConfigError with the valid names if unknown

    results = []
    for name in task_names:
        result = bench_task(name, args.seconds, args.repeats, args.slice, args.seed)
        results.append(result)
        print(
            f"{name}: raw {result['raw_steps_per_s']:,.0f}/s, "
            f"dvfb {result['dvfb_steps_per_s']:,.0f}/s, ratio {result['ratio']:.3f}, "
            f"wrapper {result['wrapper_overhead_us_per_step']:.1f} us/step",
            file=sys.stderr,
        )
    print(format_table(results))

    report = {
        "benchmark": "env_throughput",
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "settings": {
            "seconds": args.seconds,
            "repeats": args.repeats,
            "slice_seconds": args.slice,
            "seed": args.seed,
            "statistic": "median over repeats; ratio = median of per-repeat dvfb / raw",
        },
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpu_count": os.cpu_count(),
            "MUJOCO_GL": os.environ.get("MUJOCO_GL"),
        },
        "versions": {
            name: importlib.metadata.version(name)
            for name in ("dm_control", "mujoco", "numpy", "gymnasium")
        },
        "results": results,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
