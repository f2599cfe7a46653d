"""The JSON records of a run directory, typed (docs/architecture.md, "Run directories").

Each record class knows its ``kind``, its current ``format`` and how it is written and read; the
files keep the layout dvfb has always written (the format lives in the class, not in the file):

* :class:`PretrainSummary` -- ``RUN/pretrain_summary.json``, written when a pre-training finishes;
* :class:`ZeroShotResult` -- ``RUN/zeroshot/<task>[@<frames>].json``, one zero-shot evaluation;
* :class:`Curve` -- ``RUN/finetune/<name>/curve.json``, a fine-tuning run's evaluations;
* :class:`FinetuneSummary` -- ``RUN/finetune/<name>/finetune_summary.json``, written when it finishes.

Reading a record checks the fields its readers need and names the file when one is missing or of
the wrong type (``error``: the caller's error class).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from dvfb.core.errors import RunDirError
from dvfb.core.files import read_json, write_json_atomic


@dataclass(kw_only=True)
class Record:
    """Base of the JSON records: ``to_json`` in field order, the optional fields left out when None."""

    kind: ClassVar[str] = ""
    format: ClassVar[int] = 1
    optional: ClassVar[tuple[str, ...]] = ()
    # Fields a reader needs, with their types: a file lacking one is an error that names it.
    required: ClassVar[dict[str, type | tuple[type, ...]]] = {}

    def to_json(self) -> dict:
        data = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return {k: v for k, v in data.items() if not (k in self.optional and v is None)}

    def write(self, path: str | Path) -> None:
        write_json_atomic(path, self.to_json())

    @classmethod
    def from_json(cls, data: Any, where: str | Path, error: type[Exception] = RunDirError):
        if not isinstance(data, dict):
            raise error(f"{where} does not hold a JSON object")
        for key, types in cls.required.items():
            value = data.get(key)
            if value is None or (isinstance(value, bool) and bool not in _as_tuple(types)) \
                    or not isinstance(value, types):
                raise error(f"{where}: {key!r} is missing or not {_type_names(types)}")
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})

    @classmethod
    def read(cls, path: str | Path, error: type[Exception] = RunDirError):
        return cls.from_json(read_json(path, error), path, error)


def _as_tuple(types) -> tuple:
    return types if isinstance(types, tuple) else (types,)


def _type_names(types) -> str:
    if set(_as_tuple(types)) == {int, float}:
        return "a number"
    names = {int: "an integer", float: "a number", str: "a string", list: "a list", dict: "an object"}
    return " or ".join(dict.fromkeys(names.get(t, t.__name__) for t in _as_tuple(types)))


NUMBER = (int, float)


@dataclass(kw_only=True)
class PretrainSummary(Record):
    """What a finished pre-training reports (``frames``: the step it finished at)."""

    kind: ClassVar[str] = "pretrain_summary"
    optional: ClassVar[tuple[str, ...]] = ("rebuilt",)
    required: ClassVar[dict] = {"frames": int}

    agent: str | None = None
    domain: str | None = None
    frames: int
    episodes: int | None = None
    wall_clock_s: float | None = None
    frames_per_s: float | None = None
    resumed_from: int | None = None
    device: str | None = None
    rebuilt: bool | None = None  # True: remade from the last checkpoint after the file was lost


@dataclass(kw_only=True)
class FinetuneSummary(Record):
    """What a finished fine-tuning reports."""

    kind: ClassVar[str] = "finetune_summary"
    optional: ClassVar[tuple[str, ...]] = ("zero_shot_success_rate", "final_success_rate", "rebuilt")
    required: ClassVar[dict] = {"frames": int}

    task: str | None = None
    frames: int
    wall_clock_s: float | None = None
    zero_shot_return: float | None = None
    final_return: float | None = None
    zero_shot_success_rate: float | None = None
    final_success_rate: float | None = None
    rebuilt: bool | None = None  # True: remade from the last checkpoint after the file was lost


@dataclass(kw_only=True)
class ZeroShotResult(Record):
    """One zero-shot evaluation of a pre-trained run on a task: the skill, how it was found (the
    protocol's record), and the evaluation's returns (and success rates where the task has them)."""

    kind: ClassVar[str] = "zeroshot_result"
    optional: ClassVar[tuple[str, ...]] = ("success_rate", "successes", "group")
    required: ClassVar[dict] = {"mean_return": NUMBER}

    task: str
    domain: str | None = None
    agent: str | None = None
    preset: str | None = None
    pretrain_seed: int | None = None
    seed: int | None = None
    snapshot_frames: int | None = None
    protocol: str | None = None
    skill_source: str | None = None
    inference: dict | None = None
    inference_info: Any = None
    z: list | None = None
    mean_return: float
    std_return: float | None = None
    returns: list | None = None
    success_rate: float | None = None
    successes: list | None = None
    eval_episodes: int | None = None
    wall_clock_s: float | None = None
    group: list[str] | None = None  # the runs evaluated together (docs/members.md)

    @classmethod
    def from_json(cls, data: Any, where: str | Path, error: type[Exception] = RunDirError):
        if isinstance(data, dict) and "task" not in data:
            data = {**data, "task": Path(where).stem.split("@", 1)[0]}
        return super().from_json(data, where, error)


@dataclass(kw_only=True)
class Curve(Record):
    """A fine-tuning run's evaluations: one point per evaluation, ``{"frames", "mean_return",
    "std_return", "returns"}`` (and ``success_rate``, ``successes`` where the task has them)."""

    kind: ClassVar[str] = "finetune_curve"
    required: ClassVar[dict] = {"curve": list}
    optional: ClassVar[tuple[str, ...]] = ("protocol", "episodes")

    task: str | None = None
    domain: str | None = None
    agent: str | None = None
    seed: int | None = None
    snapshot: int | None = None
    z: list | None = None
    inference_info: Any = None
    curve: list[dict]
    # A protocol chosen instead of the method's fine-tuner (None: the method's own), and, for the
    # protocols that record them, every training episode: {"frames", "return"}.
    protocol: str | None = None
    episodes: list[dict] | None = None

    @classmethod
    def from_json(cls, data: Any, where: str | Path, error: type[Exception] = RunDirError):
        curve = super().from_json(data, where, error)
        for point in curve.curve:
            if not isinstance(point, dict):
                raise error(f"{where}: a point of 'curve' is not an object")
            for key in ("frames", "mean_return"):
                value = point.get(key)
                if isinstance(value, bool) or not isinstance(value, NUMBER):
                    raise error(f"{where}: {key!r} is missing or not a number")
        return curve


def curve_point(frames: int, evaluation_summary: dict) -> dict:
    """A point of a :class:`Curve`: the frames and an evaluation's summary."""
    return {"frames": frames, **evaluation_summary}


__all__ = ["Curve", "FinetuneSummary", "PretrainSummary", "Record", "ZeroShotResult", "curve_point"]
