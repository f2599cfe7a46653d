"""SMM: state marginal matching with a VAE density and a skill discriminator
(docs/methods.md, "SMM").

Two networks learn on the current state ``s = batch.obs`` and the one-hot skill ``z = batch.z``:

* a VAE on ``v = [s, z]``: encoder ``MLP(|v| -> 150 -> 150)`` (ReLU after both layers), heads
  ``Linear(150 -> 128)`` for the mean and the log-variance, decoder ``MLP(128 -> 150 -> 150 -> |v|)``;
  loss ``beta * mean_rows KL(N(mu, sigma^2) || N(0, I)) + mean squared reconstruction error``
  of one reparameterised sample ``c = mu + eps * sigma``;
* a discriminator ``d(z|s) = MLP(O -> H -> H -> d)`` (logits); loss: mean cross-entropy of the skill
  index.

Both are trained in one optimiser step with one learning rate each (Adam is per parameter and the
two losses share no parameters, so this equals URLB's two separate optimisers).

The reward of a row reuses the per-row terms of that same forward pass, before the step (URLB):

    r = state_ent * h_sz + latent_ent * log d + latent_cond_ent * h_zs,

``h_sz`` the row's *sum* of squared reconstruction errors, ``h_zs`` its discriminator
cross-entropy. URLB adds ``h_zs`` with a plus sign; kept for fidelity. All layers use orthogonal
init with zero biases.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from dvfb.core.config import param
from dvfb.data import Batch
from dvfb.nets import adam, call_network, mlp, orthogonal_init_
from dvfb.nets.members import member_mean, randn
from dvfb.nets.skills import skill_index
from dvfb.rewards.base import IntrinsicReward, Runner
from dvfb.rewards.diayn import rowwise_cross_entropy


@dataclass
class SMMConfig:
    """SMM's skill, VAE, discriminator and reward coefficients (URLB ``smm`` defaults)."""

    skill_dim: int = param(4, "Number d of discrete skills (one-hot width); drawn anew at every episode start.",
                           at_least=2)
    hidden_dim: int = param(1024, "Hidden width of the skill discriminator d(z|s).", at_least=1)
    vae_hidden_dim: int = param(150, "Hidden width of the VAE's encoder and decoder.", at_least=1)
    code_dim: int = param(128, "Width of the VAE's latent code.", at_least=1)
    vae_beta: float = param(0.5, "Weight beta of the VAE's KL term.", at_least=0)
    disc_lr: float = param(1e-3, "Adam learning rate of the skill discriminator.", above=0)
    vae_lr: float = param(1e-2, "Adam learning rate of the VAE.", above=0)
    state_ent: float = param(1.0, "Coefficient of h_sz, the per-row summed squared VAE reconstruction error.")
    latent_ent: float = param(1.0, "Coefficient of the skill prior's entropy log d.")
    latent_cond_ent: float = param(1.0, "Coefficient of h_zs, the per-row discriminator cross-entropy "
                                        "(added with URLB's plus sign).")


class SMMReward(IntrinsicReward):
    """VAE on ``[s, z]`` and discriminator on ``s``; reward from the per-row terms of their losses."""

    def __init__(self, obs_dim: int, skill_dim: int, config: SMMConfig | None = None):
        super().__init__()
        self.config = c = config if config is not None else SMMConfig()
        self.skill_dim = skill_dim
        v, h = obs_dim + skill_dim, c.vae_hidden_dim
        self.discriminator = mlp(obs_dim, c.hidden_dim, c.hidden_dim, skill_dim)
        # The VAE's parts are called one by one (through ``run``), so none returns a tuple.
        self.vae = nn.ModuleDict({
            "encoder": mlp(v, h, h, output_activation=nn.ReLU()),
            "mean": nn.Linear(h, c.code_dim),
            "log_var": nn.Linear(h, c.code_dim),
            "decoder": mlp(c.code_dim, h, h, v),
        })
        orthogonal_init_(self)

    def make_optimizer(self, lr: float, fused: bool = True) -> None:
        """One Adam with a group per network: ``disc_lr`` and ``vae_lr`` (``lr`` is not used)."""
        c = self.config
        groups = [{"params": list(self.discriminator.parameters()), "lr": c.disc_lr},
                  {"params": list(self.vae.parameters()), "lr": c.vae_lr}]
        self.optimizer = adam(groups, c.disc_lr, fused)

    def terms(self, batch: Batch, run: Runner = call_network, noise: torch.Tensor | None = None
              ) -> dict[str, torch.Tensor]:
        """Both losses and their per-row terms on one forward pass.

        ``noise``: the standard-normal ``eps`` of the reparameterised sample, ``(N, code_dim)``
        (default: a fresh draw from torch's global generator).
        Returns ``vae_loss``, ``disc_loss`` (0-d, with gradient), ``h_sz``, ``h_zs`` ``(N, 1)``
        (with gradient) and ``accuracy`` (0-d, detached).
        """
        obs_z = torch.cat([batch.obs, batch.z], dim=-1)
        if noise is None:
            noise = randn((obs_z.shape[-2], self.config.code_dim), self.generator, obs_z.device, obs_z.dtype)
        features = run(self.vae["encoder"], obs_z)
        mean, log_var = run(self.vae["mean"], features), run(self.vae["log_var"], features)
        code = mean + noise * torch.exp(0.5 * log_var)
        squared_error = (run(self.vae["decoder"], code) - obs_z).pow(2)
        kl = -0.5 * (1.0 + log_var - mean.pow(2) - log_var.exp()).sum(dim=-1)
        m = self.members
        vae_loss = self.config.vae_beta * member_mean(kl, m) + member_mean(squared_error, m)

        logits = run(self.discriminator, batch.obs)
        target = skill_index(batch.z)
        cross_entropy = rowwise_cross_entropy(logits, target)
        accuracy = member_mean((logits.detach().argmax(dim=-1) == target).float(), m)
        return {"vae_loss": vae_loss, "disc_loss": member_mean(cross_entropy, m),
                "h_sz": squared_error.sum(dim=-1, keepdim=True), "h_zs": cross_entropy.unsqueeze(-1),
                "accuracy": accuracy}

    def reward(self, h_sz: torch.Tensor, h_zs: torch.Tensor) -> torch.Tensor:
        """``state_ent * h_sz + latent_ent * log d + latent_cond_ent * h_zs`` (detached), ``(N, 1)``."""
        c = self.config
        return (c.state_ent * h_sz.detach() + c.latent_ent * math.log(self.skill_dim)
                + c.latent_cond_ent * h_zs.detach())

    def _step(self, terms: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        self.step(terms["vae_loss"] + terms["disc_loss"])
        return {"smm_vae_loss": terms["vae_loss"].detach(), "smm_disc_loss": terms["disc_loss"].detach(),
                "smm_disc_accuracy": terms["accuracy"], "smm_h_sz": member_mean(terms["h_sz"].detach(), self.members),
                "smm_h_zs": member_mean(terms["h_zs"].detach(), self.members)}

    def update(self, batch: Batch, run: Runner = call_network) -> dict[str, torch.Tensor]:
        return self._step(self.terms(batch, run))

    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        """The reward with the current networks and a fresh sample (the training reward instead
        comes from :meth:`update_and_score`)."""
        with torch.no_grad():
            t = self.terms(batch, run)
        return self.reward(t["h_sz"], t["h_zs"])

    def update_and_score(self, batch: Batch, metrics: dict, run: Runner = call_network) -> torch.Tensor:
        # URLB's reward is the loss pass's own per-row terms (networks before the step, the same
        # reparameterised sample), not a second pass after it.
        terms = self.terms(batch, run)
        reward = self.reward(terms["h_sz"], terms["h_zs"])
        metrics.update(self._step(terms))
        return reward
