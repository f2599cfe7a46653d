"""Shared test set-up.

* Import dvfb.envs first so its headless MUJOCO_GL default applies before any test module imports
  dm_control.
* One torch thread: the tests use tiny networks, for which thread start-up costs more than it
  saves, and results are then independent of the machine's core count.
* Tiers (README "Tests"): every test that uses the SLURM cluster is marked ``slurm`` and every
  test that mounts a tmpfs is marked ``root``, from the fixtures they use, so that no test can
  forget its marker. The SLURM tests share one cluster, so pytest-xdist keeps them on one worker
  (``--dist loadgroup``); ``e2e`` and ``slow`` are set by hand on the tests that run whole
  pipelines (``e2e``) or take more than a few seconds (``slow``, set from a timed run of the suite).
  ``make test-fast`` leaves out ``slurm``, ``e2e`` and ``slow``.
* The tiny pre-trained runs that several modules read (``dvfb_maze_run``, ``fb_maze_physics_run``)
  are made once per session here, and each test that used one checks that it left it as made. The
  helpers the modules share are in ``tiny.py`` (this directory is on ``sys.path``).
"""

import subprocess
from pathlib import Path

import pytest
import torch

import dvfb.envs  # noqa: F401
from dvfb.cli import main
from tiny import fb_physics_args, pretrain_args, tree_bytes

torch.set_num_threads(1)

_FIXTURE_MARKERS = {"slurm_cluster": "slurm", "small_disk": "root"}


@pytest.hookimpl(tryfirst=True)  # before -m deselects and xdist groups
def pytest_collection_modifyitems(config, items):
    for item in items:
        for fixture, marker in _FIXTURE_MARKERS.items():
            if fixture in getattr(item, "fixturenames", ()):
                item.add_marker(marker)
        if "slurm" in item.keywords:
            # One worker owns the cluster; the other runs everything else meanwhile.
            item.add_marker(pytest.mark.xdist_group("slurm"))
    # The SLURM tests first: they are the longest chain of one worker, so it starts at once and the
    # other worker's share runs beside it (xdist hands out work in collection order).
    items.sort(key=lambda item: "slurm" not in item.keywords)


@pytest.fixture
def small_disk(tmp_path):
    """A real 500 KiB tmpfs mounted for the test (root only; a missing permission fails loudly)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=500k", "tmpfs", str(mount)], capture_output=True,
                          text=True)
    if done.returncode != 0:
        pytest.fail(f"the disk-error tests need a small tmpfs (run as root): mount said {done.stderr.strip()}")
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=True)


# ---------------------------------------------------------------------------------------------
# Tiny pre-trained runs, each made once per session (per pytest-xdist worker) for every module that
# reads it. A test that writes into one (a zero-shot result, a fine-tuning, an analysis) works on
# tiny.copy_run(run, tmp_path); after every test that used a shared run, the run must be as it was
# made (tiny.tree_bytes: every file's bytes, a lock file's holder aside), or the test fails.

_SHARED_RUNS: dict[str, tuple[Path, dict]] = {}  # fixture name -> (run, its files as made)


def _shared(name: str, run: Path) -> Path:
    _SHARED_RUNS[name] = (run, tree_bytes(run))
    return run


@pytest.fixture(scope="session")
def dvfb_maze_run(tmp_path_factory) -> Path:
    """A DVFB run on the maze (tiny.pretrain_args(run, 2000)): 2000 frames, two episodes, one resume
    checkpoint per episode. Read only: write into tiny.copy_run(dvfb_maze_run, tmp_path)."""
    run = tmp_path_factory.mktemp("shared") / "dvfb_maze"
    assert main(pretrain_args(run, 2000)) == 0
    return _shared("dvfb_maze_run", run)


@pytest.fixture(scope="session")
def fb_maze_physics_run(tmp_path_factory) -> Path:
    """An FB run on the maze that records physics (tiny.fb_physics_args(run, 2000): two episodes)
    with one zero-shot result on point_mass_maze_reach_top_left. Read only, as dvfb_maze_run."""
    run = tmp_path_factory.mktemp("shared") / "fb"
    assert main(fb_physics_args(run, 2000)) == 0
    task = "point_mass_maze_reach_top_left"
    assert main(["zeroshot", str(run), "--task", task, "--inference.eval-episodes", "1"]) == 0
    return _shared("fb_maze_physics_run", run)


@pytest.fixture(autouse=True)
def _shared_runs_stay_as_made(request):
    yield
    for name in request.fixturenames:
        if name not in _SHARED_RUNS:
            continue
        run, made = _SHARED_RUNS[name]
        now = tree_bytes(run)
        if now != made:
            _SHARED_RUNS[name] = (run, now)  # blame this test only, not the ones after it
            changed = sorted(k for k in made.keys() | now.keys() if made.get(k, 0) != now.get(k, 0))
            pytest.fail(f"the test wrote into the shared run {name} ({run}): {', '.join(changed[:8])}; "
                        f"a test that writes works on tiny.copy_run({name}, tmp_path)", pytrace=False)
