"""The typed run configurations and the presets (``paper``, ``small``, ``code``).

One :class:`PretrainConfig` describes a pre-training run completely and is saved as
``config.json`` in its run directory. It nests the agent's :class:`FBConfig`, DVFB's
:class:`ExplorationConfig`, the execution options of the updates (:class:`PerfConfig`: precision,
compilation), and the defaults of the later phases (:class:`InferenceConfig`,
:class:`FinetuneConfig`) so that zero-shot and fine-tuning of a run use the preset it was trained
with unless told otherwise.

Presets:

* ``paper`` -- algorithm.md's [R] defaults (hidden 1024, batch 1024, alpha 5, eta 0.5, 2M frames).
* ``code``  -- the authors' published constants (§14): B on the code's pairings, alpha 50, RND on
  s_t, fine-tuning objective ``50 Q_F + Q_M``.
* ``small`` -- a CPU-sized preset: the paper's method and constants with narrower networks and
  smaller batches (see docs/results/ for the measurements that justify it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from dvfb.agents import AGENTS
from dvfb.agents.dvfb import ExplorationConfig
from dvfb.agents.fb import FBConfig
from dvfb.agents.finetune import FinetuneConfig
from dvfb.agents.perf import PerfConfig
from dvfb.config import merge, param, replace
from dvfb.errors import ConfigError

PRESETS = ("small", "paper", "code")
DEVICES = ("auto", "cpu", "cuda")


@dataclass
class InferenceConfig:
    """Zero-shot task inference and evaluation (algorithm.md §8)."""

    steps: int = param(10_000, "Reward-labelled environment steps collected in the task.")
    random_action_steps: int = param(4000, "Of those, the first steps use uniform actions.")
    samples: int = param(10_000, "Transitions drawn from the inference data to infer z_r.")
    with_replacement: bool = param(True, "Draw the inference samples with replacement (authors' code).")
    reward_quantile: float | None = param(0.99, "Keep samples with reward >= this quantile; none = no filter.")
    eval_episodes: int = param(50, "Mean-action evaluation episodes with the inferred z_r.")


@dataclass
class PretrainConfig:
    """A reward-free pre-training run (algorithm.md §7) and the defaults of its later phases."""

    agent: str = param("dvfb", "Method: dvfb or online fb.", AGENTS)
    domain: str = param("walker", "Domain; pre-training uses its reward-free task (tasks.md §5).")
    preset: str = param("paper", "Preset the config was built from.", PRESETS)
    frames: int = param(2_000_000, "Pre-training environment steps.")
    seed: int = param(0, "Seed of the environment, the networks and the sampling.")
    device: str = param("auto", "Torch device: auto picks cuda when available.", DEVICES)
    torch_threads: int = param(0, "torch.set_num_threads; 0 keeps torch's default.")
    seed_frames: int = param(4000, "Uniform-action steps before the first update.")
    update_every: int = param(2, "One gradient update every this many steps.")
    update_z_every: int = param(300, "Resample the rollout z when the step counter is a multiple of this.")
    replay_capacity: int = param(1_000_000, "Replay capacity in transitions.")
    snapshot_frames: list[int] = param([100_000, 500_000, 1_000_000, 2_000_000],
                                       "Frames at which agent snapshots are kept (the final frame always is).")
    checkpoint_every: int = param(100_000, "Write a resume checkpoint at the first episode end after this many steps.")
    log_every: int = param(1000, "Read metrics back from the device and log them every this many steps.")
    fb: FBConfig = field(default_factory=FBConfig, metadata={"help": "FB representation."})
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig,
                                           metadata={"help": "DVFB exploration (ignored by fb)."})
    inference: InferenceConfig = field(default_factory=InferenceConfig, metadata={"help": "Zero-shot."})
    finetune: FinetuneConfig = field(default_factory=FinetuneConfig, metadata={"help": "Fine-tuning."})
    perf: PerfConfig = field(default_factory=PerfConfig,
                             metadata={"help": "How the pre-training updates execute (precision, compilation)."})


def preset_config(preset: str, **top_level) -> PretrainConfig:
    """The config of a preset, with top-level fields (agent, domain, frames, seed, ...) applied."""
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    config = PretrainConfig(preset=preset)
    if preset == "code":
        config = merge(config, {
            "fb": {"backward_input": "code_exact"},
            "exploration": {"alpha": 50.0, "rnd_input": "obs"},
            "finetune": {"qf_coef": 50.0, "eta": 1.0},
        })
    elif preset == "small":
        config = merge(config, SMALL_PRESET)
    return replace(config, **top_level) if top_level else config


# The small preset keeps every constant of the method and shrinks widths and batch so that one
# update costs tens of milliseconds on two CPU cores (measured in docs/results/cpu_experiment.md).
SMALL_PRESET: dict = {
    "frames": 100_000,
    "replay_capacity": 1_000_000,
    "snapshot_frames": [],
    "checkpoint_every": 20_000,
    "fb": {"hidden_dim": 256, "feature_dim": 128, "backward_hidden_dim": 256, "batch_size": 256},
    "exploration": {"contrastive_hidden_dim": 256, "rnd_rep_dim": 128},
    "inference": {"eval_episodes": 10},
    "finetune": {"frames": 20_000, "eval_every": 5_000, "eval_episodes": 5, "seed_frames": 2000},
}


def resolve_device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' was requested but torch sees no CUDA device; use --device cpu or auto")
    return torch.device(device)
