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
"""

import subprocess

import pytest
import torch

import dvfb.envs  # noqa: F401

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
