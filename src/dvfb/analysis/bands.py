"""Reference bands and the health verdict of a run (docs/health.md).

* :func:`make_bands` turns a study's committed results into bands: per method, domain, preset,
  budget, task and snapshot, the mean, minimum and maximum over the seeds of the zero-shot return
  (``RUN/zeroshot/<task>[@<frames>].json``), and per domain and task the random policy's episodes
  (``dvfb random-policy --output`` files). ``dvfb bands`` writes them; the package ships those of
  docs/results/cpu_100k (:data:`PACKAGED`), regenerated when the study gains cells.
* :func:`verdicts` reads a run's newest evaluation while pre-training (``metrics/eval.jsonl``) against
  its method's band at the nearest snapshot: inside, above or below it, or no band for its method,
  domain, preset or step; and it flags, in words a user can act on, an evaluation that is not
  finite and a return still inside the random policy's band where the reference runs had left it.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from dvfb.analysis.common import (AnalysisError, discover_runs, method_name, random_scores, read_json_object,
                                  zeroshot_scores)
from dvfb.core.files import write_json_atomic

BANDS_FORMAT = 1
PACKAGED = "reference_bands.json"  # in dvfb/data: docs/results/cpu_100k's bands
# A band speaks for evaluations within this fraction of its snapshot's frames (25k: 12.5k-37.5k);
# further away the run is at a budget the reference did not measure.
NEAREST = 0.5
# "Not learning" needs a reference that had left the random policy's returns clearly: its lowest seed
# at least this many times the random policy's spread (max - min) above the random policy's best
# episode. Three seeds at a first snapshot barely above random (DVFB on walker_walk at 25k: 52.6
# against 43.1) say little about a fourth: a healthy run of the same method scored 17.3 there
# (docs/health.md, "How the verdict was checked").
CLEAR_OF_RANDOM = 1.0


@dataclass(frozen=True)
class Band:
    """The seeds' zero-shot returns of one method on one task at one snapshot."""

    method: str
    domain: str
    preset: str
    budget: int  # the pre-training frames of the runs the band came from
    task: str
    frames: int  # the snapshot's
    seeds: int
    mean: float
    min: float
    max: float


@dataclass(frozen=True)
class RandomBand:
    """The random policy's episode returns on one task."""

    domain: str
    task: str
    episodes: int
    mean: float
    min: float
    max: float


def make_bands(paths: Sequence[str | Path], random_files: Sequence[str | Path] = ()) -> dict:
    """The bands of every pre-training run under ``paths`` and of the random-policy files (module
    docstring), as the JSON object ``dvfb bands`` writes. Runs of one method, domain, preset and
    budget are one band's seeds."""
    runs = discover_runs(paths).pretrain
    if not runs:
        raise AnalysisError(f"no pre-training runs under {', '.join(map(str, paths))}")
    returns: dict[tuple, list[float]] = defaultdict(list)
    for entry in runs:
        config = entry.config
        for score in zeroshot_scores([entry], every_snapshot=True):
            frames = score.pretrain_frames if score.pretrain_frames is not None else config.frames
            returns[(entry.method, config.domain, config.preset, config.frames, score.task, frames)].append(score.value)
    bands = [Band(method, domain, preset, budget, task, frames, len(values), float(np.mean(values)),
                  float(np.min(values)), float(np.max(values)))
             for (method, domain, preset, budget, task, frames), values in sorted(returns.items())]
    randoms = []
    for raw in random_files:
        data = read_json_object(Path(raw))
        for score in random_scores([raw]):
            episodes = data["tasks"][score.task].get("returns") or [score.value]
            randoms.append(RandomBand(score.domain, score.task, len(episodes), float(np.mean(episodes)),
                                      float(np.min(episodes)), float(np.max(episodes))))
    return {"format": BANDS_FORMAT, "bands": [asdict(b) for b in bands], "random": [asdict(r) for r in randoms]}


def write_bands(bands: dict, out: str | Path) -> Path:
    out = Path(out)
    write_json_atomic(out, bands)
    return out


def packaged_bands_path() -> Path:
    return Path(str(resources.files("dvfb") / "data" / PACKAGED))


@dataclass(frozen=True)
class Bands:
    bands: tuple[Band, ...]
    random: tuple[RandomBand, ...]
    source: str


def load_bands(path: str | Path | None = None) -> Bands:
    """The bands of ``path`` (default: the package's, :data:`PACKAGED`); a damaged file is an
    :class:`AnalysisError` naming it."""
    path = Path(path) if path is not None else packaged_bands_path()
    data = read_json_object(path)
    if data.get("format") != BANDS_FORMAT or not isinstance(data.get("bands"), list):
        raise AnalysisError(f"{path} is not a bands file of format {BANDS_FORMAT} (written by dvfb bands)")
    try:
        return Bands(tuple(Band(**b) for b in data["bands"]), tuple(RandomBand(**r) for r in data.get("random", [])),
                     str(path))
    except TypeError as exc:
        raise AnalysisError(f"{path}: a band is not of this dvfb's form ({exc})") from None


# ---------------------------------------------------------------------------------------------
# the verdict


@dataclass(frozen=True)
class Verdict:
    """Where a run's newest evaluation of a task stands."""

    task: str
    step: int
    value: float
    where: str  # "inside", "above", "below", "no band", "not finite"
    band: Band | None
    random: RandomBand | None
    warning: str | None  # words a user can act on, or None

    def line(self) -> str:
        """One line of ``dvfb status``."""
        value = f"{self.value:.1f}" if math.isfinite(self.value) else str(self.value)
        text = f"{self.task} {value} at {self.step:,} frames: "
        if self.band is not None:
            b = self.band
            text += (f"{self.where} the {b.method} band at {b.frames:,} frames ({b.min:.1f}-{b.max:.1f}, mean "
                     f"{b.mean:.1f}, {b.seeds} seeds, {b.preset} preset)")
        else:
            text += self.where
        return text + (f" -- {self.warning}" if self.warning else "")


def _nearest(bands: list[Band], step: int) -> Band | None:
    if not bands:
        return None
    band = min(bands, key=lambda b: (abs(b.frames - step), b.frames))
    return band if abs(band.frames - step) <= NEAREST * band.frames else None


def clear_of_random(band: Band, random: RandomBand) -> bool:
    """Whether every reference seed had left the random policy's returns clearly (:data:`CLEAR_OF_RANDOM`)."""
    return band.min - random.max >= CLEAR_OF_RANDOM * (random.max - random.min) and band.min > random.max


def verdicts(method: str, domain: str, preset: str, records: list[dict], bands: Bands) -> list[Verdict]:
    """One :class:`Verdict` per task of the run's newest evaluation (``records``: its eval.jsonl rows)."""
    if not records:
        return []
    step = max(r["step"] for r in records)
    newest = [r for r in records if r["step"] == step]
    out = []
    for record in newest:
        task, value = record["task"], float(record["return"])
        own = [b for b in bands.bands if (b.method, b.domain, b.preset, b.task) == (method, domain, preset, task)]
        random = next((r for r in bands.random if (r.domain, r.task) == (domain, task)), None)
        band = _nearest(own, step)
        if not math.isfinite(value):
            out.append(Verdict(task, step, value, "not finite", band, random,
                               "the evaluation's return is not a number: the networks have diverged; look at the "
                               "train records' losses (dvfb status shows the newest) and restart from an earlier "
                               "checkpoint with a lower learning rate"))
            continue
        if band is None:
            if not own:
                why = f"no band for {method} on {task} at the {preset} preset"
            else:
                covered = ", ".join(f"{b.frames:,}" for b in sorted(own, key=lambda b: b.frames))
                why = f"no band at {step:,} frames (the {method} bands are at {covered} frames)"
            out.append(Verdict(task, step, value, why, None, random, None))
            continue
        where = "inside" if band.min <= value <= band.max else ("above" if value > band.max else "below")
        warning = None
        if random is not None and clear_of_random(band, random) and value <= random.max:
            warning = (f"not learning: no better than the random policy's returns ({random.min:.1f}-{random.max:.1f}) "
                       f"where every reference run had left them by {band.frames:,} frames; check the run's "
                       "options against its preset (learning rates, losses switched off) and its train records")
        elif where == "below":
            warning = "below every reference seed: watch the next evaluations before trusting this run"
        out.append(Verdict(task, step, value, where, band, random, warning))
    return out


def summary(found: list[Verdict]) -> str:
    """One short text for a run's row in ``dvfb sweep status``: the flags first, else the counts."""
    if not found:
        return "-"
    step = found[0].step
    flagged = [v for v in found if v.where == "not finite" or (v.warning or "").startswith("not learning")]
    if flagged:
        kind = "not finite" if flagged[0].where == "not finite" else "not learning"
        return f"{kind} at {step:,}: {', '.join(v.task for v in flagged)}"
    counts: dict[str, int] = {}
    for v in found:
        key = v.where if v.band is not None else "no band"
        counts[key] = counts.get(key, 0) + 1
    return f"at {step:,}: " + ", ".join(f"{n} {key}" for key, n in counts.items())


def run_verdicts(run, bands: Bands | None = None) -> list[Verdict]:
    """The verdicts of a pre-training run (a :class:`~dvfb.runs.layout.PretrainRun`) against ``bands``
    (default: the package's)."""
    records = read_eval_records(run.path)
    if not records:
        return []
    config = run.config
    return verdicts(method_name(config), config.domain, config.preset, records, bands or load_bands())


def read_eval_records(run_path: str | Path) -> list[dict]:
    """The whole records of ``RUN/metrics/eval.jsonl`` (a torn last line passed over)."""
    path = Path(run_path) / "metrics" / "eval.jsonl"
    if not path.is_file():
        return []
    rows = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict) and isinstance(row.get("step"), int) and "task" in row and "return" in row:
            rows.append(row)
    return rows


def plot(run_name: str, method: str, domain: str, preset: str, records: list[dict], bands: Bands, out: Path) -> Path:
    """One panel per task: the run's evaluations while pre-training (return against frames) over its
    method's band (the seeds' min-max, and their mean) and the random policy's returns."""
    # here, not at the top: matplotlib takes ~0.35 s to import and only the plots need it
    from matplotlib.figure import Figure

    tasks = list(dict.fromkeys(r["task"] for r in records))
    if not tasks:
        raise AnalysisError(f"{run_name} has no evaluations while pre-training to draw (metrics/eval.jsonl; "
                            "--eval-every)")
    n = len(tasks)
    fig = Figure(figsize=(max(6.0, 4.2 * n), 3.8), dpi=100, layout="constrained")
    fig.suptitle(f"{run_name}: evaluations while pre-training over the {method} band ({preset} preset)", fontsize=10)
    for i, task in enumerate(tasks):
        ax = fig.add_subplot(1, n, i + 1)
        own = sorted((b for b in bands.bands if (b.method, b.domain, b.preset, b.task) == (method, domain, preset, task)),
                     key=lambda b: b.frames)
        if own:
            x = [b.frames for b in own]
            ax.fill_between(x, [b.min for b in own], [b.max for b in own], color="tab:blue", alpha=0.2, linewidth=0,
                            label=f"{method} reference ({own[0].seeds} seeds, min-max)")
            ax.plot(x, [b.mean for b in own], "--", color="tab:blue", linewidth=1, label="reference mean")
        random = next((r for r in bands.random if (r.domain, r.task) == (domain, task)), None)
        if random is not None:
            ax.axhspan(random.min, random.max, color="grey", alpha=0.15, linewidth=0, label="random policy")
        rows = [r for r in records if r["task"] == task]
        ax.plot([r["step"] for r in rows], [r["return"] for r in rows], "o-", color="tab:red", label="this run")
        ax.set_title(task, fontsize=9)
        ax.set_xlabel("pre-training frames")
        ax.set_ylabel("return")
        ax.grid(alpha=0.3)
        if i == 0:
            ax.legend(fontsize=7)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    return out
