"""The files a researcher expects beside the code: CITATION.cff citing the paper and this version of
dvfb, and a .gitignore that keeps what the README's commands write out of a commit."""

from __future__ import annotations

import subprocess
from pathlib import Path

import yaml

import dvfb

ROOT = Path(__file__).resolve().parents[1]


def test_the_citation_file_cites_the_paper_and_this_version():
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert citation["cff-version"] == "1.2.0" and citation["type"] == "software"
    assert citation["version"] == dvfb.__version__
    (paper,) = citation["references"]
    assert paper["title"] == ("Unsupervised Zero-Shot Reinforcement Learning via Dual-Value Forward-Backward "
                              "Representation")
    assert paper["year"] == 2025 and paper["authors"][0]["family-names"] == "Sun"
    readme = (ROOT / "README.md").read_text()
    assert "[CITATION.cff](CITATION.cff)" in readme and "[CHANGELOG.md](CHANGELOG.md)" in readme


def test_what_the_readmes_commands_write_is_ignored_by_git():
    written = ["runs/dvfb_walker_small_s0", "demo/walker_walk.gif", "datasets/rnd_walker", "reports/walker",
               "shared/dvfb_walker_s0", "shared/dvfb_walker_s0.eval", "walker_walk.gif", "sweeps/alpha"]
    for path in written:
        done = subprocess.run(["git", "-C", str(ROOT), "check-ignore", "--no-index", "-q", path])
        assert done.returncode == 0, f"{path} is not ignored"
    kept = ["docs/results/cpu_experiment/exploration/dvfb_walker.png", "sweeps/paper/table1_zeroshot.toml",
            "src/dvfb/cli"]
    for path in kept:
        assert subprocess.run(["git", "-C", str(ROOT), "check-ignore", "--no-index", "-q", path]).returncode == 1, path
