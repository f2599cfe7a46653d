"""Task inference from interaction alone: OpTI-BFM (docs/methods.md, "Online task inference").

No labelled data: the agent acts in the task with the mean actions of ``pi(s, proj z)``, sees the
reward only of the states it visits, and infers the task vector online. With the features
``phi = Cov(B)^-1 B`` (FB and its variants; Cov from the pre-training data, stored in the snapshot)
or ``phi(s')`` (the successor features) a linear reward ``r = phi . w*`` makes ``F(s, a, z) . w*``
the value of ``pi_z``, so choosing z is a linear bandit whose context is the state and whose arm
features are ``psi_k(s, z) = F_k(s, pi(s, proj z), proj z)`` (one per twin head). A Bayesian linear regression (:class:`BayesianLinearRegression`, float64) keeps
the estimate ``w_hat`` and its confidence ellipsoid; the skill of a step is chosen

* ``ucb`` (OpTI-BFM): the best of ``candidates`` draws uniform in the ellipsoid
  ``||w - w_hat||_V <= 2 beta`` by ``min_k [psi_k . w_hat + beta ||psi_k||_{V^-1}]``
  (:func:`ucb_choice`);
* ``ts`` (OpTI-BFM-TS): one draw of the posterior ``N(w_hat, V^-1)``;
* ``random`` (the paper's Random baseline fed to the same regression): uniform in the unit ball.

It runs on the fine-tuning loop as a :class:`~dvfb.protocols.base.Finetuner` that trains nothing:
before each step's choice the regression takes the newest transition of the fine-tuning replay
(``x = phi(s')`` and its reward); the evaluation skill is ``proj(w_hat)`` (a prior draw before any
data), so the fine-tuning workflow's evaluations at 0 and at the end are "before any interaction"
and "the final z, frozen". Every episode's return goes into the curve (``records_episodes``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from dvfb.agents.base import Model, ReplayNeeds
from dvfb.core.config import param
from dvfb.core.errors import ConfigError
from dvfb.protocols.base import Finetuner, FinetuneSchedule, register_finetuner, reward_features

# The features a method's task reward is linear in (protocols.base.reward_features): FB's reward of
# z is B . Cov^-1 z, so phi = Cov(B)^-1 B ("measure", Cov stored in the snapshot); the successor
# features' is phi . z, so phi itself ("regression").
RULES = ("ucb", "ts", "random")
SAMPLINGS = ("ellipsoid", "ball")
TIE_BREAK = 1e-8  # scale of the uniform noise that breaks ties between equal UCB scores


@dataclass
class OnlineInferenceConfig(FinetuneSchedule):
    """Online task inference (OpTI-BFM): its budget on the fine-tuning loop and the bandit's constants."""

    frames: int = param(10_000, "Steps of interaction with the task (10 episodes of 1000 steps), every one "
                        "with a reward seen only for the state visited.", at_least=1)
    eval_every: int = param(10_000, "Evaluate the current z = proj(w_hat) every this many steps (and at 0, "
                            "before any interaction, and at the end).", at_least=1)
    eval_episodes: int = param(50, "Mean-action episodes per evaluation.", at_least=1)
    seed_frames: int = param(1, "Steps before the first bookkeeping update (it only logs the regression; "
                             "at least 1: there is no transition to draw before the first step).", at_least=1)
    update_every: int = param(1, "Log the regression's metrics every this many steps (the regression itself "
                              "takes every step).", at_least=1)
    replay_capacity: int = param(1000, "Fine-tuning replay capacity in transitions (it only hands over the "
                                 "newest transition; at least one episode).", at_least=1)
    checkpoint_every: int = param(1000, "Write a resume checkpoint every this many steps (at episode ends).",
                                  at_least=1)
    rule: str = param("ucb", "How z is chosen: ucb (OpTI-BFM, optimism over the confidence ellipsoid), ts "
                      "(OpTI-BFM-TS, a draw of the posterior) or random (the baseline: uniform in the unit ball, the "
                      "same regression).", RULES)
    beta: float = param(0.1, "ucb: radius beta of the confidence ellipsoid (the bonus beta ||psi||_{V^-1}; "
                        "candidates are drawn within 2 beta).", at_least=0)
    ridge: float = param(1.0, "Prior precision lambda: V = lambda I + sum x x^T / sigma^2.", above=0)
    ucb_noise: float = param(1.0, "ucb and random: reward noise sigma of the regression.", above=0)
    ts_noise: float = param(0.01, "ts: reward noise sigma_n of the posterior N(w_hat, V^-1).", above=0)
    candidates: int = param(128, "ucb: random-shooting candidates per choice.", at_least=1)
    sampling: str = param("ellipsoid", "ucb: candidates uniform in the 2 beta ellipsoid around w_hat, or "
                          "uniform in the unit ball.", SAMPLINGS)
    period: int = param(1, "Steps between choices of z (also at each episode start); 1000 = once per episode "
                        "(the -EP variant).", at_least=1)
    decay: float = param(1.0, "Forgetting rho per step: V <- rho V + x x^T, b <- rho b + r x (prior "
                         "included); 1 = none.", above=0, at_most=1)
    gate: float = param(0.0, "Label gating kappa: add a datum only if its leverage ||x / sigma||^2_{V^-1} "
                        ">= e^kappa - 1 (0 = always).", at_least=0)


# ---------------------------------------------------------------------------------------------
# The regression


class BayesianLinearRegression:
    """Bayesian linear regression of rewards on features, in float64:

    ``V = rho^t lambda I + sum_s rho^(t-s) x_s x_s^T / sigma^2``, ``b = sum_s rho^(t-s) r_s x_s / sigma^2``,
    ``w_hat = V^-1 b``: the ridge least-squares estimate, the mean of the posterior ``N(w_hat, V^-1)``
    of a prior ``N(0, I / lambda)`` and Gaussian reward noise ``sigma``, and the centre of the
    confidence ellipsoid ``||w - w_hat||_V <= beta``.

    Each :meth:`observe` is one step: ``V`` and ``b`` decay by ``rho``, then the datum is added if its
    leverage ``h = x^T V^-1 x / sigma^2`` reaches ``e^kappa - 1`` (the gate; kappa = 0 adds all). ``V``
    is refactorised (Cholesky ``V = L L^T``) once after each change, when it is next needed. The
    state stays on ``device`` and no step reads a value back to the host.
    """

    def __init__(self, dim: int, ridge: float = 1.0, noise: float = 1.0, decay: float = 1.0, gate: float = 0.0,
                 device: str | torch.device = "cpu"):
        self.dim, self.ridge, self.noise, self.decay, self.gate = dim, ridge, noise, decay, gate
        self.threshold = math.expm1(gate)
        self.device = torch.device(device)
        f64 = {"dtype": torch.float64, "device": self.device}
        self.precision = ridge * torch.eye(dim, **f64)  # V
        self.moment = torch.zeros(dim, **f64)  # b
        self.count = torch.zeros((), **f64)  # data added
        self.skipped = torch.zeros((), **f64)  # data the gate left out
        self._factor: torch.Tensor | None = None
        self._mean: torch.Tensor | None = None

    # The state ----------------------------------------------------------------------------------
    @property
    def factor(self) -> torch.Tensor:
        """The lower Cholesky factor L of ``V = L L^T``."""
        if self._factor is None:
            # cholesky_ex: no host sync for the error check; V is positive definite by construction.
            self._factor = torch.linalg.cholesky_ex(self.precision)[0]
        return self._factor

    @property
    def mean(self) -> torch.Tensor:
        """``w_hat = V^-1 b``, ``(d,)``."""
        if self._mean is None:
            self._mean = torch.cholesky_solve(self.moment.unsqueeze(-1), self.factor)[:, 0]
        return self._mean

    def _changed(self) -> None:
        self._factor = self._mean = None

    # Data ---------------------------------------------------------------------------------------
    def leverage(self, x: torch.Tensor) -> torch.Tensor:
        """``h = ||x / sigma||^2_{V^-1} = x^T V^-1 x / sigma^2`` of features ``x (..., d)``, ``(...)``."""
        return self.norms(x.to(self.precision) / self.noise) ** 2

    def observe(self, x: torch.Tensor, reward: torch.Tensor | float) -> tuple[torch.Tensor, torch.Tensor]:
        """One step with features ``x (d,)`` and its reward: decay, then add the datum if the gate
        lets it through. Returns its leverage ``h`` (under the decayed V) and whether it was added
        (0-dim tensors)."""
        x = x.to(self.precision).reshape(self.dim) / self.noise
        reward = torch.as_tensor(reward, dtype=torch.float64, device=self.device).reshape(()) / self.noise
        if self.decay != 1.0:
            factor = None if self._factor is None else self._factor * math.sqrt(self.decay)
            self.precision.mul_(self.decay)
            self.moment.mul_(self.decay)
            self._changed()
            self._factor = factor  # the Cholesky factor of rho V is sqrt(rho) L
        h = self.norms(x) ** 2
        added = h >= self.threshold
        weight = added.to(torch.float64)
        self.precision.add_(torch.outer(x, x) * weight)
        self.moment.add_(x * (reward * weight))
        self.count.add_(weight)
        self.skipped.add_(1 - weight)
        self._changed()
        return h, added

    # The confidence ellipsoid and the posterior -------------------------------------------------
    def norms(self, v: torch.Tensor) -> torch.Tensor:
        """``||v||_{V^-1} = sqrt(v^T V^-1 v)`` of ``v (..., d)``, ``(...)``."""
        flat = v.to(self.precision).reshape(-1, self.dim)
        solved = torch.linalg.solve_triangular(self.factor, flat.mT, upper=False)  # L^-1 v
        return solved.square().sum(0).sqrt().reshape(v.shape[:-1])

    def ucb(self, psi: torch.Tensor, beta: float) -> torch.Tensor:
        """``max_{||w - w_hat||_V <= beta} psi . w = psi . w_hat + beta ||psi||_{V^-1}`` of ``psi (..., d)``."""
        psi = psi.to(self.precision)
        return psi @ self.mean + beta * self.norms(psi)

    def _through_ellipsoid(self, u: torch.Tensor) -> torch.Tensor:
        """``w_hat + L^-T u`` of ``u (n, d)``: ``||w - w_hat||_V = ||u||``, and ``N(0, I)`` becomes ``N(0, V^-1)``."""
        offsets = torch.linalg.solve_triangular(self.factor.mT, u.mT, upper=True).mT
        return self.mean + offsets

    def ellipsoid_samples(self, n: int, radius: float, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` draws uniform in the ellipsoid ``||w - w_hat||_V <= radius``, ``(n, d)``."""
        return self._through_ellipsoid(ball_samples(n, self.dim, radius, generator, self.device))

    def posterior_samples(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` draws of the posterior ``N(w_hat, V^-1)``, ``(n, d)``."""
        return self._through_ellipsoid(_randn(n, self.dim, generator, self.device))

    # Resume -------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        # Copies: the state is updated in place afterwards.
        return {key: getattr(self, key).detach().cpu().clone() for key in ("precision", "moment", "count", "skipped")}

    def load_state_dict(self, state: dict) -> None:
        for key in ("precision", "moment", "count", "skipped"):
            value = torch.as_tensor(state[key])
            if value.shape != getattr(self, key).shape:
                raise ValueError(f"the regression's {key} has shape {tuple(value.shape)}, expected "
                                 f"{tuple(getattr(self, key).shape)}")
            setattr(self, key, value.to(device=self.device, dtype=torch.float64).clone())
        self._changed()


def _randn(n: int, dim: int, generator: torch.Generator | None, device: torch.device) -> torch.Tensor:
    where = generator.device if generator is not None else device
    return torch.randn(n, dim, generator=generator, dtype=torch.float64, device=where).to(device)


def ball_samples(n: int, dim: int, radius: float, generator: torch.Generator | None = None,
                 device: str | torch.device = "cpu") -> torch.Tensor:
    """``n`` draws uniform in the ball of ``radius`` in ``dim`` dimensions (float64, ``(n, dim)``):
    a Gaussian direction, and a radius ``radius * U^(1/dim)``."""
    device = torch.device(device)
    direction = _randn(n, dim, generator, device)
    direction = direction / direction.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    where = generator.device if generator is not None else device
    scale = torch.rand(n, 1, generator=generator, dtype=torch.float64, device=where).to(device) ** (1.0 / dim)
    return radius * scale * direction


# ---------------------------------------------------------------------------------------------
# The choices of z


def project(w: torch.Tensor) -> torch.Tensor:
    """``proj(w) = sqrt(d) w / ||w||`` row-wise in float64, without the networks' floor of 1e-12 on
    the norm (``w_hat`` has the rewards' scale, however small)."""
    w = w.to(torch.float64)
    return math.sqrt(w.shape[-1]) * w / w.norm(dim=-1, keepdim=True).clamp_min(1e-300)


def ucb_choice(regression: BayesianLinearRegression, successor_features: Callable[[torch.Tensor], torch.Tensor],
               beta: float, candidates: int, generator: torch.Generator | None = None,
               sampling: str = "ellipsoid") -> tuple[torch.Tensor, torch.Tensor]:
    """OpTI-BFM's choice by random shooting: ``candidates`` draws ``w`` (uniform in the ellipsoid
    ``||w - w_hat||_V <= 2 beta``, or in the unit ball), each scored by the pessimistic UCB of its
    successor features ``min_k [psi_k . w_hat + beta ||psi_k||_{V^-1}]``, ``psi = successor_features(proj w)``
    ``(K, n, d)``; the best, with a tie-break of uniform noise of scale 1e-8. Returns ``(proj w, its score)``
    (float64)."""
    if sampling == "ellipsoid":
        draws = regression.ellipsoid_samples(candidates, 2 * beta, generator)
    else:
        draws = ball_samples(candidates, regression.dim, 1.0, generator, regression.device)
    z = project(draws)
    scores = regression.ucb(successor_features(z), beta).amin(0)
    where = generator.device if generator is not None else regression.device
    noise = torch.rand(candidates, generator=generator, dtype=torch.float64, device=where).to(regression.device)
    best = torch.argmax(scores + TIE_BREAK * noise)
    return z[best], scores[best]


def thompson_choice(regression: BayesianLinearRegression,
                    generator: torch.Generator | None = None) -> torch.Tensor:
    """OpTI-BFM-TS's choice: ``proj(w)`` of one draw ``w ~ N(w_hat, V^-1)`` (float64)."""
    return project(regression.posterior_samples(1, generator)[0])


# ---------------------------------------------------------------------------------------------
# The protocol


def _covariance(model: Model) -> torch.Tensor | None:
    statistics = getattr(model, "statistics", None) or {}
    return statistics.get("cov_backward")


@register_finetuner
class OnlineInference(Finetuner):
    """Task inference from interaction alone on the fine-tuning loop (see the module docstring).

    Nothing is trained: F, B and the actor are the pre-trained ones, actions are the actor's means
    (temperature 0) from the first step, and the "update" of fine-tuning only reports the
    regression (the regression takes each transition in :meth:`rollout_skill`).
    """

    name = "online_inference"
    config_cls = OnlineInferenceConfig
    uniform_seed_actions = False
    infers_skill = False
    records_episodes = True
    replaces = ("dual_value",)

    def __init__(self, model: Model, skill: torch.Tensor | None, config: OnlineInferenceConfig):
        nn.Module.__init__(self)
        self.check(model, config)
        self.model, self.config = model, config
        device = model.device
        self.cov_inverse = None  # raw features: none
        if reward_features(model) == "measure":
            cov = _covariance(model).to(device=device, dtype=torch.float64)
            self.cov_inverse = torch.cholesky_inverse(torch.linalg.cholesky(cov))
        noise = config.ucb_noise if config.rule == "ucb" else config.ts_noise
        self.regression = BayesianLinearRegression(model.skill_dim, config.ridge, noise, config.decay, config.gate,
                                                   device)
        # The evaluation skill before any datum: a prior draw (the protocol starts from no knowledge).
        prior = model.sample_skill(1)[0] if skill is None else skill
        self.prior = prior.detach().clone().to(device=device, dtype=torch.float32)
        self.current: torch.Tensor | None = None  # the z of the latest choice
        self.last_choice = -1  # the step of the latest choice
        self.last_key: tuple[int, int] | None = None  # the newest transition taken
        self.replay = None
        zero = torch.zeros((), dtype=torch.float64, device=device)
        self.last = {"leverage": zero, "reward": zero, "score": zero}

    # The protocol's interface -----------------------------------------------------------------
    @classmethod
    def check(cls, model: Model, config: OnlineInferenceConfig) -> None:
        kind = reward_features(model)
        if kind is None or not model.learns_skill_value or model.skill_dim == 0:
            raise ConfigError(f"online task inference needs a model of the FB family or the successor features "
                              f"(rewards linear in features, a forward map, a skill z); {model.name!r} is neither")
        if kind == "regression":
            return
        cov = _covariance(model)
        d = model.skill_dim
        if cov is None:
            raise ConfigError("online task inference needs Cov(B) of the pre-training data, which this snapshot "
                              "lacks (it was written by an older dvfb): re-make the snapshot with this version")
        if tuple(cov.shape) != (d, d) or not bool(torch.isfinite(cov).all()) \
                or int(torch.linalg.cholesky_ex(cov.double())[1]) != 0:
            raise ConfigError(f"the snapshot's Cov(B) is not a finite positive-definite {d}x{d} matrix: re-make "
                              "the snapshot")

    @classmethod
    def check_group(cls, config: OnlineInferenceConfig) -> None:
        raise ConfigError("online_inference runs one run at a time (each chooses its own z from its own "
                          "rewards): run the members one by one")

    @classmethod
    def needs_of(cls, model: Model) -> ReplayNeeds:
        # The update reads no batch: the smallest draw.
        return ReplayNeeds(1, model.settings.discount)

    def bind_replay(self, replay) -> None:
        self.replay = replay

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {}

    def update_networks(self) -> list[nn.Module]:
        return [self.model.actor, self.model.forward_map]  # every choice of ucb calls them

    def act(self, obs, skills, explore: bool):
        return self.model.act(obs, skills, False)  # mean actions while inferring (temperature 0)

    @property
    def skill(self) -> torch.Tensor:
        """The evaluation skill: ``proj(w_hat)`` of every transition so far (the prior draw before any
        datum, or while every reward has been 0). The projection is computed in float64 without a
        floor on the norm: ``w_hat`` has the rewards' scale, however small."""
        self.absorb()
        mean = self.regression.mean
        norm = float(mean.norm())
        if float(self.regression.count) == 0 or not 0 < norm < math.inf:
            return self.prior
        return project(mean).to(torch.float32)

    def rollout_skill(self, step: int, episode_start: bool, current: torch.Tensor | None,
                      generator: torch.Generator | None = None, obs: np.ndarray | None = None) -> torch.Tensor:
        """Take the newest transition into the regression, then choose the step's z at ``obs`` when
        a choice is due (every ``period`` steps and at each episode start)."""
        self.absorb()
        due = self.current is None or episode_start or step - self.last_choice >= self.config.period
        if due:
            self.current = self.choose(obs, generator if generator is not None else self.generator)
            self.last_choice = step
        return self.current

    def update(self, batch) -> dict[str, torch.Tensor]:
        regression = self.regression
        metrics = {"w_norm": regression.mean.norm(), "data": regression.count.clone(),
                   "gated_out": regression.skipped.clone(), "leverage": self.last["leverage"],
                   "reward": self.last["reward"]}
        if self.config.rule == "ucb":
            metrics["ucb"] = self.last["score"]
        return metrics

    # The inference ----------------------------------------------------------------------------
    @torch.no_grad()
    def features(self, obs: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """The features of transitions ``(n, O)`` that the task's reward is regressed on, float64
        ``(n, d)``: FB's ``phi = Cov(B)^-1 B`` (the reward ``B . Cov^-1 z`` of its skill z is then
        ``phi . z``), the successor features' ``phi(s')`` itself."""
        features = self.model.backward_features(obs, next_obs).to(torch.float64)
        return features if self.cov_inverse is None else features @ self.cov_inverse

    @torch.no_grad()
    def absorb(self) -> None:
        """The replay's newest transition into the regression, once."""
        if self.replay is None:
            return
        found = self.replay.newest()
        if found is None or found[0] == self.last_key:
            return
        key, obs, reward, next_obs = found
        device = self.model.device
        x = self.features(obs.to(device).unsqueeze(0), next_obs.to(device).unsqueeze(0))[0]
        h, _ = self.regression.observe(x, reward.to(device))
        self.last_key = key
        self.last["leverage"], self.last["reward"] = h, reward.to(device=device, dtype=torch.float64)

    @torch.no_grad()
    def successor_features(self, obs: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """``psi_k(s, z) = F_k(s, pi(s, z), z)`` of one state ``(O,)`` and skills ``z (n, d)`` (already
        projected), float64 ``(K, n, d)``: the mean action of the skill's policy."""
        run, model = self.net_runner, self.model
        z = z.to(torch.float32)
        states = obs.expand(z.shape[0], -1)
        action = run(model.actor, states, z)
        return run(model.forward_map, states, action, z).to(torch.float64)

    @torch.no_grad()
    def choose(self, obs: np.ndarray, generator: torch.Generator | None) -> torch.Tensor:
        """The z of a step at ``obs`` by the configured rule (float32, ``(d,)``)."""
        c = self.config
        if c.rule == "ts":
            return thompson_choice(self.regression, generator).to(torch.float32)
        if c.rule == "random":
            draw = ball_samples(1, self.regression.dim, 1.0, generator, self.regression.device)[0]
            return project(draw).to(torch.float32)
        if obs is None:
            raise ValueError("the ucb rule chooses z at the step's observation: pass obs")
        state = torch.as_tensor(np.asarray(obs), dtype=torch.float32, device=self.model.device)
        z, score = ucb_choice(self.regression, lambda zs: self.successor_features(state, zs), c.beta, c.candidates,
                              generator, c.sampling)
        self.last["score"] = score
        return z.to(torch.float32)

    # Resume -------------------------------------------------------------------------------------
    def training_state(self) -> dict:
        return {"regression": self.regression.state_dict(), "prior": self.prior.cpu().clone(),
                "current": None if self.current is None else self.current.cpu().clone(),
                "last_choice": self.last_choice, "last_key": None if self.last_key is None else list(self.last_key),
                "last": {k: v.cpu().clone() for k, v in self.last.items()}}

    def load_training_state(self, state: dict) -> None:
        device = self.model.device
        self.regression.load_state_dict(state["regression"])
        self.prior = state["prior"].to(device=device, dtype=torch.float32)
        self.current = None if state["current"] is None else state["current"].to(device=device, dtype=torch.float32)
        self.last_choice = int(state["last_choice"])
        self.last_key = None if state["last_key"] is None else (int(state["last_key"][0]), int(state["last_key"][1]))
        self.last = {k: torch.as_tensor(state["last"][k]).to(device=device, dtype=torch.float64)
                     for k in ("leverage", "reward", "score")}
