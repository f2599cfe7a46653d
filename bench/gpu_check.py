"""The GPU acceptance check: does every method run on this device, how fast, and what would the
paper's scale cost here? One command, a table and a JSON file (bench/README.md, "GPU check").

    python bench/gpu_check.py                       # on CUDA: the whole check (sized for <= 8 min on one H200)
    python bench/gpu_check.py --device cpu --quick  # the same code path on the CPU, in about a minute

Sections:

* ``machine`` -- torch, MuJoCo, dm_control and numpy versions, the CPU and the GPUs
  (dvfb.runs.machine), and the TF32 switches (off: fp32 is IEEE float32, docs/methods.md "perf").
* ``peak`` -- the device's measured fp32 matrix-multiply peak (bench/learner.py's measurement);
  every GFLOP/s below is also given as a percentage of it.
* ``methods`` -- every registered method, built from its preset (``paper``; ``small`` with
  ``--quick``), timed over ``--updates`` updates after a warm-up, in fp32: eager, with
  ``--perf.compile`` and with ``--perf.cuda-graphs`` (CUDA only). Per row: ms/update (median),
  GFLOP per update (torch's FLOP counter on one eager update), GFLOP/s and % of the peak, the
  device memory the updates peaked at (CUDA), and whether it ran. A compiled variant is skipped,
  and says so, once ``--compile-budget-s`` seconds of compilation have been spent.
* ``groups`` -- DVFB and FB as groups of ``--seeds`` seeds (5; 2 with ``--quick``) through the
  pre-training workflow itself, at the same preset, for ``--frames`` frames: frames/s of the
  group, member-updates/s, device memory, and the steady rate after the seed frames (from the runs'
  own ``fps`` records).
* ``projection`` -- the wall time of 2M frames x 5 seeds for DVFB and FB on this device as one
  group: ``2M / steady rate`` (every frame at the training rate, so at most the seed frames' share
  too high). A projection from a measured rate, not a measurement.

Exit status: 0 when every row ran, 1 when one failed (its error is in the table and the JSON),
2 for bad input (``--device cuda`` without a CUDA device).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

# isort: off
import learner as lb  # noqa: E402 - bench/learner.py: builds, timing, FLOPs, the peak (imports dvfb.envs first)
# isort: on

import torch  # noqa: E402

from dvfb.agents import agent_names  # noqa: E402
from dvfb.core.config import replace  # noqa: E402
from dvfb.nets.execution import PerfConfig, set_tf32  # noqa: E402
from dvfb.runs import read_metrics  # noqa: E402
from dvfb.runs import machine  # noqa: E402
from dvfb.runs.presets import preset_config  # noqa: E402

RESULTS_PATH = HERE / "results" / "gpu_check.json"
PAPER_FRAMES, PAPER_SEEDS = 2_000_000, 5
VARIANTS = ("eager", "compile", "cuda_graphs")
GROUP_AGENTS = ("dvfb", "fb")


def variant_perf(variant: str) -> PerfConfig:
    return PerfConfig(compile=variant != "eager", cuda_graphs=variant == "cuda_graphs")


def cuda_memory_reset(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)


def cuda_memory_mb(device: torch.device) -> float | None:
    return torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else None


def method_row(agent: str, variant: str, preset: str, device: torch.device, dims: tuple[int, int],
               args, flops: dict, peak: float) -> dict:
    """One method in one variant: build, warm up (compiles), time; the error text if it fails."""
    row = {"agent": agent, "variant": variant, "preset": preset}
    try:
        config = replace(preset_config(preset, agent), device=device.type)
        cuda_memory_reset(device)
        agent_obj, replay = lb.build(agent, config, device, *dims, perf=variant_perf(variant))
        if agent not in flops:  # eager FLOPs of one update (the same for every variant)
            flops[agent] = lb.count_flops(agent_obj, replay)
        started = time.perf_counter()
        timing = lb.time_updates(agent_obj, replay, args.warmup, args.updates, device)
        row["warmup_and_timing_s"] = time.perf_counter() - started
        gflop = flops[agent] / 1e9
        gflops = gflop / (timing["ms_per_update"] / 1e3)
        row.update(status="ok", ms_per_update=timing["ms_per_update"], gflop_per_update=gflop, gflops=gflops,
                   percent_of_peak=100 * gflops / peak, memory_mb=cuda_memory_mb(device), updates=args.updates)
    except Exception as exc:  # noqa: BLE001 - an acceptance check reports every failure and goes on
        row.update(status="error", error=f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}",
                   traceback=traceback.format_exc(limit=6))
    return row


def run_methods(args, device: torch.device, peak: float) -> list[dict]:
    preset = "small" if args.quick else "paper"
    dims = lb.env_dims(args.domain)
    agents = args.agents.split(",") if args.agents else agent_names()
    flops: dict[str, int] = {}
    rows, compile_spent = [], 0.0
    for variant in VARIANTS:
        for agent in agents:
            if variant == "cuda_graphs" and device.type != "cuda":
                rows.append({"agent": agent, "variant": variant, "preset": preset, "status": "skipped",
                             "error": "CUDA graphs exist on CUDA only"})
                continue
            if variant != "eager" and (args.quick or compile_spent > args.compile_budget_s):
                why = "--quick" if args.quick else f"compile budget of {args.compile_budget_s:g} s spent"
                rows.append({"agent": agent, "variant": variant, "preset": preset, "status": "skipped", "error": why})
                continue
            row = method_row(agent, variant, preset, device, dims, args, flops, peak)
            if variant != "eager":
                compile_spent += row.get("warmup_and_timing_s", 0.0)
            rows.append(row)
            print_row(row)
    return rows


def steady_rate(run: Path, seed_frames: int) -> float | None:
    """Frames/s between the first and the last ``train`` record after the seed frames; each record's
    ``fps`` is its step over the time since the run started, so ``step / fps`` is that time."""
    records = [r for r in read_metrics(run, "train") if r.get("step", 0) > seed_frames and r.get("fps")]
    if len(records) < 2:
        return None
    first, last = records[0], records[-1]
    elapsed = last["step"] / last["fps"] - first["step"] / first["fps"]
    return (last["step"] - first["step"]) / elapsed if elapsed > 0 else None


def group_row(agent: str, args, device: torch.device, root: Path) -> dict:
    from dvfb.workflows.pretrain import pretrain

    preset = "small" if args.quick else "paper"
    seeds = list(range(args.seeds))
    seed_frames, frames = args.seed_frames, args.frames
    row = {"agent": agent, "preset": preset, "members": len(seeds), "frames": frames, "seed_frames": seed_frames}
    config = replace(preset_config(preset, agent), device=device.type, frames=frames, seed_frames=seed_frames,
                     log_every=max(1, (frames - seed_frames) // 4), checkpoint_every=10 * frames,
                     snapshot_frames=[], domain=args.domain, torch_threads=args.threads)
    try:
        cuda_memory_reset(device)
        started = time.perf_counter()
        runs = pretrain(config, [root / f"{agent}_s{s}" for s in seeds], seeds=seeds, progress=False)
        wall = time.perf_counter() - started
        updates = (frames - seed_frames) // config.update_every
        steady = steady_rate(runs[0].path, seed_frames)
        row.update(status="ok", wall_s=wall, frames_per_s=frames / wall,
                   member_updates_per_s=len(seeds) * updates / wall, update_every=config.update_every,
                   steady_frames_per_s=steady, memory_mb=cuda_memory_mb(device))
        if steady:
            # Every frame at the training rate: an upper bound by at most seed_frames / steady (the
            # uniform-action seed frames run faster).
            row["projection"] = {"frames": PAPER_FRAMES, "seeds": len(seeds), "hours": PAPER_FRAMES / steady / 3600,
                                 "how": "2M frames at this group's measured steady training rate"}
    except Exception as exc:  # noqa: BLE001 - reported, the check goes on
        row.update(status="error", error=f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}",
                   traceback=traceback.format_exc(limit=6))
    print_group(row)
    return row


def print_row(row: dict) -> None:
    if row["status"] != "ok":
        print(f"  {row['agent']:<14} {row['variant']:<12} {row['status']}: {row.get('error', '')}", flush=True)
        return
    memory = f"{row['memory_mb']:9.1f}" if row.get("memory_mb") is not None else f"{'-':>9}"
    print(f"  {row['agent']:<14} {row['variant']:<12} {row['ms_per_update']:9.2f} {row['gflop_per_update']:8.3f} "
          f"{row['gflops']:9.1f} {row['percent_of_peak']:6.1f}% {memory}", flush=True)


def print_group(row: dict) -> None:
    if row["status"] != "ok":
        print(f"  {row['agent']:<6} x{row['members']}: {row['status']}: {row.get('error', '')}", flush=True)
        return
    steady = f"{row['steady_frames_per_s']:.1f}" if row.get("steady_frames_per_s") else "-"
    memory = f"{row['memory_mb']:.1f} MB" if row.get("memory_mb") is not None else "-"
    projection = f"{row['projection']['hours']:.1f} h" if row.get("projection") else "-"
    print(f"  {row['agent']:<6} x{row['members']}: {row['frames_per_s']:.1f} frames/s, {row['member_updates_per_s']:.1f} "
          f"member-updates/s, steady {steady} frames/s, memory {memory}; 2M frames x {row['members']} seeds: "
          f"{projection}", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--device", default="cuda", choices=("cuda", "cpu"), help="device to check")
    parser.add_argument("--quick", action="store_true",
                        help="small preset, 3 updates, no compiled variants, groups of 2 for 400 frames")
    parser.add_argument("--agents", default="", help="comma-separated methods (default: every registered one)")
    parser.add_argument("--domain", default="walker", help="domain whose sizes the methods and groups use")
    parser.add_argument("--updates", type=int, default=None, help="timed updates per row (default 300; 3 --quick)")
    parser.add_argument("--warmup", type=int, default=None, help="untimed updates first (default 20; 1 --quick)")
    parser.add_argument("--compile-budget-s", type=float, default=240.0,
                        help="seconds of compiled rows after which the remaining compiled rows are skipped")
    parser.add_argument("--seeds", type=int, default=None, help="members of each group (default 5; 2 --quick)")
    parser.add_argument("--frames", type=int, default=None, help="frames of each group (default 6000; 400 --quick)")
    parser.add_argument("--seed-frames", type=int, default=None, help="uniform-action frames first (default 2000; 100 --quick)")
    parser.add_argument("--threads", type=int, default=0,
                        help="torch CPU threads (0: torch's default); 1 where other processes share the cores")
    parser.add_argument("--output", default=str(RESULTS_PATH), help="JSON file to write")
    args = parser.parse_args(argv)
    quick = args.quick
    defaults = {"updates": (300, 3), "warmup": (20, 1), "seeds": (PAPER_SEEDS, 2), "frames": (6000, 400),
                "seed_frames": (2000, 100)}
    for name, (full, short) in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, short if quick else full)
    for name in ("updates", "seeds", "frames"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1")
    if args.warmup < 0 or not 0 <= args.seed_frames < args.frames:
        parser.error("--warmup must be >= 0 and --seed-frames from 0 to below --frames")
    unknown = [a for a in args.agents.split(",") if a and a not in agent_names()]
    if unknown:
        parser.error(f"unknown method(s) {', '.join(unknown)}; registered: {', '.join(agent_names())}")
    if args.device == "cuda" and not torch.cuda.is_available():
        print("gpu_check: torch sees no CUDA device; `--device cpu --quick` checks the same code on the CPU",
              file=sys.stderr)
        return 2
    if args.threads < 0:
        parser.error("--threads must be >= 0")
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    if device.type == "cuda":
        set_tf32(False)  # the check measures IEEE fp32, the default of every run
    started = time.perf_counter()
    report = {"when": time.strftime("%Y-%m-%d %H:%M:%S"), "command": ["python", "bench/gpu_check.py", *(argv or sys.argv[1:])],
              "quick": quick, "machine": machine.describe(),
              "tf32": {"matmul": torch.backends.cuda.matmul.fp32_precision,
                       "cudnn_conv": torch.backends.cudnn.conv.fp32_precision}}
    report["peak"] = lb.matmul_peak(device, torch.float32, quick=True)
    peak = report["peak"]["gflops"]
    print(f"gpu_check on {device} ({', '.join(report['machine']['gpus']) or report['machine']['cpu']['model']}): "
          f"fp32 matmul peak {peak:.0f} GFLOP/s", flush=True)
    print(f"  {'method':<14} {'variant':<12} {'ms/upd':>9} {'GFLOP':>8} {'GFLOP/s':>9} {'%peak':>7} {'mem MB':>9}")
    report["methods"] = run_methods(args, device, peak)
    print("groups:", flush=True)
    with tempfile.TemporaryDirectory(prefix="dvfb_gpu_check_") as tmp:
        report["groups"] = [group_row(agent, args, device, Path(tmp)) for agent in GROUP_AGENTS]
    report["wall_s"] = time.perf_counter() - started
    failed = [f"{r['agent']} {r.get('variant', 'group')}" for r in report["methods"] + report["groups"]
              if r["status"] == "error"]
    report["failed"] = failed
    output = Path(args.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps(report, indent=1, default=str) + "\n")
    print(f"{len(report['methods'])} method rows, {len(report['groups'])} groups in {report['wall_s']:.0f} s; "
          f"{'all ran' if not failed else 'FAILED: ' + ', '.join(failed)}; {output}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
