"""The presets a pre-training config is built from (docs/methods.md §14):

* ``paper`` -- the spec's defaults (hidden 1024, batch 1024, alpha 5, eta 0.5, 2M frames);
* ``code``  -- the authors' published constants where the method has them (DVFB/FB: B on the
  code's pairings, alpha 50, RND on s_t, fine-tuning objective ``50 Q_F + Q_M``), and their
  driver's replay sampling for every method (loader shards: finished episodes, one shard a batch);
* ``small`` -- a CPU-sized preset: each method's constants with narrower networks and smaller
  batches (see docs/results/ for the measurements that justify it).

Each method adds its own part in its :class:`~dvfb.agents.registry.AgentSpec` (``presets``,
``defaults``); the run-level fields are here.
"""

from __future__ import annotations

from dvfb.agents import agent_names, get_spec
from dvfb.core.config import merge, replace
from dvfb.core.errors import ConfigError
from dvfb.runs.run_config import DEFAULT_AGENT, GENERIC_PRESETS, PRESETS, PretrainConfig, run_config_class


def preset_config(preset: str, agent: str = DEFAULT_AGENT, **top_level) -> PretrainConfig:
    """The config of a preset for a method, with top-level fields (domain, frames, seed, ...) applied."""
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    spec = get_spec(agent)
    if preset not in GENERIC_PRESETS and preset not in spec.presets:
        owners = [name for name in agent_names() if preset in get_spec(name).presets]
        raise ConfigError(f"preset {preset!r} holds the constants of {', '.join(owners)}; {agent!r} has the presets "
                          f"{', '.join(GENERIC_PRESETS)}")
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
    # Ten evaluations over the preset's 100k frames, at about 2-6% of its wall clock (docs/health.md).
    "eval_every": 10_000,
    "inference": {"eval_episodes": 10},
    "finetune": {"frames": 20_000, "eval_every": 5_000, "eval_episodes": 5, "seed_frames": 2000},
}


# The authors' driver, whatever the method: their (URLB's) replay reaches the updates through a
# DataLoader with 4 workers that each hold a share of the finished episodes (docs/methods.md,
# "Replay sampling"; measured in docs/results/crosscheck_walker.md).
CODE_PRESET: dict = {"replay": {"sampling": "loader_shards", "loader_workers": 4, "loader_refresh": 1000}}


__all__ = ["CODE_PRESET", "PRESETS", "SMALL_PRESET", "preset_config"]
