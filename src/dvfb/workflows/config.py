"""The typed run configurations and the presets (``paper``, ``small``, ``code``).

One run config describes a pre-training run completely and is saved as ``config.json`` in its run
directory. Its top-level fields (:class:`PretrainConfig`) are the same for every method; the
method adds its own typed sections from the registry (``fb`` and ``exploration`` for DVFB,
``ddpg`` and ``rnd`` for RND, ...), and its family's zero-shot (``inference``) and fine-tuning
(``finetune``) configs, so that zero-shot and fine-tuning of a run use the preset it was trained
with unless told otherwise. :func:`run_config_class` builds that dataclass once per method, so
loading stays strict: unknown keys and wrong types are errors.

Presets:

* ``paper`` -- the spec's defaults (hidden 1024, batch 1024, alpha 5, eta 0.5, 2M frames).
* ``code``  -- the authors' published constants where the method has them (DVFB/FB: B on the
  code's pairings, alpha 50, RND on s_t, fine-tuning objective ``50 Q_F + Q_M``), and their
  driver's replay sampling for every method (loader shards: finished episodes, one shard a batch).
* ``small`` -- a CPU-sized preset: each method's constants with narrower networks and smaller
  batches (see docs/results/ for the measurements that justify it).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from dvfb.agents import get_spec
from dvfb.execution import PerfConfig
from dvfb.protocols import protocols_of
from dvfb.protocols.zero_shot import InferenceConfig
from dvfb.config import from_dict, merge, param, replace, require_updates
from dvfb.errors import ConfigError
from dvfb.data import ReplaySamplingConfig
from dvfb.runs import read_json

PRESETS = ("small", "paper", "code")
DEVICES = ("auto", "cpu", "cuda")
DEFAULT_AGENT = "dvfb"


@dataclass
class PretrainConfig:
    """A reward-free pre-training run (docs/methods.md §7): the fields every method shares.

    A run's config is an instance of :func:`run_config_class` ``(agent)``, a subclass with the
    method's sections and its family's ``inference`` and ``finetune`` configs.
    """

    agent: str = param(DEFAULT_AGENT, "Method (see `dvfb agents`).")
    domain: str = param("walker", "Domain; pre-training uses its reward-free task (docs/tasks.md §5).")
    preset: str = param("paper", "Preset the config was built from.", PRESETS)
    frames: int = param(2_000_000, "Pre-training environment steps.", at_least=1)
    seed: int = param(0, "Seed of the environment, the networks and the sampling.", at_least=0)
    device: str = param("auto", "Torch device: auto picks cuda when available.", DEVICES)
    torch_threads: int = param(0, "torch.set_num_threads; 0 keeps torch's default.", at_least=0)
    seed_frames: int = param(4000, "Uniform-action steps before the first update.", at_least=0)
    update_every: int = param(2, "One gradient update every this many steps.", at_least=1)
    replay_capacity: int = param(1_000_000, "Replay capacity in transitions.", at_least=1)
    dataset: str = param("", "Offline: train on the dataset in this directory (dvfb dataset export / relabel) "
                         "instead of acting: no environment steps, one update per step (--frames counts updates; "
                         "--seed-frames and --update-every do not apply). Empty: online.")
    replay: ReplaySamplingConfig = field(default_factory=ReplaySamplingConfig,
                                         metadata={"help": "How the updates' batches are drawn from the replay, "
                                                           "and what it records."})
    snapshot_frames: list[int] = param([100_000, 500_000, 1_000_000, 2_000_000],
                                       "Frames at which agent snapshots are kept (the final frame always is).",
                                       at_least=1)
    checkpoint_every: int = param(100_000, "Write a resume checkpoint at the first episode end after this many steps.",
                                  at_least=1)
    log_every: int = param(1000, "Read metrics back from the device and log them every this many steps.", at_least=1)
    perf: PerfConfig = field(default_factory=PerfConfig,
                             metadata={"help": "How the pre-training updates execute (precision, compilation)."})

    def check(self) -> None:
        """Relations between fields (ranges are checked per field)."""
        if self.dataset:
            if self.replay.record_physics:
                raise ConfigError("--replay.record-physics records what an online run collects; an offline run "
                                  "(--dataset) collects nothing")
            if self.replay.sampling != "uniform":
                raise ConfigError(f"--replay.sampling {self.replay.sampling} emulates the online driver's loader; "
                                  "offline batches are drawn uniformly from the dataset (--replay.sampling uniform)")
            return
        require_updates("--frames", self.frames, "--seed-frames", self.seed_frames)


@functools.cache
def run_config_class(agent: str) -> type:
    """The run-config dataclass of a registered method: :class:`PretrainConfig` plus the method's
    sections and its family's ``inference`` and ``finetune`` configs."""
    spec = get_spec(agent)
    fields = [(name, cls, field(default_factory=cls, metadata={"help": (cls.__doc__ or name).splitlines()[0]}))
              for name, cls in spec.sections.items()]
    fields += protocol_fields(agent)
    name = "".join(part.capitalize() for part in agent.split("_")) + "RunConfig"
    cls = dataclasses.make_dataclass(name, fields, bases=(PretrainConfig,))
    cls.__module__ = __name__
    cls.__doc__ = f"The run config of {agent!r}: {spec.summary}."
    return cls


def protocol_fields(agent: str) -> list[tuple]:
    """The ``inference`` and ``finetune`` sections of a method's configs: its protocols' configs."""
    zero_shot, finetuner = protocols_of(agent)
    return [("inference", zero_shot.config_cls,
             field(default_factory=zero_shot.config_cls, metadata={"help": f"Zero-shot ({zero_shot.name})."})),
            ("finetune", finetuner.config_cls,
             field(default_factory=finetuner.config_cls, metadata={"help": f"Fine-tuning ({finetuner.name})."}))]


def agent_sections(config: Any) -> dict:
    """The method-specific sections of a run config (or its dict), the part a snapshot must match."""
    spec = get_spec(config["agent"] if isinstance(config, dict) else config.agent)
    if isinstance(config, dict):
        return {name: config.get(name) for name in spec.sections}
    return {name: dataclasses.asdict(getattr(config, name)) for name in spec.sections}


def _migrate(data: dict) -> dict:
    """Configs written by older versions, read as today's.

    * A top-level field or section that moved into a method's section (``moved_fields`` of its spec, e.g.
      the skill resampling period ``update_z_every`` -> ``fb.skill_every``) is moved there; one it
      maps to None is dropped (online FB's configs once carried DVFB's unused ``exploration``).
      A skill period of a method without skills, which never used it, is dropped too.
    """
    spec = get_spec(data["agent"])
    data = dict(data)
    for old, new in spec.moved_fields.items():
        if old in data:
            value = data.pop(old)
            if new is not None:  # None: a field the method's runs carried but never used
                section, key = new.split(".", 1)
                data[section] = {**data.get(section, {}), key: value}
    data.pop("update_z_every", None)  # methods without skills ignored the global period
    return data


def run_config_from_dict(data: dict, source: str = "config") -> PretrainConfig:
    """A run config from its JSON dict, strictly (unknown keys and wrong types are errors)."""
    if not isinstance(data, dict) or not isinstance(data.get("agent"), str):
        raise ConfigError(f"{source}: not a dvfb run config (no 'agent' field)")
    return from_dict(run_config_class(data["agent"]), _migrate(data))


def load_run_config(path: str | Path) -> PretrainConfig:
    """Read a pre-training run's ``config.json``."""
    return run_config_from_dict(read_json(Path(path), ConfigError), str(path))


def preset_config(preset: str, agent: str = DEFAULT_AGENT, **top_level) -> PretrainConfig:
    """The config of a preset for a method, with top-level fields (domain, frames, seed, ...) applied."""
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    spec = get_spec(agent)
    config = run_config_class(agent)(agent=agent, preset=preset)
    if spec.defaults:
        config = merge(config, spec.defaults)
    if preset == "small":
        config = merge(config, SMALL_PRESET)
    if preset == "code":
        config = merge(config, CODE_PRESET)
    config = merge(config, spec.presets.get(preset, {}))
    return replace(config, **top_level) if top_level else config


# The small preset keeps every constant of a method and shrinks widths and batch (each method's
# own part is in its AgentSpec.presets) so that one update costs tens of milliseconds on two CPU
# cores (measured in docs/results/cpu_experiment.md). These are the run-level fields.
SMALL_PRESET: dict = {
    "frames": 100_000,
    "replay_capacity": 1_000_000,
    "snapshot_frames": [],
    "checkpoint_every": 20_000,
    "inference": {"eval_episodes": 10},
    "finetune": {"frames": 20_000, "eval_every": 5_000, "eval_episodes": 5, "seed_frames": 2000},
}


# The authors' driver, whatever the method: their (URLB's) replay reaches the updates through a
# DataLoader with 4 workers that each hold a share of the finished episodes (docs/methods.md,
# "Replay sampling"; measured in docs/results/crosscheck_walker.md).
CODE_PRESET: dict = {"replay": {"sampling": "loader_shards", "loader_workers": 4, "loader_refresh": 1000}}


def resolve_device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' was requested but torch sees no CUDA device; use --device cpu or auto")
    return torch.device(device)


__all__ = ["DEVICES", "InferenceConfig", "PRESETS", "PretrainConfig", "agent_sections", "load_run_config",
           "preset_config", "resolve_device", "run_config_class", "run_config_from_dict"]
