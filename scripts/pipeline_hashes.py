"""Hashes of everything a tiny pipeline writes, for every registered method: the check that a
refactor keeps users' numbers.

For each method (the tiny widths of tests/tiny.py, point_mass_maze, seed 3), through the ``dvfb``
command line run in this process:

* pre-training for 1,500 frames (snapshots at 1,000 and 1,500);
* zero-shot on ``point_mass_maze_reach_top_left`` by the method's protocol (short budgets), and, for
  the methods that infer skills, from a reward function over the run's replay;
* fine-tuning on the same task for 1,500 frames (evaluations at 0, 1,000 and 1,500);
* the same three phases as a group of two seeds (5, 6);
* offline: an RND run that records physics is exported as a dataset, on which FB, VC-FB, MC-FB and
  SF train for 300 updates and infer their skill from the dataset relabelled for the task.

Each run directory's snapshots (their tensors and fields, not the archive bytes), zero-shot
results, fine-tuning curves, summaries and metric records are hashed with every field that
measures time left out (wall clock, frames per second). Run it on two commits of the same
machine and compare:

    python scripts/pipeline_hashes.py --out before.json          # on the old commit
    python scripts/pipeline_hashes.py --compare before.json      # on the new one

``--compare`` prints every hash that differs (or "identical") and exits 1 if any does.
``--agents fb,dvfb`` restricts the methods; ``--keep DIR`` keeps the run directories;
``--ignore-key NAME`` leaves a config field that the change adds out of every hash (both sides).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from tiny import TINY_SECTIONS  # noqa: E402

from dvfb.agents import agent_names, get_spec  # noqa: E402
from dvfb.cli import main  # noqa: E402
from dvfb.protocols import protocols_of  # noqa: E402

DOMAIN = "point_mass_maze"
TASK = "point_mass_maze_reach_top_left"
# The temporary root of the runs (and its resolved form), replaced in every hashed string.
ROOTS: list[str] = []
# Fields that measure time, not what was computed.
TIMING = {"wall_clock_s", "fps", "fps_recent", "frames_per_s", "resumed_from"}
IGNORED: set[str] = set()  # --ignore-key: a config field added by the change under test
COMMON = ["--domain", DOMAIN, "--frames", "1500", "--seed-frames", "500", "--update-every", "4",
          "--checkpoint-every", "1000", "--log-every", "250", "--torch-threads", "1", "--snapshot-frames", "1000",
          "--no-progress"]
FINETUNE = ["--finetune.frames", "1500", "--finetune.seed-frames", "500", "--finetune.eval-every", "1000",
            "--finetune.eval-episodes", "1", "--finetune.checkpoint-every", "1000", "--no-progress"]
REWARD_FN = "def reward(next_obs):\n    return next_obs[:, 0] - next_obs[:, 1]\n"


def section_flags(agent: str) -> list[str]:
    flags = []
    for section in get_spec(agent).sections:
        for key, value in TINY_SECTIONS.get(section, {}).items():
            flags += [f"--{section}.{key.replace('_', '-')}", str(value)]
    return flags


def inference_flags(agent: str) -> list[str]:
    """Short budgets for the fields the method's zero-shot protocol has."""
    zero_shot, _ = protocols_of(agent)
    fields = set(zero_shot.config_cls.__dataclass_fields__)
    wanted = {"steps": 1000, "random_action_steps": 500, "samples": 500, "eval_episodes": 1}
    return [flag for key, value in wanted.items() if key in fields
            for flag in (f"--inference.{key.replace('_', '-')}", str(value))]


def call(argv: list[str]) -> None:
    code = main([str(a) for a in argv])
    if code != 0:
        raise SystemExit(f"dvfb {' '.join(map(str, argv))} exited with {code}")


# Hashing ------------------------------------------------------------------------------------------

def _feed(digest, value) -> None:
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().contiguous()
        digest.update(f"tensor{value.dtype}{tuple(value.shape)}".encode())
        digest.update(value.reshape(-1).view(torch.uint8).numpy().tobytes() if value.numel() else b"")
    elif isinstance(value, np.ndarray):
        digest.update(f"array{value.dtype}{value.shape}".encode())
        digest.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, dict):
        digest.update(b"{")
        for key in sorted(value, key=str):
            if key in TIMING or key in IGNORED:
                continue
            digest.update(repr(key).encode())
            _feed(digest, value[key])
        digest.update(b"}")
    elif isinstance(value, (list, tuple)):
        digest.update(b"[")
        for item in value:
            _feed(digest, item)
        digest.update(b"]")
    elif isinstance(value, str):
        # Run directories live under a fresh temporary root: hash their paths relative to it.
        for root in ROOTS:
            value = value.replace(root, "<root>")
        digest.update(repr(value).encode())
    else:
        digest.update(repr(value).encode())


def value_hash(value) -> str:
    digest = hashlib.sha256()
    _feed(digest, value)
    return digest.hexdigest()[:16]


def file_hash(path: Path) -> str:
    if path.suffix == ".pt":
        return value_hash(torch.load(path, map_location="cpu", weights_only=True))
    if path.suffix == ".jsonl":
        return value_hash([json.loads(line) for line in path.read_text().splitlines() if line.strip()])
    return value_hash(json.loads(path.read_text()))


def run_hashes(run: Path, label: str) -> dict[str, str]:
    """Hashes of a run's snapshots, results, curves, summaries and metrics (not its checkpoints,
    whose layout a refactor may change)."""
    out = {}
    patterns = ["snapshots/*.pt", "zeroshot/*.json", "pretrain_summary.json", "metrics/*.jsonl",
                "finetune/*/curve.json", "finetune/*/finetune_summary.json", "finetune/*/metrics/*.jsonl",
                "config.json", "finetune/*/config.json"]
    for pattern in patterns:
        for path in sorted(run.glob(pattern)):
            out[f"{label}/{path.relative_to(run)}"] = file_hash(path)
    return out


# The pipeline -----------------------------------------------------------------------------------

def method_pipeline(agent: str, root: Path, reward_fn: Path) -> dict[str, str]:
    hashes = {}
    tiny = section_flags(agent)
    inference = inference_flags(agent)
    zero_shot, _ = protocols_of(agent)
    task = TASK if get_spec(agent).task_field is None else None
    tasks = [TASK] if task else ["all"]
    # One run.
    run = root / f"{agent}_s3"
    call(["pretrain", "--agent", agent, *COMMON, "--seed", "3", "--run-dir", run, *tiny])
    call(["zeroshot", run, "--task", *tasks, *inference, "--no-progress"])
    if "reward_fn" in zero_shot.sources:
        call(["zeroshot", run, "--task", TASK, "--skill-source", "reward_fn", "--reward-fn", f"{reward_fn}:reward",
              "--overwrite", *inference, "--no-progress"])
    finetune_task = task or get_spec(agent).task_of(json.loads((run / "config.json").read_text()))
    call(["finetune", run, "--task", finetune_task, *inference, *FINETUNE])
    hashes.update(run_hashes(run, run.name))
    # A group of two.
    template = root / f"{agent}_g{{seed}}"
    call(["pretrain", "--agent", agent, *COMMON, "--seeds", "5,6", "--run-dir", str(template), *tiny])
    members = [Path(str(template).replace("{seed}", str(s))) for s in (5, 6)]
    call(["zeroshot", *members, "--task", *tasks, *inference, "--no-progress"])
    call(["finetune", *members, "--task", finetune_task, *inference, *FINETUNE])
    for member in members:
        hashes.update(run_hashes(member, member.name))
    return hashes


def offline_pipeline(root: Path, agents: list[str]) -> dict[str, str]:
    hashes = {}
    source = root / "rnd_physics"
    call(["pretrain", "--agent", "rnd", *COMMON, "--seed", "4", "--run-dir", source, "--replay.record-physics", "true",
          *section_flags("rnd")])
    dataset = root / "dataset"
    call(["dataset", "export", source, "--out", dataset])
    for agent in [a for a in ("fb", "vcfb", "mcfb", "sf") if a in agents]:
        run = root / f"{agent}_offline"
        call(["pretrain", "--agent", agent, "--domain", DOMAIN, "--frames", "300", "--checkpoint-every", "200",
              "--log-every", "100", "--torch-threads", "1", "--seed", "2", "--run-dir", run, "--dataset", dataset,
              "--no-progress", *section_flags(agent)])
        call(["zeroshot", run, "--task", TASK, "--skill-source", "dataset", *inference_flags(agent), "--no-progress"])
        hashes.update(run_hashes(run, run.name))
    for path in sorted(dataset.glob("*")):
        if path.suffix == ".npz":
            with np.load(path) as data:
                hashes[f"dataset/{path.name}"] = value_hash({k: data[k] for k in data.files})
    return hashes


def main_(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", default=None, help="comma-separated methods (default: every registered one)")
    parser.add_argument("--out", default=None, help="write the hashes to this JSON file")
    parser.add_argument("--compare", default=None, help="compare with the hashes of this JSON file; exit 1 if any differ")
    parser.add_argument("--keep", default=None, help="keep the run directories in this directory")
    parser.add_argument("--ignore-key", action="append", default=[],
                        help="leave every dict entry of this name out of the hashes (a config field that the "
                             "change under test adds; run both sides with it); repeatable")
    args = parser.parse_args(argv)
    IGNORED.update(args.ignore_key)
    torch.set_num_threads(1)
    agents = args.agents.split(",") if args.agents else list(agent_names())
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="dvfb_pipeline_"))
    root.mkdir(parents=True, exist_ok=True)
    ROOTS[:] = sorted({str(root), str(root.resolve())}, key=len, reverse=True)
    reward_fn = root / "reward.py"
    reward_fn.write_text(REWARD_FN)
    hashes: dict[str, str] = {}
    started = time.time()
    try:
        for agent in agents:
            t0 = time.time()
            agent_hashes = method_pipeline(agent, root, reward_fn)
            hashes.update(agent_hashes)
            print(f"{agent:14s} {value_hash(agent_hashes)}  ({len(agent_hashes)} files, {time.time() - t0:.0f} s)",
                  flush=True)
        offline = offline_pipeline(root, agents)
        hashes.update(offline)
        print(f"{'offline':14s} {value_hash(offline)}  ({len(offline)} files)", flush=True)
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)
    print(f"all            {value_hash(hashes)}  ({len(hashes)} files, {time.time() - started:.0f} s)")
    if args.out:
        Path(args.out).write_text(json.dumps(hashes, indent=1, sort_keys=True) + "\n")
    if args.compare:
        before = json.loads(Path(args.compare).read_text())
        if args.agents:  # a part of the pipeline: compare what it wrote
            before = {k: v for k, v in before.items() if k in hashes}
        differ = sorted(k for k in set(before) | set(hashes) if before.get(k) != hashes.get(k))
        for key in differ:
            print(f"DIFFERS {key}: {before.get(key)} -> {hashes.get(key)}")
        print("identical" if not differ else f"{len(differ)} of {len(set(before) | set(hashes))} differ")
        return 1 if differ else 0
    return 0


if __name__ == "__main__":
    sys.exit(main_())
