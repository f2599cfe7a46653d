"""Run every dvfb benchmark: ``make bench`` (or ``python bench/run.py [--quick] [learner options]``).

* bench/env_throughput.py   -- env steps/s of dvfb.envs versus raw dm_control;
* bench/preset_update_ms.py -- ms per update of the exact presets (1 and 2 threads);
* bench/learner.py          -- learner ms/update, FLOPs, fraction of the matmul peak, memory,
  scaling, collector steps/s and end-to-end frames/s.

Options other than ``--skip-env`` / ``--skip-preset`` are passed to bench/learner.py (``--quick``
also shortens the env benchmark). Each benchmark prints its figures; env_throughput and learner
also write JSON to bench/results/.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import env_throughput  # noqa: E402
import learner  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], add_help=False)
    parser.add_argument("--skip-env", action="store_true", help="do not run bench/env_throughput.py")
    parser.add_argument("--skip-preset", action="store_true", help="do not run bench/preset_update_ms.py")
    parser.add_argument("-h", "--help", action="store_true")
    args, rest = parser.parse_known_args(argv)
    if args.help:
        parser.print_help()
        print("\nbench/learner.py options:")
        return learner.main(["--help"])
    status = 0
    if not args.skip_env:
        print("# env_throughput", flush=True)
        env_args = ["--seconds", "0.5", "--repeats", "2"] if "--quick" in rest else []
        status |= env_throughput.main(env_args)
        print(flush=True)
    if not args.skip_preset:
        print("# preset_update_ms", flush=True)
        status |= subprocess.run([sys.executable, str(HERE / "preset_update_ms.py")], check=False).returncode
        print(flush=True)
    print("# learner", flush=True)
    status |= learner.main(rest)
    return status


if __name__ == "__main__":
    sys.exit(main())
