"""A group split over several processes (docs/members.md, "A group over several processes").

A group's members are independent runs, so they may be trained by more than one process: the
members are cut into contiguous shares, and each share is an ordinary group of its own in a child
process with its own torch threads. On a CPU with few cores, two single-thread processes multiply
faster than one process on two threads (each keeps its core's caches to itself), and each share
still stacks its members' networks (bench/README.md, "Members").

The parent holds every member's run-directory lock while its children run, forwards SIGTERM and
SIGINT to them (as SIGTERM: a second SIGINT would stop a child without its checkpoint), waits for
all of them, and reports their errors as one. A child that dies (``kill -9``, the out-of-memory
killer) or fails has the others stopped with SIGTERM, so that every share has a checkpoint and the
group resumes together. A child whose parent dies (``kill -9``) gets SIGTERM from the kernel, so it
checkpoints and stops rather than train on without its locks.
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import threading
import traceback
from multiprocessing.connection import wait
from typing import Any, Callable, Sequence

import torch

from dvfb.core import errors
from dvfb.core.errors import DvfbError, RunInterrupted
from dvfb.runs.machine import cores


def shares(count: int, processes: int) -> list[range]:
    """``count`` members cut into ``min(processes, count)`` contiguous shares whose sizes differ by
    at most one, the larger ones first."""
    processes = max(1, min(processes, count))
    size, extra = divmod(count, processes)
    out, start = [], 0
    for k in range(processes):
        stop = start + size + (1 if k < extra else 0)
        out.append(range(start, stop))
        start = stop
    return out


def group_schedule(members: int, processes: int, torch_threads: int, cuda: bool = False) -> tuple[int, int]:
    """How a group of ``members`` runs (README.md, "Threads and progress"): ``(processes, torch threads of
    each)``, the threads 0 for a group in this process (it takes a run's threads).

    ``processes`` given (> 0): that many shares, at most one per member, sharing ``torch_threads`` (0:
    the CPUs) equally. Not given (0, the default): on a CUDA device, or with ``torch_threads`` given,
    the group runs in this process; otherwise one single-thread share per CPU this process may use,
    up to one per member. Single threads, because a share of several OpenMP threads crawls when
    another process takes one of its cores, while single-thread processes only share the cores; and
    on a CPU with few cores two single-thread processes multiply faster than one on two threads
    (bench/README.md, "The default schedule of a group")."""
    if processes > 0:
        count = min(processes, members)
        return count, threads_per_process(torch_threads, count) if count > 1 else 0
    if cuda or torch_threads > 0 or members == 1:
        return 1, 0
    count = min(members, cores())
    return count, 1 if count > 1 else 0


def threads_per_process(torch_threads: int, processes: int) -> int:
    """The torch threads of each child: an equal part (at least one) of the command's ``torch_threads``,
    or of the CPUs when it is 0."""
    return max(1, (torch_threads if torch_threads > 0 else cores()) // processes)


class _Stop(Exception):
    """The parent's answer to a child that was ready while another child was not."""


def _die_with(parent: int) -> None:
    """Have the kernel send this process SIGTERM when ``parent`` dies (Linux's PR_SET_PDEATHSIG): a
    child whose command was killed outright checkpoints and stops instead of training on in
    directories whose locks died with the command."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: the parent's signal forwarding is all there is
        return
    if os.getppid() != parent:  # it died before the request was made
        os.kill(os.getpid(), signal.SIGTERM)


def _send(pipe, message) -> None:
    try:
        pipe.send(message)
    except OSError:  # the parent is gone: nobody to tell
        pass


def _child(target: Callable, args: tuple, threads: int, pipe, parent: int) -> None:
    _die_with(parent)
    # Set before the target builds anything: torch's thread pool sizes itself on first use.
    torch.set_num_threads(threads)

    def ready(status: Any) -> None:
        pipe.send(("ready", status))
        if pipe.recv() != "go":
            raise _Stop

    try:
        target(*args, ready=ready)
    except _Stop:
        _send(pipe, ("stopped", "", None))
        raise SystemExit(1) from None
    except DvfbError as exc:
        _send(pipe, (type(exc).__name__, str(exc), getattr(exc, "signum", None)))
        raise SystemExit(1) from None
    except BaseException:
        _send(pipe, ("crash", traceback.format_exc(), None))
        raise SystemExit(1) from None
    _send(pipe, None)


def _died(child) -> tuple[str, str, int | None]:
    """The outcome of a child that ended without reporting: killed by a signal (the out-of-memory
    killer's SIGKILL), or an exit of the interpreter itself."""
    child.join()
    code = child.exitcode
    if code is not None and code < 0:
        name = signal.Signals(-code).name
        why = " (as the out-of-memory killer does)" if -code == signal.SIGKILL else ""
        return ("died", f"its process was killed by {name}{why} and wrote nothing after its last resume checkpoint",
                -code)
    return "died", f"its process ended with exit code {code} before reporting", None


def _answer(child, pipe) -> Any:
    """The child's message, or its death when it ended without one (waiting for either: a child
    that dies may leave its pipe open where a process it started still holds it)."""
    wait([pipe, child.sentinel])
    try:
        if pipe.poll():
            return pipe.recv()
    except EOFError:
        pass
    return _died(child)


def _stops_the_group(outcome) -> bool:
    """Whether a share's ending stops the others: its process died, crashed, was stopped by a signal
    or failed; a share whose members all went non-finite is a member fault, which the others outlive
    (docs/members.md)."""
    return outcome is not None and outcome[0] not in ("stopped", "NonFiniteLossError")


def run_in_processes(target: Callable, calls: Sequence[tuple], threads: int, names: Sequence[str],
                     agree: Callable[[list], None] | None = None) -> None:
    """``target(*args, ready=...)`` for every ``args`` of ``calls``, each in its own child process
    with ``threads`` torch threads, all at once; ``names[k]`` says in an error which members call
    ``k`` trained.

    Each target calls ``ready(status)`` once it has checked and read everything and before it writes
    anything; the children go on together when every one of them is ready and ``agree`` (given the
    statuses) raises nothing. Otherwise the ready ones stop unchanged and the first error is raised.
    Once they train, a child that dies (``kill -9``, the out-of-memory killer) or fails stops the
    others with SIGTERM, so that each writes a checkpoint and the group resumes together. Returns when
    every child has ended; raises, after all have ended, the children's errors as one
    :class:`~dvfb.core.errors.DvfbError` (the first child's class; a signal received here, or one that
    killed a child, makes it :class:`~dvfb.core.errors.RunInterrupted` with that signal).
    """
    context = multiprocessing.get_context("spawn")  # no fork of a process that holds torch's threads
    children, pipes = [], []
    received: list[int] = []

    def forward(signum, _frame) -> None:
        received.append(signum)
        for child in children:
            if child.is_alive() and child.pid is not None:
                os.kill(child.pid, signal.SIGTERM)

    main = threading.current_thread() is threading.main_thread()
    previous = {s: signal.signal(s, forward) for s in (signal.SIGTERM, signal.SIGINT)} if main else {}
    agreed: Exception | None = None
    try:
        for args in calls:
            here, there = context.Pipe()
            child = context.Process(target=_child, args=(target, args, threads, there, os.getpid()))
            child.start()
            there.close()
            children.append(child)
            pipes.append(here)
            if received:  # a signal came while starting: this child stops too
                os.kill(child.pid, signal.SIGTERM)
        first = [_answer(child, pipe) for child, pipe in zip(children, pipes)]
        ready = [isinstance(m, tuple) and m[0] == "ready" for m in first]
        if all(ready) and agree is not None:
            try:
                agree([m[1] for m in first])
            except DvfbError as exc:
                agreed = exc
        go = all(ready) and agreed is None
        for pipe, is_ready in zip(pipes, ready):
            if is_ready:
                pipe.send("go" if go else "stop")
        outcomes = [None if is_ready else message for message, is_ready in zip(first, ready)]
        _wait_for_all(children, pipes, [k for k, is_ready in enumerate(ready) if is_ready], outcomes, go)
    finally:
        for child in children:
            child.join()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if agreed is not None:
        raise agreed
    failed = [(name, outcome) for name, outcome in zip(names, outcomes)
              if outcome is not None and outcome[0] != "stopped"]
    if not failed:
        return
    # The share that died first in the line: it is why the others stopped.
    failed.sort(key=lambda item: item[1][0] != "died")
    message = "; ".join(f"{name}: {text}" for name, (_kind, text, _signum) in failed)
    killed = [s for _name, (kind, _t, s) in failed if kind == "died" and s is not None]
    interrupted = [s for _name, (kind, _t, s) in failed if kind == "RunInterrupted"]
    if received or killed or interrupted:
        raise RunInterrupted(message, (received or killed or interrupted)[0])
    kind = failed[0][1][0]
    if kind == "crash":
        raise RuntimeError(message)
    error = getattr(errors, kind, DvfbError) if kind != "died" else DvfbError
    raise error(message)


def _wait_for_all(children, pipes, pending: list[int], outcomes: list, training: bool) -> None:
    """Each pending child's outcome into ``outcomes``, in the order they end; while ``training``, the
    first to die or fail has the others stopped with SIGTERM (each checkpoints and reports)."""
    pending = list(pending)
    stopping = False
    while pending:
        ready = wait([pipes[k] for k in pending] + [children[k].sentinel for k in pending])
        for k in [k for k in pending if pipes[k] in ready or children[k].sentinel in ready]:
            pending.remove(k)
            outcomes[k] = _answer(children[k], pipes[k])
            if training and not stopping and _stops_the_group(outcomes[k]):
                stopping = True
                for j in pending:
                    if children[j].is_alive():
                        os.kill(children[j].pid, signal.SIGTERM)
