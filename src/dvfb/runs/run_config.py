"""The typed run configurations: what ``config.json`` holds (docs/methods.md, "Configuration").

One run config describes a run completely and is saved as ``config.json`` in its run directory.

* A **pre-training run** (:class:`PretrainConfig`): the fields every method shares, plus the
  method's own typed sections from the registry (``fb`` and ``exploration`` for DVFB, ``ddpg`` and
  ``rnd`` for RND, ...) and its family's zero-shot (``inference``) and fine-tuning (``finetune``)
  configs, so that zero-shot and fine-tuning of a run use the preset it was trained with unless
  told otherwise. :func:`run_config_class` builds that dataclass once per method, so loading stays
  strict: unknown keys and wrong types are errors.
* A **fine-tuning run** (:class:`FinetuneRunConfig`): which snapshot of which pre-training run,
  the task, the fine-tuner's registered name, and the ``inference`` and ``finetune`` sections of
  its protocols (:func:`finetune_run_config_from_dict`).

Configs written by older versions are read through :mod:`dvfb.runs.migrations`. The presets that
build pre-training configs are :mod:`dvfb.runs.presets`.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dvfb import envs
from dvfb.agents import get_spec
from dvfb.core.config import flag_name, from_dict, param, require_updates, seed_param
from dvfb.core.errors import ConfigError
from dvfb.core.files import read_json
from dvfb.data import ReplaySamplingConfig
from dvfb.nets.execution import DEVICES, PerfConfig
from dvfb.protocols import FinetuneSchedule, protocols_of
from dvfb.runs.migrations import migrate_finetune_run_config, migrate_run_config
from dvfb.runs.wandb_sink import LogConfig

# small, paper, code: every method's; a method may add its own (fbee: its authors' constants).
PRESETS = ("small", "paper", "code", "fbee")
GENERIC_PRESETS = ("small", "paper", "code")
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
    seed: int = seed_param(0, "Seed of the environment, the networks and the sampling.")
    device: str = param("auto", "Torch device: auto picks cuda when available.", DEVICES)
    torch_threads: int = param(0, "Torch threads of the run's process; 0: OMP_NUM_THREADS when set, else half the CPUs "
                               "this process may use (its affinity and cgroup quota), at least one (README.md, "
                               "\"Threads and progress\").", at_least=0)
    processes: int = param(0, "Split a group's members (--seeds) over this many processes (at most one per "
                           "member), each training its share as a group of its own; they share --torch-threads (0: "
                           "the CPUs) equally, at least one thread each (docs/members.md). 0: one single-thread "
                           "process per CPU this process may use, up to one per member, on a CPU (one process on "
                           "CUDA, or when --torch-threads is given); config.json records the number chosen.",
                           at_least=0)
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
    eval_every: int = param(100_000, "Frames between zero-shot evaluations of the current networks while pre-training, "
                            "on small budgets by the method's protocol (metrics/eval.jsonl; docs/health.md); 0: none. "
                            "Training is unchanged by them (their own random streams and environments).", at_least=0)
    eval_tasks: list[str] = param(["all"], "Tasks of the evaluations while pre-training; all: every task of the domain.")
    eval_samples: int = param(10_000, "Newest pre-training transitions the evaluations keep with their physics states: "
                              "each task's reward is computed on them exactly and z_r inferred from them (the methods "
                              "that infer from rewards).", at_least=1)
    eval_skill_steps: int = param(2000, "Reward-labelled steps per task in which an evaluation of a skill-discovery "
                                  "method tries a prior skill per episode and keeps the best.", at_least=1)
    eval_episodes: int = param(2, "Mean-action episodes per task of each evaluation while pre-training.", at_least=1)
    perf: PerfConfig = field(default_factory=PerfConfig,
                             metadata={"help": "How the pre-training updates execute (precision, compilation)."})
    log: LogConfig = field(default_factory=LogConfig,
                           metadata={"help": "Where the metrics go besides metrics/ and tb/: Weights & Biases "
                                             "(docs/methods.md, \"Logging to Weights & Biases\")."})

    def check(self) -> None:
        """Relations between fields (ranges are checked per field)."""
        self._check_neighbours()
        if self.eval_tasks != ["all"] and self.domain in envs.DOMAINS:
            for task in self.eval_tasks:
                if envs.TASKS.get(task) is None or envs.TASKS[task].domain != self.domain:
                    raise ConfigError(f"--eval-tasks: {task!r} is not a task of {self.domain} (its tasks: "
                                      f"{', '.join(envs.tasks_of_domain(self.domain))}; or all)")
        if self.dataset:
            if self.replay.record_physics:
                raise ConfigError("--replay.record-physics records what an online run collects; an offline run "
                                  "(--dataset) collects nothing")
            if self.replay.sampling != "uniform":
                raise ConfigError(f"--replay.sampling {self.replay.sampling} emulates the online driver's loader; "
                                  "offline batches are drawn uniformly from the dataset (--replay.sampling uniform)")
            return
        require_updates("--frames", self.frames, "--seed-frames", self.seed_frames)


    def _check_neighbours(self) -> None:
        """A k-nearest-neighbour reward looks for its k neighbours among the update's batch (the
        row itself included): a k above the batch size would be cut to it silently, so refuse it."""
        sections = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                    if dataclasses.is_dataclass(getattr(self, f.name))}
        batch = next(((name, s.batch_size) for name, s in sections.items() if hasattr(s, "batch_size")), None)
        if batch is None:
            return
        for name, section in sections.items():
            for k_field in ("knn_k", "ce_k"):
                k = getattr(section, k_field, None)
                if k is not None and k > batch[1]:
                    raise ConfigError(f"{flag_name(f'{name}.{k_field}')} {k} is larger than the batch its neighbours "
                                      f"are found in ({flag_name(f'{batch[0]}.batch_size')} {batch[1]})")


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
    """The ``inference`` and ``finetune`` sections of a method's pre-training config: its protocols'
    configs."""
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


def run_config_from_dict(data: dict, source: str = "config") -> PretrainConfig:
    """A pre-training run config from its JSON dict, strictly (unknown keys and wrong types are
    errors), older versions' configs migrated first."""
    if not isinstance(data, dict) or not isinstance(data.get("agent"), str):
        raise ConfigError(f"{source}: not a dvfb run config (no 'agent' field)")
    return from_dict(run_config_class(data["agent"]), migrate_run_config(data, get_spec(data["agent"])))


def load_run_config(path: str | Path) -> PretrainConfig:
    """Read a pre-training run's ``config.json``; errors name the file."""
    try:
        return run_config_from_dict(read_json(Path(path), ConfigError), str(path))
    except ConfigError as exc:
        if str(path) in str(exc):
            raise
        raise ConfigError(f"{path}: {exc}") from exc


@dataclass
class FinetuneRunConfig:
    """A fine-tuning run: which pre-trained snapshot, which task, the fine-tuner (``protocol``) and
    its sections: ``inference``, the method's zero-shot protocol's config, and ``finetune``, the
    fine-tuner's (a :class:`~dvfb.protocols.base.FinetuneSchedule` subclass declared beside it,
    docs/adding_a_method.md, "A fine-tuning protocol"). Read with
    :func:`finetune_run_config_from_dict`, which builds each section as its protocol's class."""

    pretrain_run: str = param("", "Path of the pre-training run directory.")
    agent: str = param("dvfb", "Agent of the pre-training run (copied for reports).")
    domain: str = param("walker", "Domain of the pre-training run.")
    task: str = param("walker_walk", "Downstream task.")
    snapshot: int = param(0, "Pre-training snapshot (frames) the agent starts from.")
    seed: int = seed_param(0, "Seed of the task environment and the fine-tuning randomness.")
    device: str = param("auto", "Torch device.")
    protocol: str = param("", "The registered fine-tuner: the method's own, or one chosen instead with --protocol "
                          "(latent_search, online_inference; docs/methods.md, \"Protocols\").")
    log: LogConfig = field(default_factory=LogConfig,
                           metadata={"help": "Where the metrics go besides metrics/ and tb/: Weights & Biases."})
    # The zero-shot protocols' configs share no base class: each protocol's config_cls.
    inference: Any = field(default=None, metadata={"help": "Zero-shot: the method's protocol's config."})
    finetune: FinetuneSchedule = field(default_factory=FinetuneSchedule,
                                       metadata={"help": "Fine-tuning: the fine-tuner's config."})

    @property
    def own_protocol(self) -> bool:
        """Whether the fine-tuner is the method's own (not one chosen instead with ``--protocol``)."""
        return self.protocol == get_spec(self.agent).finetuner


def finetune_run_config_from_dict(data: dict, source: str = "config") -> FinetuneRunConfig:
    """A fine-tuning run config from its JSON dict, strictly, older versions' configs migrated first
    (a run of the method's own fine-tuner once recorded no protocol); errors name ``source``."""
    if not isinstance(data, dict) or not isinstance(data.get("agent"), str):
        raise ConfigError(f"{source}: not a dvfb fine-tuning config")
    try:
        data = migrate_finetune_run_config(data, get_spec(data["agent"]))
        if not isinstance(data["protocol"], str):
            raise ConfigError(f"FinetuneRunConfig.protocol: expected str, got {data['protocol']!r}")
        zero_shot, finetuner = protocols_of(data["agent"], data["protocol"])
        # A section an older config lacks is its protocol's defaults, as it was read then.
        sections = {"inference": zero_shot.config_cls, "finetune": finetuner.config_cls}
        return from_dict(FinetuneRunConfig, {**{name: {} for name in sections}, **data}, section_types=sections)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from exc


def load_finetune_run_config(path: str | Path) -> FinetuneRunConfig:
    """A fine-tuning run's ``config.json``, strictly; errors name the file."""
    return finetune_run_config_from_dict(read_json(Path(path), ConfigError), str(path))


__all__ = ["DEFAULT_AGENT", "PRESETS", "FinetuneRunConfig", "PretrainConfig", "agent_sections",
           "finetune_run_config_from_dict", "load_finetune_run_config", "load_run_config", "protocol_fields",
           "run_config_class", "run_config_from_dict"]
