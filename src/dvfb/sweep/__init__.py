"""Sweeps: a grid of methods x domains x seeds (x any config flag) run through the phases
pre-train -> zero-shot -> fine-tune -> report, on a local worker pool or a SLURM cluster, resumable
after preemption, requeue or a killed submitter (README "Sweeps", docs/sweeps.md).

* :mod:`dvfb.sweep.spec` -- the typed sweep description (a TOML/JSON file or CLI flags) and its
  expansion into cells, one run directory per cell;
* :mod:`dvfb.sweep.units` -- one phase of one cell (a "unit"): when it is done, the ``dvfb``
  command that runs or resumes it, and its state record and log;
* :mod:`dvfb.sweep.executors` -- the ``debug`` (in-process), ``local`` (worker pool) and ``slurm``
  (submitit job arrays) executors;
* :mod:`dvfb.sweep.runner` -- starting or continuing a sweep, its reports, and the table of
  ``dvfb sweep status``.

The command lines are :mod:`dvfb.cli.sweep`'s. A sweep reads its runs through :mod:`dvfb.runs` and
runs ``dvfb`` commands; it imports no workflow.

A sweep directory holds::

    SWEEP/sweep.json               the resolved sweep (what a re-run must match)
    SWEEP/runs/<cell>/             one pre-training run directory per cell (zeroshot/, finetune/)
    SWEEP/state/<cell>/<unit>.json state of each unit: running/done/failed, attempts, exit reason
    SWEEP/logs/<cell>/<unit>.log   output of every attempt of the unit
    SWEEP/slurm/                   submitit's job scripts and logs (slurm executor)
    SWEEP/jobs.json                SLURM job ids of the units submitted (slurm executor)
    SWEEP/report/                  the report over seeds (dvfb report), one per swept value
    SWEEP/.gitignore               leaves checkpoints, snapshots, state and logs out of git, so that
                                   a committed sweep directory holds its small results
"""
