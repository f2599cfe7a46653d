"""The Python API: ``dvfb.load(path)`` gives a pre-trained model to infer a task and act with.

    import dvfb
    model = dvfb.load("runs/dvfb_walker_small_s0")   # a run directory, or an exported model
    z = model.infer_z(reward_fn=lambda next_obs: next_obs[:, 0])  # or goal=..., or samples
    act = model.policy(z)
    action = act(obs)
    model.save_pretrained("shared/dvfb_walker_s0")   # safetensors + config.json + model card

The object holds the model (:class:`~dvfb.agents.base.Model`, through the registry, any method: its
networks for acting and inference, no optimiser) and uses the zero-shot machinery of
:mod:`dvfb.workflows.zeroshot`; it writes nothing into the run directory. An exported model
(docs/sharing.md) is read without any pickle.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from dvfb.agents import get_spec
from dvfb.core.errors import ConfigError
from dvfb.nets.execution import resolve_device
from dvfb.runs.export import export_model, is_export, load_export, write_export
from dvfb.runs.snapshots import load_model
from dvfb.workflows.resources import open_run
from dvfb.workflows.zeroshot import check_goal, exported_states, infer_from_reward_fn, run_protocol


class PretrainedModel:
    """A pre-training run's model, loaded from a snapshot (the newest by default): ``model``.

    ``infer_z`` turns a task into the model's skill (methods that infer skills: the FB family, SF);
    ``act`` and ``policy`` act with a skill, or without one for single-policy methods.
    """

    def __init__(self, path: str | Path, snapshot: int | None = None, device: str | None = None):
        self.export = None
        if isinstance(device, str):  # "cuda" without CUDA, or a typo: one line, not torch's error
            device = resolve_device(device)
        if is_export(path):
            if snapshot is not None:
                raise ConfigError(f"{path} is an exported model of one snapshot; load it without snapshot=")
            self.export = load_export(path, device or "cpu")
            self.run, self.config, self.model = None, self.export.config, self.export.model
            self.snapshot = self.export.info["frames"]
        else:
            self.run = open_run(path)
            self.config = self.run.config
            self.model, self.snapshot = load_model(self.run, snapshot, device)
        self.spec = get_spec(self.config.agent)

    @property
    def name(self) -> str:
        return self.config.agent

    @property
    def agent(self):
        """The old name of :attr:`model`, kept for one release with a DeprecationWarning (CHANGELOG.md):
        what ``dvfb.load`` gives has held the model, not a learner, since the model/learner split."""
        warnings.warn("dvfb.load(...).agent is deprecated and will be removed; use .model (the same object)",
                      DeprecationWarning, stacklevel=2)
        return self.model

    def infer_z(self, obs=None, next_obs=None, rewards=None, *, reward_fn: Callable | None = None,
                goal=None, **inference) -> torch.Tensor:
        """The skill of a task, from exactly one of:

        * reward-labelled samples ``(obs, next_obs, rewards)`` (arrays ``(N, O)``, ``(N, O)``, ``(N,)``);
        * ``reward_fn(next_obs (N, O)) -> rewards (N,)``, applied to the run's own replay states;
        * ``goal``, an observation to reach.

        ``inference`` overrides the run's inference options (e.g. ``reward_quantile=None``).
        """
        given = [rewards is not None, reward_fn is not None, goal is not None]
        if sum(given) != 1:
            raise ConfigError("infer_z needs exactly one of (obs, next_obs, rewards), reward_fn= or goal=")
        if not self.model.skill.has_skill:
            raise ConfigError(f"{self.name!r} has a single policy and no skill to infer; call policy() without z")
        protocol = run_protocol(self.config, inference, "goal" if goal is not None else "reward_fn")
        device = self.model.device
        if goal is not None:
            check_goal(goal, self.model.goal_widths(), self.config.domain, "goal")
            return protocol.skill_from_goal(self.model, goal)[0]
        if reward_fn is not None:
            return infer_from_reward_fn(self.model, self.run, reward_fn, protocol, config=self.config,
                                        states=self._exported_states())[0]
        if obs is None or next_obs is None:
            raise ConfigError("infer_z from samples needs obs, next_obs and rewards")

        def tensor(x):
            return torch.as_tensor(np.asarray(x), dtype=torch.float32, device=device)

        obs_t, next_t, reward_t = tensor(obs), tensor(next_obs), tensor(rewards).reshape(-1)
        for name, value in (("obs", obs_t), ("next_obs", next_t)):
            if value.dim() != 2 or value.shape[1] != self.model.obs_dim:
                raise ConfigError(f"{name} has shape {tuple(value.shape)}; it must be (N, {self.model.obs_dim}), one "
                                  f"{self.config.domain} observation per row")
        if not (obs_t.shape[0] == next_t.shape[0] == reward_t.shape[0]):
            raise ConfigError(f"obs, next_obs and rewards have {obs_t.shape[0]}, {next_t.shape[0]} and "
                              f"{reward_t.shape[0]} rows; they must match")
        return protocol.skill_from_samples(self.model, obs_t, next_t, reward_t)[0]

    def _exported_states(self):
        data = self.export.inference_data if self.export is not None else None
        return exported_states(data, self.model.device) if data else None

    def save_pretrained(self, out: str | Path, with_inference_data: bool = False, overwrite: bool = False) -> Path:
        """Write the model as an exported model (docs/sharing.md): ``model.safetensors``,
        ``config.json`` and a model card ``README.md`` in ``out`` (absent or empty; ``overwrite``
        replaces an exported model), with the reward-inference samples if ``with_inference_data``."""
        if self.run is not None:
            return export_model(self.run, out, snapshot=self.snapshot, with_inference_data=with_inference_data,
                                overwrite=overwrite)
        data = self.export.inference_data if with_inference_data else None
        if with_inference_data and data is None:
            raise ConfigError(f"{self.export.path} has no inference data to save")
        info = self.export.info
        return write_export(out, self.model, self.config, frames=info["frames"], zero_shot=info.get("zero_shot"),
                            command=info.get("command"), commands=info.get("commands"),
                            zero_shot_budget=info.get("zero_shot_budget"), inference_data=data, overwrite=overwrite)

    def act(self, obs: np.ndarray, z: torch.Tensor | None = None, explore: bool = False) -> np.ndarray:
        """One action: the policy's mean (or a rollout sample with ``explore``)."""
        if z is None and self.model.skill_dim:
            raise ConfigError(f"{self.name!r} acts with a skill: pass z (from infer_z)")
        if z is not None and not self.model.skill_dim:
            raise ConfigError(f"{self.name!r} has a single policy and takes no z; call act(obs) without it")
        if z is not None:
            z = torch.as_tensor(np.asarray(z) if not isinstance(z, torch.Tensor) else z, dtype=torch.float32)
            if z.numel() != self.model.skill_dim:
                raise ConfigError(f"z has {z.numel()} values; {self.name!r}'s skill has {self.model.skill_dim}")
            z = z.reshape(-1).to(self.model.device)
        obs = np.asarray(obs, dtype=np.float32)
        if obs.shape != (self.model.obs_dim,):
            raise ConfigError(f"obs has shape {obs.shape}; a {self.config.domain} observation has "
                              f"{self.model.obs_dim} values")
        return self.model.act(obs[None], None if z is None else z[None], explore)[0]

    def policy(self, z: torch.Tensor | None = None, explore: bool = False) -> Callable[[np.ndarray], np.ndarray]:
        """``obs -> action`` with the skill fixed."""
        return lambda obs: self.act(obs, z, explore)


def load(path: str | Path, snapshot: int | None = None, device: str | None = None) -> PretrainedModel:
    """Load a pre-trained model from a run directory (its newest snapshot, or ``snapshot``) or from
    an exported model's directory (see :class:`PretrainedModel`)."""
    return PretrainedModel(path, snapshot, device)

