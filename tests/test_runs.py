"""Tests for dvfb.runs: run directories, metrics, atomic results and checkpoints."""

import dataclasses
import json

import pytest
import torch

from dvfb import __version__
from dvfb.core.config import param
from dvfb.core.errors import CheckpointError, ConfigError, RunDirError
from dvfb.runs import (
    MetricsLogger,
    RunDir,
    latest_checkpoint,
    list_snapshots,
    load_checkpoint,
    load_snapshot,
    read_metrics,
    save_checkpoint,
    save_snapshot,
    write_json_atomic,
)


@dataclasses.dataclass
class OptimConfig:
    lr: float = param(1e-4, "learning rate")
    betas: list[float] = param([0.9, 0.999], "Adam betas")


@dataclasses.dataclass
class ToyConfig:
    task: str = param("walker_run", "task name")
    seed: int = param(0, "seed")
    mode: str = param("dvfb", "agent", choices=("dvfb", "fb"))
    optim: OptimConfig = dataclasses.field(default_factory=OptimConfig,
                                           metadata={"help": "optimiser"})


def make_run(tmp_path, **kwargs):
    config = ToyConfig(seed=3, optim=OptimConfig(lr=3e-4))
    return RunDir.create(tmp_path / "run", config, **kwargs), config


def listing(directory):
    return sorted(p.name for p in directory.iterdir())


def contents(directory):
    """Every file's bytes, by name (temporary files included)."""
    return {p.name: p.read_bytes() for p in directory.iterdir()}


# ---------------------------------------------------------------------------------------------
# run directories


def test_create_writes_config_and_meta(tmp_path):
    run, config = make_run(tmp_path, command=["dvfb", "pretrain", "--seed", "3"])
    assert run.path == tmp_path / "run"
    assert listing(run.path) == ["config.json", "meta.json"]
    assert run.load_config(ToyConfig) == config
    assert RunDir.open(run.path).load_config(ToyConfig) == config
    meta = run.read_meta()
    assert meta["config_class"] == "ToyConfig"
    assert meta["dvfb_version"] == __version__
    assert meta["command"] == ["dvfb", "pretrain", "--seed", "3"]
    assert "created" in meta
    # The machine and the versions that decide the numbers.
    import mujoco
    import numpy

    machine = meta["machine"]
    assert machine["versions"]["torch"] in (torch.__version__, torch.__version__.split("+")[0])
    assert machine["versions"]["numpy"] == numpy.__version__ and machine["versions"]["mujoco"] == mujoco.__version__
    assert machine["versions"]["dm_control"]
    assert machine["cpu"]["torch_capability"] == torch.backends.cpu.get_cpu_capability()
    assert ("avx2" in machine["cpu"]["vector_extensions"]) == (torch.backends.cpu.get_cpu_capability() != "DEFAULT")
    assert machine["gpus"] == [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]


def test_create_refuses_existing_non_empty_directory(tmp_path):
    run, _ = make_run(tmp_path)
    (run.path / "notes.txt").write_text("keep me")
    before = {p.name: p.read_bytes() for p in run.path.iterdir()}
    with pytest.raises(RunDirError) as info:
        RunDir.create(run.path, ToyConfig(seed=99))
    message = str(info.value)
    assert str(run.path) in message and "--overwrite" in message and "another" in message
    assert {p.name: p.read_bytes() for p in run.path.iterdir()} == before


def test_create_accepts_empty_existing_directory(tmp_path):
    (tmp_path / "run").mkdir()
    run, config = make_run(tmp_path)
    assert run.load_config(ToyConfig) == config


def test_explicit_overwrite_replaces_old_contents(tmp_path):
    run, _ = make_run(tmp_path)
    save_checkpoint(run, {"x": torch.zeros(1)}, "step_1")
    new = RunDir.create(run.path, ToyConfig(seed=99), overwrite=True)
    assert listing(new.path) == ["config.json", "meta.json"]
    assert new.load_config(ToyConfig).seed == 99


def test_overwrite_refuses_a_directory_that_is_not_a_run(tmp_path):
    other = tmp_path / "documents"
    other.mkdir()
    (other / "thesis.tex").write_text("precious")
    with pytest.raises(RunDirError, match="does not look like a dvfb run"):
        RunDir.create(other, ToyConfig(), overwrite=True)
    assert (other / "thesis.tex").read_text() == "precious"


def test_open_errors(tmp_path):
    with pytest.raises(RunDirError, match="does not exist"):
        RunDir.open(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RunDirError, match="no config.json"):
        RunDir.open(tmp_path / "empty")
    run, _ = make_run(tmp_path)
    run.config_path.write_text('{"task": "walker_run", "se')
    with pytest.raises(RunDirError, match="corrupt") as info:
        RunDir.open(run.path)
    assert str(run.config_path) in str(info.value)


def test_load_config_is_strict(tmp_path):
    run, _ = make_run(tmp_path)
    data = json.loads(run.config_path.read_text())
    data["unknown_option"] = 1
    run.config_path.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match="unknown_option") as info:
        run.load_config(ToyConfig)
    assert str(run.config_path) in str(info.value)


# ---------------------------------------------------------------------------------------------
# metrics and results


def test_metrics_jsonl_and_tensorboard(tmp_path):
    run, _ = make_run(tmp_path)
    with MetricsLogger(run) as logger:
        logger.log(10, {"loss": 1.5, "q": torch.tensor(2.25)})
        logger.log(20, {"loss": 0.5, "q": torch.tensor(1.0)})
        logger.log(20, {"return": 300.0}, prefix="eval")
    assert read_metrics(run, "train") == [{"step": 10, "loss": 1.5, "q": 2.25},
                                          {"step": 20, "loss": 0.5, "q": 1.0}]
    assert read_metrics(run.path, "eval") == [{"step": 20, "return": 300.0}]
    assert read_metrics(run, "missing") == []
    assert len((run.metrics_dir / "train.jsonl").read_text().splitlines()) == 2
    events = list(run.tb_dir.glob("events.out.tfevents.*"))
    assert events and all(e.stat().st_size > 0 for e in events)


@pytest.mark.parametrize("tail", ['{"step": 5, "x": 5.', '{"step": 5, "x": 5.\n', '\0\0\0\n'])
def test_the_last_record_for_a_status_passes_over_a_torn_line(tmp_path, tail):
    from dvfb.runs import last_metric_record

    run, _ = make_run(tmp_path)
    assert last_metric_record(run) is None
    with MetricsLogger(run, tensorboard=False) as logger:
        for step in (250, 500, 1000):
            logger.log(step, {"fps": 50.0})
    with open(run.metrics_dir / "train.jsonl", "a") as file:
        file.write(tail)
    assert last_metric_record(run) == {"step": 1000, "fps": 50.0}


def test_metrics_append_across_resume(tmp_path):
    run, _ = make_run(tmp_path)
    with MetricsLogger(run, tensorboard=False) as logger:
        for step in (1, 2, 3, 4):
            logger.log(step, {"x": float(step)})
    # Simulate a crash mid-line, then resume from a checkpoint taken at step 3.
    with open(run.metrics_dir / "train.jsonl", "a") as file:
        file.write('{"step": 5, "x": 5.')
    assert [r["step"] for r in read_metrics(run)] == [1, 2, 3, 4]  # torn line skipped
    with MetricsLogger(run, tensorboard=False, purge_step=3) as logger:
        logger.log(3, {"x": 30.0})
        logger.log(4, {"x": 40.0})
    assert read_metrics(run) == [{"step": 1, "x": 1.0}, {"step": 2, "x": 2.0},
                                 {"step": 3, "x": 30.0}, {"step": 4, "x": 40.0}]
    # Without purge_step, a reopened logger just appends.
    with MetricsLogger(run, tensorboard=False) as logger:
        logger.log(5, {"x": 50.0})
    assert [r["step"] for r in read_metrics(run)] == [1, 2, 3, 4, 5]


def test_metrics_reject_bad_values(tmp_path):
    run, _ = make_run(tmp_path)
    with MetricsLogger(run, tensorboard=False) as logger:
        with pytest.raises(TypeError, match="'v'"):
            logger.log(1, {"v": torch.ones(3)})
        with pytest.raises(ValueError, match="reserved"):
            logger.log(1, {"step": 1.0})
    (run.metrics_dir / "train.jsonl").write_text('{"step": 1}\nnot json\n{"step": 2}\n')
    with pytest.raises(RunDirError, match="train.jsonl:2"):
        read_metrics(run)


def test_write_json_atomic(tmp_path):
    path = tmp_path / "results" / "eval.json"
    write_json_atomic(path, {"return": torch.tensor(1.5), "returns": torch.tensor([1.0, 2.0])})
    assert json.loads(path.read_text()) == {"return": 1.5, "returns": [1.0, 2.0]}
    with pytest.raises(TypeError):
        write_json_atomic(path, {"bad": object()})
    assert json.loads(path.read_text())["return"] == 1.5
    assert listing(path.parent) == ["eval.json"]


# ---------------------------------------------------------------------------------------------
# checkpoints


class ExplodingPickle:
    """Pickling this raises, as a process dying in the middle of torch.save would stop it."""

    def __reduce__(self):
        raise RuntimeError("simulated crash while writing")


def test_latest_pointer_semantics(tmp_path):
    run, _ = make_run(tmp_path)
    assert latest_checkpoint(run) is None
    save_checkpoint(run, {"step": 1, "w": torch.ones(2)}, "step_1")
    assert (run.checkpoints_dir / "latest").read_text().strip() == "step_1.pt"
    assert load_checkpoint(run)["step"] == 1
    save_checkpoint(run, {"step": 2}, "step_2")
    # The previous resume checkpoint is deleted once the pointer has moved.
    assert listing(run.checkpoints_dir) == ["latest", "step_2.pt"]
    assert latest_checkpoint(run) == run.checkpoints_dir / "step_2.pt"
    save_checkpoint(run, {"step": 3}, "step_3", keep_previous=True)
    assert listing(run.checkpoints_dir) == ["latest", "step_2.pt", "step_3.pt"]
    assert load_checkpoint(run)["step"] == 3
    assert load_checkpoint(run, "step_2")["step"] == 2
    # Re-saving under the pointer's own name replaces it in place.
    save_checkpoint(run, {"step": 4}, "step_3")
    assert listing(run.checkpoints_dir) == ["latest", "step_2.pt", "step_3.pt"]
    assert load_checkpoint(run.path)["step"] == 4


def test_interrupted_checkpoint_keeps_previous_intact(tmp_path):
    run, _ = make_run(tmp_path)
    good = {"step": 1, "weights": torch.arange(1000.0)}
    save_checkpoint(run, good, "step_1")
    before = contents(run.checkpoints_dir)
    # A large tensor is written first, so the failure happens part-way through the file.
    bad = {"weights": torch.randn(100_000), "broken": ExplodingPickle()}
    for name in ("step_2", "step_1"):
        with pytest.raises(RuntimeError, match="simulated crash"):
            save_checkpoint(run, bad, name)
        assert contents(run.checkpoints_dir) == before  # no temp files either
    assert torch.equal(load_checkpoint(run)["weights"], good["weights"])
    with pytest.raises(RuntimeError, match="simulated crash"):
        save_snapshot(run, bad, "final")
    assert listing(run.snapshots_dir) == []


def test_disk_full_mid_write_keeps_previous_intact(tmp_path, monkeypatch):
    run, _ = make_run(tmp_path)
    save_checkpoint(run, {"step": 1}, "step_1")
    before = contents(run.checkpoints_dir)
    seen_temp = []

    def half_written_save(obj, file):
        file.write(b"x" * 4096)
        file.flush()
        seen_temp.extend(n for n in listing(run.checkpoints_dir) if ".tmp-" in n)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", half_written_save)
    with pytest.raises(CheckpointError, match="No space left") as info:
        save_checkpoint(run, {"step": 2}, "step_2")
    assert "step_2.pt" in str(info.value)
    assert seen_temp, "the write should go through a temporary file"
    assert contents(run.checkpoints_dir) == before


def test_stale_temp_files_are_cleaned(tmp_path):
    run, _ = make_run(tmp_path)
    run.checkpoints_dir.mkdir()
    (run.checkpoints_dir / ".step_1.pt.tmp-deadbeef").write_bytes(b"half a checkpoint")
    save_checkpoint(run, {"step": 1}, "step_1")
    assert listing(run.checkpoints_dir) == ["latest", "step_1.pt"]


def test_missing_and_corrupt_checkpoints(tmp_path):
    run, _ = make_run(tmp_path)
    with pytest.raises(CheckpointError, match="latest does not exist"):
        load_checkpoint(run)
    with pytest.raises(CheckpointError, match="step_9.pt does not exist"):
        load_checkpoint(run, "step_9")
    path = save_checkpoint(run, {"w": torch.randn(10_000)}, "step_1")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="truncated or corrupt") as info:
        load_checkpoint(run)
    assert str(path) in str(info.value)
    path.write_bytes(b"this is not a checkpoint")
    with pytest.raises(CheckpointError, match="step_1.pt"):
        load_checkpoint(run)
    (run.checkpoints_dir / "latest").write_text("../../etc/passwd\n")
    with pytest.raises(CheckpointError, match="pointer .* is corrupt"):
        load_checkpoint(run)
    (run.checkpoints_dir / "latest").write_text("gone.pt\n")
    with pytest.raises(CheckpointError, match="gone.pt does not exist"):
        load_checkpoint(run)


def test_weights_only_refusal_is_explained(tmp_path):
    run, _ = make_run(tmp_path)
    save_checkpoint(run, {"config": ToyConfig()}, "step_1")
    with pytest.raises(CheckpointError, match="other than tensors"):
        load_checkpoint(run)
    assert load_checkpoint(run, weights_only=False)["config"] == ToyConfig()


def test_snapshots_are_retained(tmp_path):
    run, _ = make_run(tmp_path)
    save_checkpoint(run, {"step": 1}, "step_1")
    save_snapshot(run, {"step": 1, "model": torch.ones(3)}, "step_1")
    assert latest_checkpoint(run).name == "step_1.pt"  # the snapshot did not move latest
    for step in (2, 3, 4):
        save_checkpoint(run, {"step": step}, f"step_{step}")
    save_snapshot(run, {"step": 4}, "final")
    assert list_snapshots(run) == ["final", "step_1"]
    assert listing(run.checkpoints_dir) == ["latest", "step_4.pt"]
    assert torch.equal(load_snapshot(run, "step_1")["model"], torch.ones(3))
    with pytest.raises(CheckpointError, match="does not exist"):
        load_snapshot(run, "step_2")


def test_checkpoint_names_are_checked(tmp_path):
    run, _ = make_run(tmp_path)
    for bad in ("../escape", "", ".hidden", "a/b"):
        with pytest.raises(ValueError):
            save_checkpoint(run, {}, bad)
