"""bf16 versus fp32 learning curves: is the bf16 option within seed noise of fp32?

The performance issue allows ``--perf.precision bf16`` as the default only if a short training
run shows the same learning curves as fp32 within seed noise. This script pre-trains DVFB with
both precisions and several seeds (``dvfb pretrain``, small preset by default), then compares
every logged training metric:

* per logged step, the precision gap ``|mean_bf16 - mean_fp32|`` (means over seeds) against the
  seed spread ``max(range over seeds of fp32, range over seeds of bf16)`` at that step;
* over the second half of the training phase, the same with per-run means.

A metric is "within seed noise" when its second-half gap is at most the second-half seed spread.
Results: a markdown table on stdout and ``comparison.json`` + ``curves.png`` in ``--out``.

    python scripts/precision_check.py --frames 12000 --seeds 0,1 --out runs/precision_check
    python scripts/precision_check.py --out runs/precision_check --compare-only

Runs already complete in ``--out`` are reused. ``--parallel 2`` runs two trainings at a time with
one torch thread each (the development machine has two cores).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from dvfb.runs import read_metrics

PRECISIONS = ("fp32", "bf16")
METRICS = ("fb_loss", "fb_diag", "fb_offdiag", "ortho_loss", "fb_q_loss", "actor_loss", "skill_value",
           "rnd_loss", "nce_loss", "rnd_reward", "ce_reward", "intrinsic_reward", "exploration_critic_loss",
           "exploration_value")


def run_name(precision: str, seed: int) -> str:
    return f"{precision}_s{seed}"


def pretrain(args, precision: str, seed: int) -> None:
    run = args.out / run_name(precision, seed)
    summary = run / "pretrain_summary.json"
    if summary.exists() and json.loads(summary.read_text())["frames"] >= args.frames:
        print(f"== {run} already complete", flush=True)
        return
    cmd = [sys.executable, "-m", "dvfb", "pretrain", "--agent", "dvfb", "--domain", args.domain,
           "--preset", args.preset, "--frames", str(args.frames), "--seed", str(seed),
           "--perf.precision", precision, "--run-dir", str(run), "--torch-threads", str(args.threads),
           "--log-every", str(args.log_every), "--no-progress", "--overwrite"]
    print("== " + " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def load_curves(args) -> dict[tuple[str, int], dict[int, dict]]:
    """(precision, seed) -> {step: logged training record} of every run."""
    return {(p, s): {row["step"]: row for row in read_metrics(args.out / run_name(p, s), "train")}
            for p in PRECISIONS for s in args.seeds}


def compare(args, curves: dict) -> dict:
    steps = sorted(set.intersection(*(set(c) for c in curves.values())))
    if len(steps) < 2:
        raise SystemExit(f"{args.out}: fewer than two logged steps common to every run")
    second_half = steps[len(steps) // 2:]
    report = {"steps": steps, "seeds": args.seeds, "metrics": {}}
    for metric in METRICS:
        if not all(metric in curves[key][steps[0]] for key in curves):
            continue

        def values(p, step_list):
            return [statistics.fmean(curves[(p, s)][t][metric] for t in step_list) for s in args.seeds]

        per_step_within = 0
        for t in steps:
            by_p = {p: values(p, [t]) for p in PRECISIONS}
            gap = abs(statistics.fmean(by_p["bf16"]) - statistics.fmean(by_p["fp32"]))
            spread = max(max(v) - min(v) for v in by_p.values())
            per_step_within += gap <= spread
        late = {p: values(p, second_half) for p in PRECISIONS}
        gap = abs(statistics.fmean(late["bf16"]) - statistics.fmean(late["fp32"]))
        spread = max(max(v) - min(v) for v in late.values())
        report["metrics"][metric] = {
            "second_half_fp32": late["fp32"], "second_half_bf16": late["bf16"],
            "second_half_gap": gap, "second_half_seed_spread": spread, "within_seed_noise": gap <= spread,
            "logged_steps_within_seed_noise": per_step_within, "logged_steps": len(steps)}
    return report


def plot(args, report: dict, curves: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = list(report["metrics"])
    cols = 4
    rows = -(-len(metrics) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.8 * rows), squeeze=False)
    colours = {"fp32": "tab:blue", "bf16": "tab:orange"}
    for ax, metric in zip(axes.flat, metrics):
        for p in PRECISIONS:
            for i, s in enumerate(args.seeds):
                c = curves[(p, s)]
                ts = sorted(c)
                ax.plot(ts, [c[t][metric] for t in ts], color=colours[p], alpha=0.8,
                        linestyle="-" if i == 0 else "--", label=f"{p} seed {s}")
        ax.set_title(metric, fontsize=9)
        ax.tick_params(labelsize=7)
        if metric in ("fb_q_loss", "ortho_loss", "exploration_critic_loss"):
            ax.set_yscale("symlog")
    for ax in list(axes.flat)[len(metrics):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(f"DVFB {args.domain}, {args.preset} preset: bf16 (orange) vs fp32 (blue), "
                 f"seeds {','.join(map(str, args.seeds))}", fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out / "curves.png", dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("runs/precision_check"))
    parser.add_argument("--domain", default="walker")
    parser.add_argument("--preset", default="small")
    parser.add_argument("--frames", type=int, default=12000)
    parser.add_argument("--seeds", default="0,1", help="comma-separated seeds (at least two)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per training")
    parser.add_argument("--parallel", type=int, default=2, help="trainings at a time")
    parser.add_argument("--log-every", type=int, default=500)
    parser.add_argument("--compare-only", action="store_true", help="do not train; compare the runs in --out")
    args = parser.parse_args(argv)
    args.seeds = [int(s) for s in args.seeds.split(",") if s]
    if len(args.seeds) < 2:
        parser.error("--seeds needs at least two seeds: the seed spread is the yardstick")
    if not args.compare_only:
        args.out.mkdir(parents=True, exist_ok=True)
        jobs = [(p, s) for s in args.seeds for p in PRECISIONS]
        with ThreadPoolExecutor(max_workers=args.parallel) as pool:
            for future in [pool.submit(pretrain, args, p, s) for p, s in jobs]:
                future.result()
    curves = load_curves(args)
    report = compare(args, curves)
    report.update(domain=args.domain, preset=args.preset, frames=args.frames)
    (args.out / "comparison.json").write_text(json.dumps(report, indent=2) + "\n")
    plot(args, report, curves)
    print("| metric | fp32 (2nd half, per seed) | bf16 (2nd half, per seed) | gap | seed spread | "
          "within noise | logged steps within |")
    print("|---|---|---|---:|---:|---|---:|")
    for metric, m in report["metrics"].items():
        fmt = lambda v: ", ".join(f"{x:.4g}" for x in v)  # noqa: E731
        print(f"| {metric} | {fmt(m['second_half_fp32'])} | {fmt(m['second_half_bf16'])} | "
              f"{m['second_half_gap']:.4g} | {m['second_half_seed_spread']:.4g} | "
              f"{'yes' if m['within_seed_noise'] else 'no'} | "
              f"{m['logged_steps_within_seed_noise']}/{m['logged_steps']} |")
    print(f"\nwrote {args.out / 'comparison.json'} and {args.out / 'curves.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
