"""A group's default schedule against the alternatives, end to end (README.md, "Threads and
progress"; bench/README.md, "The default schedule of a group").

For each method and group size N, the wall clock of ``dvfb pretrain --seeds 0..N-1`` (small preset,
``--frames`` per member of which ``--seed-frames`` uniform) in each schedule, one after the other:

* ``default``: no thread or process flag and no ``OMP_NUM_THREADS`` (what a user gets);
* ``threads``: one process, ``--torch-threads`` = the CPUs;
* ``processes``: ``--processes`` = the CPUs (one thread each);
* ``separate``: N ordinary runs, ``--torch-threads 1``, as many at a time as there are CPUs (the
  best schedule of separate runs on this machine: bench/README.md, "A group split over processes").

member-frames/s = N x frames / wall; "vs separate" is that of the separate schedule measured in the
same run. With ``--busy``, the default group of each size also runs beside one busy single-thread
process (a Python loop), and its rate is set against the idle default's:

    python bench/group_schedule.py                                   # dvfb, fb; N = 2, 4, 5
    python bench/group_schedule.py --agents dvfb --members 4 --busy  # the issue's row
    python bench/group_schedule.py --members 2,5 --no-all-schedules  # the default and the separate runs only

Writes ``bench/results/group_schedule.json``. Run it on an idle machine: every figure is a wall clock.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from dvfb.runs.machine import cores, describe

sys.path.insert(0, str(Path(__file__).resolve().parent))
from members import _timed as timed  # noqa: E402 - bench/members.py: the commands' wall clock

RESULTS = Path(__file__).resolve().parent / "results" / "group_schedule.json"


def _command(agent: str, args, run_dir: Path, seeds: list[int], flags: list[str]) -> list[str]:
    cmd = [sys.executable, "-m", "dvfb", "pretrain", "--agent", agent, "--domain", args.domain, "--preset", "small",
           "--frames", str(args.frames), "--seed-frames", str(args.seed_frames), "--no-progress", "--log-every", "500",
           "--device", "cpu", "--run-dir", str(run_dir), *flags]
    return cmd + (["--seeds", ",".join(map(str, seeds))] if len(seeds) > 1 else ["--seed", str(seeds[0])])


def _busy() -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


def row(agent: str, n: int, args, root: Path) -> dict:
    cpus = cores()
    seeds = list(range(n))
    schedules = {
        "default": ([_command(agent, args, root / "default_s{seed}", seeds, [])], 1),
        f"--torch-threads {cpus}": ([_command(agent, args, root / "threads_s{seed}", seeds,
                                              ["--torch-threads", str(cpus)])], 1),
        f"--processes {cpus}": ([_command(agent, args, root / "processes_s{seed}", seeds,
                                          ["--processes", str(cpus)])], 1),
        f"separate, {cpus} at a time x 1 thread": (
            [_command(agent, args, root / f"separate_{s}", [s], ["--torch-threads", "1"]) for s in seeds], cpus),
    }
    if not args.all_schedules:  # the default against the separate runs only
        schedules = {name: v for name, v in schedules.items() if name == "default" or name.startswith("separate")}
    walls = {}
    for name, (commands, at_once) in schedules.items():
        walls[name] = timed(commands, at_once, None)
        print(f"  {agent} N={n} {name}: {walls[name]:.0f} s", file=sys.stderr, flush=True)
    separate = walls[f"separate, {cpus} at a time x 1 thread"]
    out = {"agent": agent, "members": n, "frames": args.frames, "seed_frames": args.seed_frames,
           "domain": args.domain, "preset": "small",
           "schedules": {name: {"wall_s": wall, "member_frames_per_s": n * args.frames / wall,
                                "vs_separate": separate / wall} for name, wall in walls.items()},
           "commands": {name: [" ".join(c) for c in commands] for name, (commands, _) in schedules.items()}}
    if args.busy:
        busy = _busy()
        try:
            wall = timed([_command(agent, args, root / "busy_s{seed}", seeds, [])], 1, None)
        finally:
            busy.kill()
            busy.wait()
        out["default_beside_busy"] = {"wall_s": wall, "member_frames_per_s": n * args.frames / wall,
                                      "of_idle_default": walls["default"] / wall}
        print(f"  {agent} N={n} default beside a busy process: {wall:.0f} s "
              f"({walls['default'] / wall:.2f} of idle)", file=sys.stderr, flush=True)
    return out


def table(rows: list[dict]) -> str:
    lines = ["| agent | N | schedule | wall s | member-frames/s | vs separate |", "|---|---:|---|---:|---:|---:|"]
    for r in rows:
        for name, s in r["schedules"].items():
            lines.append(f"| {r['agent']} | {r['members']} | {name} | {s['wall_s']:.0f} | "
                         f"{s['member_frames_per_s']:.1f} | {s['vs_separate']:.2f}x |")
        if "default_beside_busy" in r:
            b = r["default_beside_busy"]
            lines.append(f"| {r['agent']} | {r['members']} | default, beside one busy process | {b['wall_s']:.0f} | "
                         f"{b['member_frames_per_s']:.1f} | {b['of_idle_default']:.2f} of idle |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", default="dvfb,fb", help="methods, comma-separated")
    parser.add_argument("--members", default="2,4,5", help="group sizes, comma-separated")
    parser.add_argument("--domain", default="walker", help="the domain")
    parser.add_argument("--frames", type=int, default=2500, help="frames per member")
    parser.add_argument("--seed-frames", type=int, default=1000, help="uniform-action frames per member")
    parser.add_argument("--busy", action="store_true", help="also the default group beside one busy process")
    parser.add_argument("--all-schedules", action=argparse.BooleanOptionalAction, default=True,
                        help="--torch-threads and --processes too (--no-all-schedules: the default and the separate runs)")
    parser.add_argument("--output", type=Path, default=RESULTS, help="where the JSON goes")
    args = parser.parse_args(argv)
    rows = []
    started = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        # One short run first, so that the first schedule timed does not pay for cold imports and caches.
        warm = argparse.Namespace(**{**vars(args), "frames": 300, "seed_frames": 200})
        timed([_command(args.agents.split(",")[0], warm, Path(tmp) / "warm", [0], [])], 1, None)
        for agent in args.agents.split(","):
            for n in (int(v) for v in args.members.split(",")):
                rows.append(row(agent, n, args, Path(tmp) / f"{agent}_{n}"))
    print(table(rows))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps({"command": " ".join(["python", "bench/group_schedule.py", *(argv or sys.argv[1:])]),
                                       "machine": describe(), "cpus": cores(), "rows": rows,
                                       "wall_s": time.time() - started}, indent=2) + "\n")
    print(f"wrote {args.output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
