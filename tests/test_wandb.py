"""Optional Weights & Biases logging (``--log.wandb``; docs/methods.md, "Logging to Weights & Biases").

The runs log offline, with no network: W&B's transaction log (``RUN/wandb/offline-run-*/run-ID.wandb``)
is read back here and compared with the TensorBoard events the same run wrote.
"""

import json
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from wandb.proto import wandb_internal_pb2

from dvfb.cli import main
from dvfb.runs import read_metrics
from dvfb.runs.run_config import load_finetune_run_config, load_run_config
from dvfb.runs.wandb_sink import LogConfig

TINY = ["--agent", "fb", "--domain", "point_mass_maze", "--seed-frames", "500", "--update-every", "4",
        "--log-every", "250", "--fb.z-dim", "8", "--fb.hidden-dim", "32", "--fb.feature-dim", "16",
        "--fb.backward-hidden-dim", "32", "--fb.batch-size", "32", "--torch-threads", "1", "--no-progress"]
WANDB = ["--log.wandb", "true", "--log.wandb-mode", "offline", "--log.wandb-group", "g1", "--log.wandb-tags", "a",
         "b"]
MAZE = "point_mass_maze_reach_top_left"
FINETUNE = ["--task", MAZE, "--inference.steps", "200", "--inference.random-action-steps", "100",
            "--inference.samples", "200", "--inference.eval-episodes", "1", "--finetune.frames", "1000",
            "--finetune.seed-frames", "250", "--finetune.update-every", "4", "--finetune.eval-every", "500",
            "--finetune.eval-episodes", "1", "--no-progress"]

# W&B's transaction log: LevelDB's log format (32 KiB blocks of records, each with a 7-byte header:
# CRC-32 of the type byte and the payload, length, type) after a 7-byte file header.
BLOCK, RECORD_HEADER = 32768, 7
FULL, FIRST, MIDDLE, LAST = 1, 2, 3, 4


def wandb_records(path: Path) -> list:
    data = path.read_bytes()
    assert data[:4] == b":W&B", f"{path} is not a W&B transaction log"
    pos, parts, records = 7, [], []
    while pos + RECORD_HEADER <= len(data):
        room = BLOCK - pos % BLOCK
        if room < RECORD_HEADER:  # the block's zero-filled trailer
            pos += room
            continue
        crc, length, kind = struct.unpack("<IHB", data[pos:pos + RECORD_HEADER])
        payload = data[pos + RECORD_HEADER:pos + RECORD_HEADER + length]
        pos += RECORD_HEADER + length
        if kind == 0:
            continue
        assert zlib.crc32(payload, zlib.crc32(bytes([kind]))) == crc, f"{path}: bad checksum at {pos}"
        assert kind in (FULL, FIRST, MIDDLE, LAST)
        parts = [payload] if kind in (FULL, FIRST) else [*parts, payload]
        if kind in (FULL, LAST):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(b"".join(parts))
            records.append(record)
    return records


def read_offline_run(directory: Path) -> dict:
    """What one offline W&B run holds: its id, name, group, tags, job type, config and history
    ({step: {key: value}})."""
    (path,) = directory.glob("run-*.wandb")
    out = {"config": {}, "history": {}}
    for record in wandb_records(path):
        kind = record.WhichOneof("record_type")
        if kind == "run":
            run = record.run
            out.update(id=run.run_id, name=run.display_name, project=run.project, group=run.run_group,
                       tags=list(run.tags), job_type=run.job_type)
            out["config"].update({item.key: json.loads(item.value_json) for item in run.config.update})
        elif kind == "config":
            out["config"].update({item.key: json.loads(item.value_json) for item in record.config.update})
        elif kind == "history":
            items = {item.key or "/".join(item.nested_key): json.loads(item.value_json) for item in record.history.item}
            step = items.pop("_step")
            row = out["history"].setdefault(step, {})
            row.update({k: v for k, v in items.items() if not k.startswith("_")})
    out["config"].pop("_wandb", None)
    assert path.name == f"run-{out['id']}.wandb"
    return out


def offline_runs(run: Path) -> list[dict]:
    return [read_offline_run(d) for d in sorted((run / "wandb").glob("offline-run-*"))]


def tensorboard_scalars(run: Path) -> dict:
    """{step: {tag: value}} of the run's TensorBoard events."""
    events = EventAccumulator(str(run / "tb"), size_guidance={"scalars": 0})
    events.Reload()
    out: dict = {}
    for tag in events.Tags()["scalars"]:
        for event in events.Scalars(tag):
            out.setdefault(event.step, {})[tag] = event.value
    return out


def assert_same_scalars(wandb_history: dict, tensorboard: dict) -> None:
    """W&B's rows equal TensorBoard's scalars: the same steps, tags and values (TensorBoard keeps float32)."""
    assert sorted(wandb_history) == sorted(tensorboard)
    for step, row in tensorboard.items():
        assert sorted(wandb_history[step]) == sorted(row), step
        for tag, value in row.items():
            assert np.float32(wandb_history[step][tag]) == np.float32(value), (step, tag)


@pytest.fixture
def no_network_wandb(tmp_path, monkeypatch):
    """W&B quiet, offline and with its own files in the test's directory (nothing under ~)."""
    monkeypatch.setenv("WANDB_SILENT", "true")
    for name in ("WANDB_API_KEY", "WANDB_MODE", "WANDB_BASE_URL", "WANDB_PROJECT", "WANDB_ENTITY", "WANDB_RUN_ID",
                 "WANDB_RUN_GROUP", "WANDB_TAGS", "WANDB_RESUME"):
        monkeypatch.delenv(name, raising=False)
    home = tmp_path / "wandb_home"
    for name in ("WANDB_CONFIG_DIR", "WANDB_CACHE_DIR", "WANDB_DATA_DIR", "WANDB_ARTIFACT_DIR"):
        monkeypatch.setenv(name, str(home / name.lower()))
    monkeypatch.setenv("NETRC", str(tmp_path / "no_netrc"))
    return home


@pytest.mark.slow
def test_wandb_gets_the_tensorboard_scalars_and_the_config_and_a_resume_continues_its_run(
        tmp_path, no_network_wandb):
    run = tmp_path / "maze_fb"
    assert main(["pretrain", *TINY, "--frames", "1000", "--run-dir", str(run), *WANDB]) == 0
    (first,) = offline_runs(run)
    assert first["id"] == (run / "wandb_id.txt").read_text().strip()
    assert (first["name"], first["project"], first["group"], first["tags"], first["job_type"]) == \
        ("maze_fb", "dvfb", "g1", ["a", "b"], "pretrain")
    # The run config, logged once as the W&B run's config.
    config = json.loads((run / "config.json").read_text())
    assert first["config"] == config and config["log"]["wandb"] is True
    assert_same_scalars(first["history"], tensorboard_scalars(run))
    assert {"train/fb_loss", "episode/episode_task_reward"} <= set(first["history"][1000])

    # W&B only observes: the run's numbers are those of the same run without it (fps aside).
    plain = tmp_path / "plain"
    assert main(["pretrain", *TINY, "--frames", "1000", "--run-dir", str(plain)]) == 0
    assert not (plain / "wandb").exists() and not (plain / "wandb_id.txt").exists()
    for prefix in ("train", "episode"):
        strip = [{k: v for k, v in r.items() if not k.startswith("fps")} for r in read_metrics(run, prefix)]
        assert strip == [{k: v for k, v in r.items() if not k.startswith("fps")} for r in read_metrics(plain, prefix)]

    # A resume continues the same W&B run (offline: a second offline-run directory with its id).
    assert main(["pretrain", *TINY, "--frames", "2000", "--run-dir", str(run), *WANDB, "--resume"]) == 0
    runs = offline_runs(run)
    assert len(runs) == 2 and runs[1]["id"] == first["id"] and runs[1]["name"] == "maze_fb"
    assert runs[0]["history"] == first["history"]
    assert runs[1]["config"]["frames"] == 2000 and min(runs[1]["history"]) > 1000
    assert_same_scalars({**runs[0]["history"], **runs[1]["history"]}, tensorboard_scalars(run))

    # Fine-tuning inherits the pre-training run's log section: a W&B run of its own.
    assert main(["finetune", str(run), *FINETUNE]) == 0
    tuned = run / "finetune" / MAZE
    (tuned_wandb,) = offline_runs(tuned)
    assert tuned_wandb["id"] == (tuned / "wandb_id.txt").read_text().strip() != first["id"]
    assert (tuned_wandb["name"], tuned_wandb["job_type"], tuned_wandb["group"]) == \
        (f"maze_fb/finetune/{MAZE}", "finetune", "g1")
    assert tuned_wandb["config"] == json.loads((tuned / "config.json").read_text())
    assert_same_scalars(tuned_wandb["history"], tensorboard_scalars(tuned))
    assert [step for step, row in sorted(tuned_wandb["history"].items()) if "eval/eval_return" in row] == \
        [0, 500, 1000]


def test_a_resume_may_turn_wandb_on_or_off(tmp_path, no_network_wandb):
    run = tmp_path / "maze_fb"
    assert main(["pretrain", *TINY, "--frames", "1000", "--run-dir", str(run)]) == 0
    assert not (run / "wandb").exists()
    assert main(["pretrain", *TINY, "--frames", "1500", "--run-dir", str(run), *WANDB, "--resume"]) == 0
    (resumed,) = offline_runs(run)
    assert sorted(resumed["history"]) == [1250, 1500]
    assert load_run_config(run / "config.json").log.wandb is True


def test_a_resume_refused_for_a_damaged_wandb_id_changes_no_file(tmp_path, no_network_wandb, capsys):
    run = tmp_path / "maze_fb"
    assert main(["pretrain", *TINY, "--frames", "1000", "--run-dir", str(run), *WANDB]) == 0
    (run / "wandb_id.txt").write_text("not an id!\n")
    capsys.readouterr()
    before = {str(p.relative_to(run)): p.read_bytes() if p.is_file() and p.name != ".lock" else None
              for p in sorted(run.rglob("*"))}
    assert main(["pretrain", *TINY, "--frames", "1500", "--run-dir", str(run), *WANDB, "--resume"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    # The memory estimate may come first; the refusal is one line, and nothing was resumed.
    assert "wandb_id.txt does not hold a W&B run id" in err[-1] and not any("resuming" in e for e in err), err
    assert err[-1].startswith("dvfb pretrain: error: ") and len(err) <= 2, err
    after = {str(p.relative_to(run)): p.read_bytes() if p.is_file() and p.name != ".lock" else None
             for p in sorted(run.rglob("*"))}
    assert after == before  # config.json still says 1,000 frames; the metrics keep their records
    assert load_run_config(run / "config.json").frames == 1000


def run_cli(args: list[str], env: dict, preamble: str = "") -> subprocess.CompletedProcess:
    code = f"import sys; {preamble}from dvfb.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env,
                          timeout=300)


def test_without_wandb_installed_the_flag_is_one_line_and_creates_nothing(tmp_path):
    run = tmp_path / "run"
    done = run_cli(["pretrain", *TINY, "--frames", "1000", "--run-dir", str(run), "--log.wandb", "true"],
                   {**os.environ, "WANDB_SILENT": "true"}, preamble="sys.modules['wandb'] = None; ")
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "pip install 'dvfb[wandb]'" in lines[0] and "--log.wandb" in lines[0]
    assert not run.exists()
    # Without the flag, a missing wandb is nothing to the run (it is never imported).
    done = run_cli(["pretrain", *TINY, "--frames", "600", "--run-dir", str(run)], dict(os.environ),
                   preamble="sys.modules['wandb'] = None; ")
    assert done.returncode == 0, done.stderr
    assert not (run / "wandb").exists() and not (run / "wandb_id.txt").exists()


def test_online_without_credentials_is_one_line_and_creates_nothing(tmp_path, no_network_wandb, capsys):
    run = tmp_path / "run"
    assert main(["pretrain", *TINY, "--frames", "1000", "--run-dir", str(run), "--log.wandb", "true",
                 "--log.wandb-mode", "online"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "credentials" in err[0] and "--log.wandb-mode offline" in err[0]
    assert not run.exists()
    assert main(["pretrain", *TINY, "--frames", "1000", "--run-dir", str(run), "--log.wandb-mode", "sometimes"]) == 2
    assert "--log.wandb-mode 'sometimes' is not one of auto, online, offline" in capsys.readouterr().err
    assert not run.exists()


def test_online_with_an_unreachable_server_is_one_line_and_creates_nothing(tmp_path, no_network_wandb, capsys,
                                                                           monkeypatch):
    import socket

    with socket.socket() as sock:  # a loopback port nothing listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    monkeypatch.setenv("WANDB_API_KEY", "0" * 40)
    monkeypatch.setenv("WANDB_BASE_URL", f"http://127.0.0.1:{port}")
    monkeypatch.setenv("WANDB_INIT_TIMEOUT", "20")  # bounds the wait where the check is missing
    run = tmp_path / "run"
    assert main(["pretrain", *TINY, "--frames", "1000", "--run-dir", str(run), "--log.wandb", "true",
                 "--log.wandb-mode", "online"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the W&B server 127.0.0.1 cannot be reached" in err[0], err
    assert not run.exists()  # it was left with config.json, meta.json, wandb_id.txt and wandb/


def test_configs_written_before_the_log_section_load_with_it_off():
    old = Path(__file__).parent / "fixtures" / "v0.1.0" / "dvfb_maze"  # written by dvfb 0.1.0
    tuned = old / "finetune" / MAZE / "config.json"
    assert "log" not in json.loads((old / "config.json").read_text()) and "log" not in json.loads(tuned.read_text())
    assert load_run_config(old / "config.json").log == LogConfig()
    assert load_finetune_run_config(tuned).log == LogConfig()
    assert LogConfig().wandb is False
