"""``dvfb tasks`` and ``dvfb agents``: the task table and the registered methods."""

from __future__ import annotations

import argparse

from dvfb import envs
from dvfb.agents import AGENTS


def cmd_tasks(args: argparse.Namespace) -> int:
    print(envs.format_task_table())
    return 0


def cmd_agents(args: argparse.Namespace) -> int:
    """The registered methods, from the registry."""
    rows = [(s.name, s.family, s.zero_shot, s.finetuner, ", ".join(s.sections)) for s in AGENTS.values()]
    header = ("agent", "family", "zero-shot", "fine-tuner", "config sections")
    widths = [max(len(r[i]) for r in rows + [header]) for i in range(len(header))]
    print("  ".join(h.ljust(w) for h, w in zip(header, widths)))
    for row in rows:
        print("  ".join(c.ljust(w) for c, w in zip(row, widths)))
    print()
    for spec in AGENTS.values():
        print(f"{spec.name}: {spec.summary}")
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser("tasks", help="print the task table", description="Print every task with its dimensions.")
    p.set_defaults(func=cmd_tasks)

    p = sub.add_parser("agents", help="list the methods", description="Every registered method with its family, "
                       "zero-shot strategy, fine-tuner and config sections.")
    p.set_defaults(func=cmd_agents)
