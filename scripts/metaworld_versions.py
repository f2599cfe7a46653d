"""How much do the faucet tasks differ between Meta-World's declared MuJoCo and dvfb's?

dvfb runs metaworld 3.0.0 on MuJoCo 3.17 (with its weld reset fixed, docs/tasks.md §7); metaworld
3.1.1 declares mujoco == 3.3.0. This script needs only metaworld and NumPy (not dvfb), so the same
file runs in both environments and their outputs can be compared:

    python scripts/metaworld_versions.py > mujoco317.json        # in dvfb's .venv
    python3 -m venv /tmp/mw33 && /tmp/mw33/bin/pip install mujoco==3.3.0 metaworld==3.1.1 packaging
    /tmp/mw33/bin/python scripts/metaworld_versions.py > mujoco33.json
    python scripts/metaworld_versions.py --compare mujoco317.json mujoco33.json
    # and metaworld 3.0.0 on mujoco 3.3.0, to separate Meta-World's changes from MuJoCo's:
    python3 -m venv /tmp/mw30 && /tmp/mw30/bin/pip install mujoco==3.3.0 metaworld==3.0.0 packaging
    /tmp/mw30/bin/python scripts/metaworld_versions.py > mujoco33_mw300.json
    python scripts/metaworld_versions.py --compare mujoco33_mw300.json mujoco33.json

For each task it runs ML1's first 10 test tasks (seed 0) for 250 steps with the same uniform-random
actions, and with Meta-World's scripted expert, recording the return and the final-step success.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import pickle
import sys
import warnings

import numpy as np

TASKS = ("faucet-open-v3", "faucet-close-v3")
EPISODES, STEPS = 10, 250


def measure() -> dict:
    import mujoco
    import metaworld
    from metaworld import policies, sawyer_xyz_env

    if mujoco.mjNEQDATA > 11:  # the weld fix of dvfb.envs.meta_world, written out here
        def reset_mocap_welds(self):
            for i in range(self.model.eq_data.shape[0]):
                if self.model.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
                    self.model.eq_data[i, :11] = [0.0, 0, 0, 0, 0, 0, -1.0, 0, 0, 0, 5.0]
        sawyer_xyz_env.SawyerMocapBase.reset_mocap_welds = reset_mocap_welds
    experts = {"faucet-open-v3": policies.SawyerFaucetOpenV3Policy(),
               "faucet-close-v3": policies.SawyerFaucetCloseV3Policy()}
    out = {"mujoco": mujoco.__version__, "metaworld": importlib.metadata.version("metaworld"), "tasks": {}}
    for name in TASKS:
        benchmark = metaworld.ML1(name, seed=0)
        env = benchmark.test_classes[name]()
        rows = []
        for index, task in enumerate(benchmark.test_tasks[:EPISODES]):
            row = {"position": np.asarray(pickle.loads(task.data)["rand_vec"]).tolist()}
            for policy in ("random", "expert"):
                env.set_task(task)
                obs, _ = env.reset()
                actions = np.random.default_rng(index).uniform(-1, 1, (STEPS, 4))
                total, info = 0.0, {}
                for t in range(STEPS):
                    if policy == "random":
                        action = actions[t]
                    else:
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore")
                            action = np.clip(experts[name].get_action(obs), -1, 1)
                    obs, reward, _, _, info = env.step(action)
                    total += float(reward)
                row[policy] = {"return": total, "success": bool(info["success"])}
            rows.append(row)
        out["tasks"][name] = rows
    return out


def compare(a: dict, b: dict) -> None:
    print(f"A: mujoco {a['mujoco']}, metaworld {a['metaworld']}; B: mujoco {b['mujoco']}, metaworld {b['metaworld']}")
    for name in TASKS:
        rows_a, rows_b = a["tasks"][name], b["tasks"][name]
        same_positions = all(ra["position"] == rb["position"] for ra, rb in zip(rows_a, rows_b))
        print(f"{name}: same ML1 test positions: {same_positions}")
        for policy in ("random", "expert"):
            ret_a = np.array([r[policy]["return"] for r in rows_a])
            ret_b = np.array([r[policy]["return"] for r in rows_b])
            rel = np.abs(ret_a - ret_b) / np.abs(ret_b)
            succ_a = np.mean([r[policy]["success"] for r in rows_a])
            succ_b = np.mean([r[policy]["success"] for r in rows_b])
            print(f"  {policy:6s} mean return A {ret_a.mean():8.2f}  B {ret_b.mean():8.2f}  "
                  f"max per-episode relative difference {rel.max():.2e}  final-step success A {succ_a:.1f}  B {succ_b:.1f}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--compare", nargs=2, metavar=("A.json", "B.json"), help="compare two outputs")
    args = parser.parse_args()
    if args.compare:
        compare(*(json.load(open(path)) for path in args.compare))
    else:
        json.dump(measure(), sys.stdout)
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
