"""FBEE: online FB that explores with its own epistemic uncertainty (Urpí et al., RLC 2025;
docs/methods.md, "FBEE").

The posterior over the forward map is an ensemble of E complete forward maps (each with its own
two streams and twin heads, its own EMA target) that share one B and one actor. Each member is
trained with FB's twin-head loss against its own target; the loss is their mean, so identical
members give FB's loss exactly. The actor follows the ensemble's mean value ``min_k mean_e F^e_k . z``
(the model's ``forward_map`` returns the ensemble mean, which every protocol reads as F). The
exploration lives in the rollout z alone: at every episode start and every ``fb.skill_every`` steps
the learner draws ``fbee.candidates`` z's from the prior and acts with the one whose value at the
current state the members disagree on most (FBEE^Q: the std of ``F^e . z``; FBEE^F: the trace of
the covariance of the vectors ``F^e``).

The ensemble is stacked (:func:`dvfb.nets.members.stack_ensemble`): each layer of the E maps is
one batched product, and a group's members (docs/members.md) stack on top of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from dvfb.agents.dvfb import ExplorationCritic
from dvfb.agents.fb import FB_SMALL, FBAgent, FBConfig, FBModel, FBStep, fb_finetune_label
from dvfb.core.config import param
from dvfb.data import Batch
from dvfb.nets import ForwardMap, implicit_reward, offdiag_mean, orthonormality_loss, skill_values
from dvfb.nets.members import member_mean, rand, row_products, stack_ensemble

UNCERTAINTIES = ("q", "f")
SCORED_HEADS = ("first", "min", "mean")


@dataclass
class FBEEConfig:
    """The ensemble and the uncertainty-driven z choice of FBEE (docs/methods.md, "FBEE")."""

    ensemble: int = param(5, "Forward maps in the ensemble (each a complete F with twin heads, one shared B).",
                          at_least=2)
    uncertainty: str = param("q", "What the members disagree on: q = std of F.z (FBEE^Q), f = trace of the "
                             "covariance of F (FBEE^F).", UNCERTAINTIES)
    candidates: int = param(100, "Prior z's scored at the current state at every z choice.", at_least=1)
    head: str = param("first", "Which twin head is scored: the first (the authors' code), the min over the "
                      "heads of F.z, or their mean.", SCORED_HEADS)


class ForwardEnsemble(nn.Module):
    """E forward maps as one stacked network. :meth:`each` gives every member's twin-head output
    ``(..., E, K, N, d)``; calling it gives their mean ``(..., K, N, d)``, what F means wherever one F
    is read (the actor, zero-shot, fine-tuning, analyses)."""

    members: int = 0  # a group's member count (set when a group stacks its agents)

    def __init__(self, obs_dim: int, action_dim: int, z_dim: int, hidden_dim: int, feature_dim: int, size: int):
        super().__init__()
        self.size = size
        # Built one after the other, each initialised as a separate F would be.
        self.net = stack_ensemble([ForwardMap(obs_dim, action_dim, z_dim, hidden_dim, feature_dim)
                                   for _ in range(size)])

    def spread(self, x: torch.Tensor) -> torch.Tensor:
        """Rows ``(..., N, w)`` copied for every member: ``(C, N, w)``, C = E (a group: M*E)."""
        lead = x.shape[:-2]
        return x.unsqueeze(-3).expand(*lead, self.size, *x.shape[-2:]).reshape(-1, *x.shape[-2:])

    def gather(self, x: torch.Tensor) -> torch.Tensor:
        """Per-network values ``(C, ...)`` back as ``(..., E, ...)`` (a group: ``(M, E, ...)``)."""
        return x.reshape(*((self.members,) if self.members else ()), self.size, *x.shape[1:])

    def each(self, obs: torch.Tensor, action: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return self.gather(self.net(self.spread(obs), self.spread(action), self.spread(z)))

    def forward(self, obs: torch.Tensor, action: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return self.each(obs, action, z).mean(-4)


def ensemble_uncertainty(forward: torch.Tensor, z: torch.Tensor, kind: str) -> torch.Tensor:
    """The disagreement of the members about each z: ``forward`` ``(..., E, C, d)`` (one head),
    ``z`` ``(..., C, d)``; returns ``(..., C)``. ``q``: the unbiased std over the members of
    ``F^e . z``; ``f``: the trace of the unbiased covariance of the vectors ``F^e``."""
    if kind == "q":
        return (forward * z.unsqueeze(-3)).sum(-1).std(dim=-2, correction=1)
    deviation = forward - forward.mean(-3, keepdim=True)
    return deviation.pow(2).sum(-1).sum(-2) / (forward.shape[-3] - 1)


def scored_head(heads: torch.Tensor, z: torch.Tensor, head: str) -> torch.Tensor:
    """One F vector per member and candidate from the twin heads ``(..., E, K, C, d)``: the first
    head, the head with the smaller ``F_k . z``, or the heads' mean."""
    if head == "first":
        return heads[..., 0, :, :]
    if head == "mean":
        return heads.mean(-3)
    values = (heads * z.unsqueeze(-3).unsqueeze(-4)).sum(-1)  # (..., E, K, C)
    index = values.argmin(-2, keepdim=True).unsqueeze(-1).expand(*values.shape[:-2], 1, *heads.shape[-2:])
    return heads.gather(-3, index).squeeze(-3)


def choose_most_uncertain(scores: torch.Tensor, generator=None) -> int:
    """The index of the highest score, ties broken uniformly at random (all-equal scores, as
    identical members give, make the choice a uniform draw)."""
    u = rand(scores.shape, generator, scores.device)
    return int(torch.where(scores == scores.max(), u, torch.full_like(u, -1.0)).argmax())


class FBEEModel(FBModel):
    """FB's model with an ensemble of forward maps: ``forward_map`` is a :class:`ForwardEnsemble`."""

    name = "fbee"

    def __init__(self, obs_dim: int, action_dim: int, config, device="cpu", perf=None, ensemble: FBEEConfig = None):
        self.ensemble_config = ensemble if ensemble is not None else FBEEConfig()
        super().__init__(obs_dim, action_dim, config, device, perf)

    def build_representation(self, config: FBConfig) -> None:
        super().build_representation(config)
        c = config
        self.forward_map = ForwardEnsemble(self.obs_dim, self.action_dim, c.z_dim, c.hidden_dim, c.feature_dim,
                                           self.ensemble_config.ensemble)

    @torch.no_grad()
    def uncertainty(self, obs: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """The score of each z ``(..., C, d)`` at the states ``obs`` ``(..., C, O)``, with the mean
        action of pi(s, z): ``(..., C)``."""
        c = self.ensemble_config
        action = self.actor(obs, z)
        heads = self.forward_map.each(obs, action, z)  # (..., E, K, C, d)
        return ensemble_uncertainty(scored_head(heads, z, c.head), z, c.uncertainty)


class FBEEAgent(FBAgent):
    """FBEE's learner: FB's update with the ensemble's loss, and the uncertainty-driven rollout z."""

    name = "fbee"
    model_cls = FBEEModel

    @classmethod
    def from_config(cls, obs_dim: int, action_dim: int, config, device="cpu") -> FBEEAgent:
        return cls(obs_dim, action_dim, cls.config_section(config), device, config.perf, cls.components(config),
                   config.fbee)

    @classmethod
    def model_from_config(cls, obs_dim: int, action_dim: int, config, device="cpu") -> FBEEModel:
        return cls.model_cls(obs_dim, action_dim, cls.config_section(config), device, config.perf, config.fbee)

    def __init__(self, obs_dim: int, action_dim: int, config, device="cpu", perf=None, components=(),
                 ensemble: FBEEConfig | None = None):
        self.ensemble_config = ensemble if ensemble is not None else FBEEConfig()
        super().__init__(obs_dim, action_dim, config, device, perf, components)

    def make_model(self, obs_dim: int, action_dim: int, config, device, perf) -> FBEEModel:
        return self.model_cls(obs_dim, action_dim, config, device, perf, self.ensemble_config)

    def update_networks(self) -> list[nn.Module]:
        # The stacked networks are what the update calls (perf.compile compiles them).
        return [self.actor, self.forward_map.net, self.backward_map, self.forward_target.net, self.backward_target]

    # The rollout z --------------------------------------------------------------------------------
    @torch.no_grad()
    def explore_skill(self, obs: np.ndarray, generator=None, member: int | None = None) -> torch.Tensor:
        """The z of the next stretch of rollout at ``obs``: of ``fbee.candidates`` prior draws, the
        one the members disagree on most (ties at random)."""
        candidates = self.sample_skill(self.ensemble_config.candidates, generator=generator)  # (C, d)
        state = torch.as_tensor(np.asarray(obs), dtype=torch.float32, device=self.device)
        states = state.expand(candidates.shape[0], state.shape[-1])
        z = candidates
        if self.members:  # a group's stacked networks score the member's candidates for every member
            states = states.expand(self.members, *states.shape)
            z = candidates.expand(self.members, *candidates.shape)
        scores = self.model.uncertainty(states, z)
        if member is not None and self.members:
            scores = scores[member]
        return candidates[choose_most_uncertain(scores, generator)]

    # The update ---------------------------------------------------------------------------------
    def fb_losses(self, batch: Batch, z: torch.Tensor, next_action: torch.Tensor, backward: torch.Tensor,
                  target_input: torch.Tensor, step: FBStep | None = None) -> dict[str, torch.Tensor]:
        """FB's losses (§7.8-§7.10) with every member's twin-head FB loss against its own target,
        averaged over the members; B's orthonormality loss once (B is shared). The auxiliary Q loss,
        where on, is likewise each member's, averaged."""
        c = self.config
        run = self.net_runner
        ensemble = self.forward_map
        spread, networks = ensemble.spread, ensemble.size * max(self.members, 1)
        discount = spread(batch.discount)  # (C, N, 1)
        z_each = spread(z)
        with torch.no_grad():
            target_forward = run(self.forward_target.net, spread(batch.next_obs), spread(next_action), z_each)
            target_backward = run(self.backward_target, target_input)
            target_m = row_products(target_forward, spread(target_backward), networks).amin(-3)  # (C, N, N)
        forward = run(ensemble.net, spread(batch.obs), spread(batch.action), z_each)  # (C, K, N, d)
        if step is not None:
            step.forward = ensemble.gather(forward).mean(-4)
        m = row_products(forward, spread(backward), networks)  # (C, K, N, N)
        offdiag = offdiag_mean((m - (discount * target_m).unsqueeze(-3)).pow(2))  # (C, K)
        diag = m.diagonal(dim1=-2, dim2=-1).mean(-1)  # (C, K)
        fb_loss = ensemble.gather((0.5 * offdiag - diag).sum(-1)).mean(-1)
        ortho_loss = orthonormality_loss(backward, self.members)
        losses = {"fb_loss": fb_loss, "fb_offdiag": ensemble.gather(offdiag.mean(-1)).mean(-1),
                  "fb_diag": ensemble.gather(diag.mean(-1)).mean(-1), "ortho_loss": ortho_loss}
        total = fb_loss + c.ortho_coef * ortho_loss
        if c.q_loss:
            with torch.no_grad():
                reward = implicit_reward(backward.detach(), z, c.cov_ridge)  # (..., N): B is shared
                next_q = skill_values(target_forward, z_each).amin(-2)  # (C, N)
                target_q = spread(reward.unsqueeze(-1)).squeeze(-1) + discount.squeeze(-1) * next_q
            q = skill_values(forward, z_each)  # (C, K, N)
            q_loss = ensemble.gather((q - target_q.unsqueeze(-2)).pow(2).mean(-1).sum(-1)).mean(-1)
            losses["fb_q_loss"] = q_loss
            losses["implicit_reward"] = member_mean(reward, self.members)
            total = total + c.q_loss_coef * q_loss
        losses["fb_total"] = total
        return losses


# Registration (beside the agent).
from dvfb.agents.registry import AgentSpec, get_spec, register  # noqa: E402

DVFB_SPEC = get_spec("dvfb")


def fbee_label(run, finetune) -> str:
    """``fbee_q`` / ``fbee_f`` by the uncertainty, with the FB family's fine-tuning ablations."""
    section = run.get("fbee", {}) if isinstance(run, dict) else getattr(run, "fbee", None)
    kind = section.get("uncertainty", "q") if isinstance(section, dict) else getattr(section, "uncertainty", "q")
    return fb_finetune_label(f"fbee_{kind}", finetune)


# FBEE's own constants ([C-fbee]): 1M frames, batch 256, gamma 0.98, a 0.3 share of B-derived z's.
FBEE_PRESET = {"frames": 1_000_000, "replay_capacity": 1_000_000,
               "fb": {"batch_size": 256, "discount": 0.98, "mix_ratio": 0.3}}

register(AgentSpec(
    name="fbee", agent_cls=FBEEAgent, family="forward-backward",
    summary="FBEE: online FB exploring with the z its ensemble of forward maps disagrees on most (Urpi et al.)",
    sections={"fb": FBConfig, "fbee": FBEEConfig}, zero_shot="reward_inference", finetuner="dual_value",
    # The authors' code re-chooses z every 100 steps and has no auxiliary implicit-reward Q loss.
    defaults={"fb": {"skill_every": 100, "q_loss": False}},
    presets={"small": {"fb": FB_SMALL}, "fbee": FBEE_PRESET}, label=fbee_label, column=2))


class DVFBFBEEAgent(FBEEAgent):
    """DVFB with FBEE's z choice (docs/methods.md, "FBEE", the hybrid): DVFB's exploration critic
    and actor objective ``Q_M + alpha Q_P`` on FBEE's ensemble, rolled out with the z the ensemble
    disagrees on most. Q_P is conditioned on z, so the chosen z steers both value terms."""

    name = "dvfb_fbee"

    @classmethod
    def components(cls, config) -> list:
        return [ExplorationCritic(config.exploration, config.icm_apt, config.proto, config.cic)]


def dvfb_fbee_label(run, finetune) -> str:
    return fbee_label(run, finetune).replace("fbee_", "dvfb_fbee_", 1)


register(AgentSpec(
    name="dvfb_fbee", agent_cls=DVFBFBEEAgent, family="forward-backward",
    summary="DVFB with FBEE's z choice: the exploration critic on FBEE's ensemble of forward maps",
    sections={**DVFB_SPEC.sections, "fbee": FBEEConfig}, zero_shot="reward_inference", finetuner="dual_value",
    defaults={"fb": {"skill_every": 100}},
    presets={"small": DVFB_SPEC.presets["small"]}, label=dvfb_fbee_label, column=2))
