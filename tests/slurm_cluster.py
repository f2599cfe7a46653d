"""A real single-node SLURM cluster for the sweep tests (scripts/slurm_cluster.sh, README "Sweeps").

The fixture uses a cluster that is already up, or starts munged, slurmctld and slurmd with the
script (installing Debian's munge and slurm-wlm first when missing and running as root) and stops
exactly those daemons, by their process ids, at the end. A cluster that cannot be started fails
the tests that need it, with the script's reason.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "slurm_cluster.sh"


def cluster_is_up() -> bool:
    try:
        ping = subprocess.run(["scontrol", "ping"], capture_output=True, text=True, timeout=30)
        nodes = subprocess.run(["sinfo", "-h", "-N", "-o", "%T"], capture_output=True, text=True, timeout=30)
    except (FileNotFoundError, subprocess.TimeoutExpired):
        return False
    states = nodes.stdout.split()
    return ping.returncode == 0 and any(s.rstrip("*") in ("idle", "mixed", "allocated") for s in states)


def _stop(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.2)
    os.kill(pid, signal.SIGKILL)


@pytest.fixture(scope="session")
def slurm_cluster():
    """A running SLURM cluster (yields nothing); started here and stopped at the end if needed."""
    if cluster_is_up():
        yield
        return
    result = subprocess.run(["bash", str(SCRIPT), "start"], capture_output=True, text=True, timeout=900)
    if result.returncode != 0:
        pytest.fail(f"the SLURM cluster for the sweep tests could not be started ({SCRIPT} start): "
                    f"{(result.stderr or result.stdout).strip()}")
    # The script's last line: munged=PID slurmctld=PID slurmd=PID
    pids = dict(item.split("=") for item in result.stdout.strip().splitlines()[-1].split())
    try:
        yield
    finally:
        for daemon in ("slurmd", "slurmctld", "munged"):
            _stop(int(pids[daemon]))
