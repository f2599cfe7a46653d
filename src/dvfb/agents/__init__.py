"""Agents: one module per method. ``make_agent`` builds an FB-family agent from a run config."""

from __future__ import annotations

import torch

from dvfb.agents.dvfb import DVFBAgent, ExplorationConfig
from dvfb.agents.fb import FBAgent, FBConfig
from dvfb.agents.perf import PerfConfig
from dvfb.errors import ConfigError

AGENTS = ("dvfb", "fb")


def make_agent(name: str, obs_dim: int, action_dim: int, fb: FBConfig, exploration: ExplorationConfig,
               device: str | torch.device = "cpu", perf: PerfConfig | None = None) -> FBAgent:
    """``dvfb`` (FB + exploration critic) or ``fb`` (online FB, algorithm.md §10.4).

    ``perf`` sets how the updates execute (precision, compilation); None = fp32, eager.
    """
    if name == "dvfb":
        return DVFBAgent(obs_dim, action_dim, fb, exploration, device, perf)
    if name == "fb":
        return FBAgent(obs_dim, action_dim, fb, device, perf)
    raise ConfigError(f"unknown agent {name!r}; choose one of {', '.join(AGENTS)}")


__all__ = ["AGENTS", "DVFBAgent", "ExplorationConfig", "FBAgent", "FBConfig", "PerfConfig", "make_agent"]
