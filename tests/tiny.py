"""Tiny network sizes and configs shared by the agent and network tests (fast on one CPU thread), and
a replay of real maze transitions for updates."""

from dvfb.agents.dvfb import ExplorationConfig
from dvfb.agents.fb import FBConfig

OBS, ACT, D, H, E = 5, 3, 8, 32, 16


def tiny_config(**overrides) -> FBConfig:
    """An FBConfig with the tiny widths (z_dim D, hidden H, feature E) and a batch of 32."""
    kw = dict(z_dim=D, hidden_dim=H, feature_dim=E, backward_hidden_dim=H, batch_size=32)
    kw.update(overrides)
    return FBConfig(**kw)


def tiny_exploration(**overrides) -> ExplorationConfig:
    """An ExplorationConfig with tiny RND / contrastive widths and k = 4 neighbours."""
    kw = dict(rnd_rep_dim=16, contrastive_hidden_dim=32, ce_k=4)
    kw.update(overrides)
    return ExplorationConfig(**kw)


# Tiny widths for every config section a registered method may have (a section not listed here
# keeps its small-preset widths, which are still fast enough for a few hundred frames).
TINY_SECTIONS = {
    "fb": dict(z_dim=D, hidden_dim=H, feature_dim=E, backward_hidden_dim=H, batch_size=32),
    "conservative": dict(samples=6),
    "fbee": dict(ensemble=3, candidates=8),
    "sf": dict(z_dim=D, hidden_dim=H, feature_dim=E, backward_hidden_dim=H, batch_size=32),
    "exploration": dict(rnd_rep_dim=16, contrastive_hidden_dim=32, ce_k=4),
    "ddpg": dict(hidden_dim=H, batch_size=32),
    "rnd": dict(hidden_dim=H, rep_dim=16),
    "disagreement": dict(hidden_dim=H),
    "icm_apt": dict(hidden_dim=H, rep_dim=16, knn_k=4),
    "proto": dict(pred_dim=16, proj_dim=32, num_protos=16, queue_size=64),
    "cic": dict(hidden_dim=H, knn_k=4),
    "diayn": dict(hidden_dim=H),
    "smm": dict(hidden_dim=H, vae_hidden_dim=16, code_dim=8),
    "aps": dict(hidden_dim=H, knn_k=4),
    "becl": dict(hidden_dim=H),
    "comsd": dict(hidden_dim=H, knn_k=4),
    "cesd": dict(hidden_dim=H, critic_trunk_dim=16, critic_hidden_dim=32, knn_k=4),
}


def tiny_run_config(agent: str, **top_level):
    """The small-preset run config of a registered method with tiny widths, on the maze by default
    (episodes of 1000 cheap steps), seed frames 500 and an update every 4 steps."""
    from dvfb.agents import get_spec
    from dvfb.core.config import merge
    from dvfb.runs.presets import preset_config

    top = dict(domain="point_mass_maze", frames=1000, seed_frames=500, update_every=4, checkpoint_every=1000,
               log_every=250, torch_threads=1)
    top.update(top_level)
    config = preset_config("small", agent, **top)
    return merge(config, {name: TINY_SECTIONS[name] for name in get_spec(agent).sections if name in TINY_SECTIONS})


def filled_replay(agent, steps: int = 400, seed: int = 0):
    """A replay buffer of real maze transitions (two episodes of uniform actions), with skills
    drawn from the agent's prior when it has one."""
    import numpy as np

    from dvfb import envs
    from dvfb.data import ReplayBuffer

    rng = np.random.default_rng(seed)
    env = envs.make("point_mass_maze_reach_top_left", seed=seed)
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    replay = ReplayBuffer(10_000, obs_dim, action_dim, agent.skill_dim, max_episode_length=1000)
    obs, _ = env.reset(seed=seed)
    replay.start_episode(obs)
    for t in range(steps):
        if t == steps // 2:
            obs, _ = env.reset()
            replay.start_episode(obs)
        skill = agent.sample_skill(1)
        action = rng.uniform(-1, 1, action_dim).astype(np.float32)
        obs, reward, terminated, _, _ = env.step(action)
        replay.add(action, reward, 0.0 if terminated else 1.0, obs, None if skill is None else skill[0].numpy())
    return replay


def tiny_flags(agent: str, sections: tuple[str, ...] | None = None) -> list[str]:
    """``dvfb pretrain`` flags of :data:`TINY_SECTIONS`' widths for ``agent``'s sections (or only
    ``sections`` of them): the command-line twin of :func:`tiny_run_config`."""
    from dvfb.agents import get_spec
    from dvfb.core.config import flag_name

    flags = []
    for section in get_spec(agent).sections:
        if sections is not None and section not in sections:
            continue
        for key, value in TINY_SECTIONS.get(section, {}).items():
            flags += [flag_name(f"{section}.{key}"), str(value)]
    return flags


def random_batch(n: int, seed: int = 0, *, obs_dim: int = OBS, action_dim: int = ACT, step: float | None = 0.3,
                 future: bool = False, reward="normal", discount=0.99, skill=None, dtype=None):
    """A batch of ``n`` random transitions from a seeded generator, drawn in this order: ``obs``;
    ``next_obs`` (``obs`` plus ``step`` times noise; with ``step`` None, independent of ``obs``);
    ``future_obs`` (``next_obs`` plus noise, with ``future``); actions uniform in [-1, 1]; the skill
    (``skill(n, generator)``, or a fixed tensor); the discount (a number, ``"random"`` in [0.9, 1),
    or a tensor); the reward (``"normal"``, ``"positive"`` (uniform + 0.1), ``"zeros"`` or a tensor)."""
    import torch

    from dvfb.data import Batch

    g = torch.Generator().manual_seed(seed)
    kw = {"generator": g, "dtype": dtype}
    obs = torch.randn(n, obs_dim, **kw)
    next_obs = torch.randn(n, obs_dim, **kw) if step is None else obs + step * torch.randn(n, obs_dim, **kw)
    future_obs = next_obs + (step or 0.3) * torch.randn(n, obs_dim, **kw) if future else None
    action = torch.rand(n, action_dim, **kw) * 2 - 1
    z = skill(n, generator=g) if callable(skill) else skill
    if isinstance(discount, str):
        discount = 0.9 + 0.1 * torch.rand(n, 1, **kw)
    elif not isinstance(discount, torch.Tensor):
        discount = torch.full((n, 1), float(discount), dtype=dtype)
    if isinstance(reward, str):
        reward = {"normal": lambda: torch.randn(n, 1, **kw), "positive": lambda: torch.rand(n, 1, **kw) + 0.1,
                  "zeros": lambda: torch.zeros(n, 1, dtype=dtype)}[reward]()
    return Batch(obs, action, reward, discount, next_obs, future_obs, z)


def replayed_return(run, task: str, z, seed: int) -> float:
    """The return of one mean-action episode of ``run``'s model with the skill ``z`` (None for a
    single policy) in ``task``'s environment made with ``seed``, stepped here by hand: what a
    zero-shot result's first return must be."""
    import numpy as np

    import dvfb
    from dvfb import envs

    model = dvfb.load(run)
    env = envs.make(task, seed=seed)
    obs, _ = env.reset()
    total, done = 0.0, False
    skill = None if z is None else np.asarray(z, dtype=np.float32)
    while not done:
        obs, reward, terminated, truncated, _ = env.step(model.act(obs, skill))
        total += float(reward)
        done = terminated or truncated
    return total
