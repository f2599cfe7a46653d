"""Exported models (docs/sharing.md): `dvfb export` / `save_pretrained` write safetensors, config.json
and a model card; `dvfb.load(DIR)` reads them back, with no pickle and no run directory, into the
model the run itself gives. The run is conftest's fb_maze_physics_run, which the tests only read."""

from __future__ import annotations

import json
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

import dvfb
from dvfb.cli import main
from tiny import fb_physics_args

MAZE_TASK = "point_mass_maze_reach_top_left"


def _samples(seed: int = 0):
    rng = np.random.default_rng(seed)
    return (rng.standard_normal((64, 4)).astype(np.float32), rng.standard_normal((64, 4)).astype(np.float32),
            rng.random(64).astype(np.float32))


def test_an_exported_model_copied_elsewhere_acts_and_infers_as_the_run(fb_maze_physics_run, tmp_path, monkeypatch,
                                                                      capsys):
    out = tmp_path / "export"
    assert main(["export", str(fb_maze_physics_run), "--out", str(out), "--with-inference-data"]) == 0
    assert "fb on point_mass_maze, 2000 frames, seed 0" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["README.md", "config.json", "inference_data.npz",
                                                     "model.safetensors"]
    copy = tmp_path / "elsewhere" / "model"
    shutil.copytree(out, copy)

    original = dvfb.load(fb_maze_physics_run)

    def no_pickle(*args, **kwargs):
        raise AssertionError("an exported model was read with pickle")

    monkeypatch.setattr(torch, "load", no_pickle)
    monkeypatch.setattr(pickle, "load", no_pickle)
    monkeypatch.setattr(pickle, "loads", no_pickle)
    exported = dvfb.load(copy)
    monkeypatch.undo()

    obs, next_obs, rewards = _samples()
    z_run, z_export = original.infer_z(obs, next_obs, rewards), exported.infer_z(obs, next_obs, rewards)
    assert torch.equal(z_run, z_export)
    for row in obs[:8]:
        assert np.array_equal(original.act(row, z_run), exported.act(row, z_export))
    goal = [0.2, -0.1, 0.0, 0.0]
    assert torch.equal(original.infer_z(goal=goal), exported.infer_z(goal=goal))
    # The inference data hold the whole (small) replay in its order: a reward function's skill is
    # the one the run infers from its own replay (to rounding: the replay's rows are strided views,
    # the exported arrays contiguous, and the products sum them in another order).
    reward_fn = lambda states: states[:, 0] - states[:, 1]  # noqa: E731 (towards the bottom right)
    torch.testing.assert_close(original.infer_z(reward_fn=reward_fn), exported.infer_z(reward_fn=reward_fn),
                               rtol=1e-5, atol=1e-6)
    data = np.load(copy / "inference_data.npz")
    assert data["obs"].shape == data["next_obs"].shape == (2000, 4) and data["physics"].shape[0] == 2000
    # The physics of each next observation too: a task's reward is recomputed from them.
    assert data["next_physics"].shape == data["physics"].shape
    within_episodes = np.all(data["obs"][1:] == data["next_obs"][:-1], axis=1)  # row i + 1 follows row i
    assert within_episodes.sum() >= 1990
    assert np.array_equal(data["next_physics"][:-1][within_episodes], data["physics"][1:][within_episodes])
    # The snapshot's data statistics travel with the weights (online task inference reads Cov(B)).
    assert torch.equal(original.model.statistics["cov_backward"], exported.model.statistics["cov_backward"])


def test_the_model_card_carries_the_metadata_and_the_results(fb_maze_physics_run, tmp_path):
    out = dvfb.load(fb_maze_physics_run).save_pretrained(tmp_path / "card")
    text = (out / "README.md").read_text()
    assert text.startswith("---\n")
    meta = yaml.safe_load(text.split("---\n")[1])
    assert meta["library_name"] == "dvfb" and "fb" in meta["tags"] and "point_mass_maze" in meta["tags"]
    result = json_result(fb_maze_physics_run)
    (entry,) = meta["model-index"][0]["results"]
    # The hub's results format: task, dataset and metrics; the budget in the metric's args.
    assert entry["task"]["type"] == "reinforcement-learning"
    assert entry["dataset"] == {"type": f"dvfb/{MAZE_TASK}", "name": MAZE_TASK}
    (metric,) = entry["metrics"]
    assert metric["type"] == "mean_reward" and metric["value"] == pytest.approx(result, abs=0.005)
    assert metric["args"] == {"eval_episodes": 1, "labelled_steps": 10_000, "skill_source": "rewards"}
    assert metric["verified"] is False
    # Beside the number in the card's table, its budget.
    row = next(line for line in text.splitlines() if line.startswith(f"| {MAZE_TASK} |"))
    assert f"{result:.1f} ± " in row and "1 episodes, 10,000 reward-labelled steps" in row
    assert "dvfb pretrain --agent fb --domain point_mass_maze --frames 2000" in text
    assert "not comparable with the paper's tables" in text  # 2,000 frames at the small preset
    info = yaml.safe_load((out / "config.json").read_text())  # JSON is YAML
    assert (info["agent"], info["domain"], info["frames"], info["seed"]) == ("fb", "point_mass_maze", 2000, 0)
    assert info["observation_space"]["shape"] == [4] and info["action_space"]["shape"] == [2]
    assert info["inference_data"] is None and not (out / "inference_data.npz").exists()


def json_result(run: Path) -> float:
    import json

    return json.loads((run / "zeroshot" / f"{MAZE_TASK}.json").read_text())["mean_return"]


def test_an_export_is_not_a_run_and_a_report_passes_over_it(fb_maze_physics_run, tmp_path, capsys):
    out = tmp_path / "runs" / "export"
    dvfb.load(fb_maze_physics_run).save_pretrained(out)
    shutil.copytree(fb_maze_physics_run, tmp_path / "runs" / "fb", ignore=shutil.ignore_patterns("checkpoints"))
    assert main(["report", str(tmp_path / "runs"), "--out", str(tmp_path / "report")]) == 0
    capsys.readouterr()
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert main(["pretrain", "--agent", "fb", "--domain", "point_mass_maze", "--frames", "600", "--seed-frames", "500",
                 "--run-dir", str(out), "--overwrite"]) == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_bad_exports_are_one_line_and_change_nothing(fb_maze_physics_run, tmp_path, capsys):
    def fails(argv, message):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (argv, err)

    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "notes.txt").write_text("keep")
    fails(["export", str(fb_maze_physics_run), "--out", str(taken)], "is not empty; pass --overwrite")
    fails(["export", str(fb_maze_physics_run), "--out", str(taken), "--overwrite"],
          "holds something else than an exported model")
    assert [p.name for p in taken.iterdir()] == ["notes.txt"]
    fails(["export", str(fb_maze_physics_run), "--out", str(taken / "notes.txt")], "is a file")
    fails(["export", str(fb_maze_physics_run), "--out", str(tmp_path / "new"), "--snapshot", "7"],
          "has no snapshot at 7 frames")
    fails(["export", str(tmp_path / "nope"), "--out", str(tmp_path / "new")], "does not exist")
    bare = tmp_path / "bare"
    shutil.copytree(fb_maze_physics_run, bare, ignore=shutil.ignore_patterns("checkpoints"))
    fails(["export", str(bare), "--out", str(tmp_path / "new"), "--with-inference-data"], "no pre-training replay")
    fails(["push", str(fb_maze_physics_run), "--repo", "org/name"], "is not an exported model")
    assert not (tmp_path / "new").exists()
    first = tmp_path / "first"
    assert main(["export", str(fb_maze_physics_run), "--out", str(first)]) == 0
    capsys.readouterr()
    before = {p.name: p.read_bytes() for p in first.iterdir()}
    fails(["export", str(fb_maze_physics_run), "--out", str(first)], "pass --overwrite")
    assert {p.name: p.read_bytes() for p in first.iterdir()} == before
    assert main(["export", str(fb_maze_physics_run), "--out", str(first), "--overwrite"]) == 0


def test_push_without_the_hub_extra_says_how_to_install_it(fb_maze_physics_run, tmp_path):
    out = dvfb.load(fb_maze_physics_run).save_pretrained(tmp_path / "export")
    done = subprocess.run([sys.executable, "-c", "import sys; sys.modules['huggingface_hub'] = None; "
                           "from dvfb.cli import main; sys.exit(main(sys.argv[1:]))", "push", str(out), "--repo",
                           "org/name"], capture_output=True, text=True)
    assert done.returncode == 2
    assert done.stderr.strip() == ("dvfb push: error: dvfb push needs the optional hub extra: pip install 'dvfb[hub]' "
                                   "(huggingface_hub)")


def test_a_read_only_disk_is_one_line_and_leaves_nothing(fb_maze_physics_run, small_disk, capsys):
    subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], check=True)
    assert main(["export", str(fb_maze_physics_run), "--out", str(small_disk / "model")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Read-only file system" in err[0], err
    assert list(small_disk.iterdir()) == []


def _fill(disk: Path, leave: int) -> None:
    """A real file taking all but about ``leave`` bytes of the disk's free space."""
    import os

    stats = os.statvfs(disk)
    with open(disk / "filler", "wb") as file:
        file.write(b"\0" * max(0, stats.f_bavail * stats.f_frsize - leave))


def test_a_full_disk_is_one_line_and_keeps_the_export_it_would_replace(fb_maze_physics_run, small_disk, capsys):
    def fails(argv):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "No space left on device" in err[0] and "Traceback" not in err[0], err

    first = small_disk / "model"
    assert main(["export", str(fb_maze_physics_run), "--out", str(first)]) == 0
    capsys.readouterr()
    before = {p.name: p.read_bytes() for p in first.iterdir()}
    _fill(small_disk, 16 * 1024)  # room for the probe and the card, not for the weights
    # safetensors' own write error
    fails(["export", str(fb_maze_physics_run), "--out", str(small_disk / "new" / "model")])
    assert sorted(p.name for p in small_disk.iterdir()) == ["filler", "model"]  # the parents it made are gone
    fails(["export", str(fb_maze_physics_run), "--out", str(first), "--overwrite", "--with-inference-data"])
    assert {p.name: p.read_bytes() for p in first.iterdir()} == before  # the model it would replace, intact
    assert dvfb.load(first).snapshot == 2000


def _damaged(out: Path, tmp_path: Path, name: str, damage) -> Path:
    copy = tmp_path / name
    shutil.copytree(out, copy)
    damage(copy)
    return copy


def _edit_config(change):
    def damage(path: Path) -> None:
        import json

        info = json.loads((path / "config.json").read_text())
        change(info)
        (path / "config.json").write_text(json.dumps(info))
    return damage


def test_a_damaged_export_is_a_dvfb_error_naming_the_file(fb_maze_physics_run, tmp_path):
    from dvfb.core.errors import DvfbError

    out = tmp_path / "export"
    assert main(["export", str(fb_maze_physics_run), "--out", str(out), "--with-inference-data"]) == 0
    size = (out / "inference_data.npz").stat().st_size
    cases = [
        ("no_space", _edit_config(lambda info: info.pop("observation_space")), "config.json", "observation_space"),
        ("bad_shape", _edit_config(lambda info: info.update(action_space={"shape": []})), "config.json",
         "action_space"),
        ("no_frames", _edit_config(lambda info: info.pop("frames")), "config.json", "'frames'"),
        ("no_agent", _edit_config(lambda info: info["run_config"].update(agent="nope")), "config.json",
         "unknown agent 'nope'"),
        ("other_width", _edit_config(lambda info: info["run_config"]["fb"].update(hidden_dim=64)),
         "model.safetensors", "does not fit 'fb''s networks"),
        ("truncated", lambda p: os.truncate(p / "inference_data.npz", size // 2), "inference_data.npz",
         "cannot be read"),
        ("no_obs", lambda p: np.savez(p / "inference_data.npz", next_obs=np.zeros((3, 4), np.float32)),
         "inference_data.npz", "'obs' is missing"),
        ("narrow", lambda p: np.savez(p / "inference_data.npz", obs=np.zeros((3, 2), np.float32),
                                      next_obs=np.zeros((3, 2), np.float32)), "inference_data.npz", "(N, 4)"),
    ]
    for name, damage, file, message in cases:
        copy = _damaged(out, tmp_path, name, damage)
        with pytest.raises(DvfbError) as failure:
            dvfb.load(copy)
        text = str(failure.value)
        assert str(copy / file) in text and message in text and "\n" not in text, (name, text)


class _Hub:
    """A stand-in hub on a loopback port that answers every request 401 and counts them."""

    def __init__(self):
        import http.server
        import threading

        hub = self
        self.requests = 0

        class Handler(http.server.BaseHTTPRequestHandler):
            def _answer(self):
                hub.requests += 1
                body = b'{"error": "Invalid credentials in Authorization header"}'
                self.send_response(401)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            do_GET = do_POST = do_PUT = do_HEAD = _answer

            def log_message(self, *args):
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


def _closed_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_push_refuses_without_credentials_before_the_network_and_network_errors_are_one_line(fb_maze_physics_run,
                                                                                             tmp_path):
    out = dvfb.load(fb_maze_physics_run).save_pretrained(tmp_path / "export")
    hub = _Hub()
    base = {k: v for k, v in os.environ.items() if not k.startswith(("HF_", "HUGGING_FACE"))}
    base.update(HF_HOME=str(tmp_path / "hf_home"), HF_HUB_DISABLE_TELEMETRY="1")

    def push(env, repo="org/name"):
        done = subprocess.run([sys.executable, "-m", "dvfb", "push", str(out), "--repo", repo], capture_output=True,
                              text=True, env=env, timeout=120)
        assert done.returncode == 2, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("dvfb push: error: "), done.stderr
        return lines[0]

    try:
        assert "needs Hugging Face credentials" in push({**base, "HF_ENDPOINT": hub.url})
        assert "--repo 'a b' is not a hub repository name" in push({**base, "HF_TOKEN": "hf_x", "HF_ENDPOINT": hub.url},
                                                                  "a b")
        assert hub.requests == 0  # refused before the first request
        line = push({**base, "HF_TOKEN": "hf_x", "HF_ENDPOINT": hub.url})
        assert hub.requests > 0 and f"cannot push {out} to org/name:" in line and "401" in line, line
        line = push({**base, "HF_TOKEN": "hf_x", "HF_ENDPOINT": f"http://127.0.0.1:{_closed_port()}"})
        assert f"cannot push {out} to org/name:" in line, line
    finally:
        hub.close()
    # The token file (`hf auth login`) counts as credentials: the push goes on to the network.
    (tmp_path / "hf_home").mkdir()
    (tmp_path / "hf_home" / "token").write_text("hf_x")
    line = push({**base, "HF_ENDPOINT": f"http://127.0.0.1:{_closed_port()}"})
    assert f"cannot push {out} to org/name:" in line, line


FAST = ["--inference.steps", "300", "--inference.random-action-steps", "100", "--inference.eval-episodes", "1"]


def _files(directory: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir())}


def test_an_exported_model_is_evaluated_from_the_command_line_beside_it(fb_maze_physics_run, tmp_path, capsys):
    """`dvfb zeroshot EXPORT` from fresh steps, from its inference data (a reward function, or the
    task's rewards relabelled from their physics), and by online inference, then `dvfb video EXPORT`:
    the results go to EXPORT.eval, a run directory made from it; the export is only read."""
    export = tmp_path / "shared" / "fb_maze"
    assert main(["export", str(fb_maze_physics_run), "--out", str(export), "--with-inference-data"]) == 0
    before = _files(export)
    evaluation = tmp_path / "shared" / "fb_maze.eval"

    assert main(["zeroshot", str(export), "--task", MAZE_TASK, *FAST]) == 0
    out = capsys.readouterr()
    assert f"results: {evaluation / 'zeroshot'}" in out.out and "exported model" in out.err
    fresh = json.loads((evaluation / "zeroshot" / f"{MAZE_TASK}.json").read_text())
    assert fresh["skill_source"] == "rewards" and fresh["eval_episodes"] == 1
    made = json.loads((evaluation / "exported_from.json").read_text())
    assert made["export"] == str(export.resolve()) and made["frames"] == 2000

    # A reward function on the inference data gives the skill the run gives from its own replay.
    reward_file = tmp_path / "reward.py"
    reward_file.write_text("def reward(next_obs):\n    return next_obs[:, 0] - next_obs[:, 1]\n")
    own = tmp_path / "own"
    shutil.copytree(fb_maze_physics_run, own)
    source = ["--skill-source", "reward_fn", "--reward-fn", f"{reward_file}:reward", "--overwrite", *FAST]
    assert main(["zeroshot", str(own), "--task", MAZE_TASK, *source]) == 0
    assert main(["zeroshot", str(export), "--task", MAZE_TASK, *source]) == 0
    from_data = json.loads((evaluation / "zeroshot" / f"{MAZE_TASK}.json").read_text())
    assert "the exported model's inference data (2000 transitions)" in from_data["inference_info"]["states"]
    np.testing.assert_allclose(from_data["z"], json_result_z(own), rtol=1e-5, atol=1e-6)

    assert main(["zeroshot", str(export), "--task", MAZE_TASK, "--skill-source", "dataset", "--overwrite", *FAST]) == 0
    relabelled = json.loads((evaluation / "zeroshot" / f"{MAZE_TASK}.json").read_text())
    assert relabelled["inference_info"]["states"].endswith(f"rewards of {MAZE_TASK} relabelled from physics")

    online = ["--protocol", "online_inference", "--online-inference.frames", "200", "--online-inference.eval-every",
              "200", "--online-inference.eval-episodes", "1"]
    assert main(["zeroshot", str(export), "--task", MAZE_TASK, *online]) == 0
    assert (evaluation / "finetune" / f"{MAZE_TASK}.online_inference" / "curve.json").is_file()
    capsys.readouterr()

    # Rendered with the skill of the zero-shot result above, with progress lines off a terminal.
    environment = {**os.environ, "MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa", "DVFB_PROGRESS_SECONDS": "0"}
    done = subprocess.run([sys.executable, "-m", "dvfb", "video", str(export), "--task", MAZE_TASK, "--max-steps",
                           "20", "--frame-skip", "5", "--height", "48", "--width", "64"], capture_output=True,
                          text=True, env=environment)
    assert done.returncode == 0, done.stderr
    assert (evaluation / "analysis" / f"video_{MAZE_TASK}.gif").is_file() and "z from" in done.stdout
    progress = [line for line in done.stderr.splitlines() if line.startswith(f"[video {MAZE_TASK}] ")]
    assert progress and progress[-1].startswith(f"[video {MAZE_TASK}] 20/20 steps (100%)")
    assert _files(export) == before  # the export's own files: never written

    # dvfb status says what the evaluation directory is, not "pre-training: not started, 0/2000 frames".
    capsys.readouterr()
    assert main(["status", str(evaluation)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert f"made from the exported model {export.resolve()}" in lines[0]
    assert lines[1] == ("  pre-training: none here; the evaluation directory of that exported model (dvfb zeroshot and "
                        "dvfb video write its results here), holding its snapshot after 2000 frames")
    assert not any("not started" in line for line in lines)


def json_result_z(run: Path) -> list[float]:
    return json.loads((run / "zeroshot" / f"{MAZE_TASK}.json").read_text())["z"]


def test_an_evaluation_directory_is_checked_and_a_failed_first_one_is_removed(fb_maze_physics_run, tmp_path, capsys):
    def fails(argv, message):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert message in err[-1], (argv, err)

    export = tmp_path / "export"
    dvfb.load(fb_maze_physics_run).save_pretrained(export)
    capsys.readouterr()
    before = {p.name: p.read_bytes() for p in fb_maze_physics_run.iterdir() if p.is_file()}
    fails(["zeroshot", str(export), "--task", MAZE_TASK, "--eval-dir", str(fb_maze_physics_run)],
          "was trained, not made from an exported")
    assert {p.name: p.read_bytes() for p in fb_maze_physics_run.iterdir() if p.is_file()} == before
    fails(["zeroshot", str(export), "--task", "walker_walk", *FAST], "belongs to domain 'walker'")
    assert not (tmp_path / "export.eval").exists()  # made for the command, removed with its failure
    # Exported without inference data: nothing to relabel.
    fails(["zeroshot", str(export), "--task", MAZE_TASK, "--skill-source", "dataset", *FAST],
          "--skill-source dataset needs --dataset DIR")
    fails(["zeroshot", str(fb_maze_physics_run), "--task", MAZE_TASK, "--eval-dir", str(tmp_path / "x")],
          "is not an exported model")
    other = tmp_path / "other"
    shutil.copytree(export, other)
    assert main(["zeroshot", str(export), "--task", MAZE_TASK, *FAST]) == 0
    # Other weights in the same evaluation directory: refused.
    from safetensors.torch import load_file, save_file

    weights = load_file(str(other / "model.safetensors"))
    name = next(iter(weights))
    weights[name] = weights[name] + 1
    save_file(weights, str(other / "model.safetensors"))
    fails(["zeroshot", str(other), "--task", MAZE_TASK, "--eval-dir", str(tmp_path / "export.eval"), *FAST],
          "holds the evaluation of another exported model")


def test_the_card_lists_every_command_that_made_the_run(fb_maze_physics_run, tmp_path):
    resumed = tmp_path / "resumed"
    shutil.copytree(fb_maze_physics_run, resumed)
    argv = fb_physics_args(resumed, 2500, "--resume")
    assert main(argv) == 0
    (resume,) = json.loads((resumed / "meta.json").read_text())["resumes"]
    assert resume["command"] == ["dvfb", *argv] and resume["step"] == 2000
    card = (dvfb.load(resumed).save_pretrained(tmp_path / "export") / "README.md").read_text()
    made = card.split("```bash\n", 1)[1].split("```", 1)[0].splitlines()
    assert made[0].startswith("dvfb pretrain --agent fb --domain point_mass_maze --frames 2000 ")
    assert made[1].startswith("dvfb pretrain --agent fb --domain point_mass_maze --frames 2500 ")
    assert made[1].endswith("--resume") and len(made) == 2
