"""Tables, curves and analyses built from run directories.

* :mod:`~dvfb.analysis.common` -- the runs of a report (found by :mod:`dvfb.runs`), method names
  (:func:`method_name`), scores;
* :mod:`~dvfb.analysis.tables` -- the paper's Table 1 / Table 2 layout, statistics, markdown and CSV;
* :mod:`~dvfb.analysis.curves` -- fine-tuning curves (PNG);
* :mod:`~dvfb.analysis.report` -- ``dvfb report``: tables and curves from run directories;
* :mod:`~dvfb.analysis.aggregate`, :mod:`~dvfb.analysis.aggregate_report`,
  :mod:`~dvfb.analysis.normalise` -- normalised scores, aggregates with intervals, profiles;
* :mod:`~dvfb.analysis.statistics` -- the statistics of the analyses (rank correlations, coverage).
* :mod:`~dvfb.analysis.paper` -- the paper's published numbers (package data) beside a report's
  domain averages (``dvfb report --paper``, docs/reproduce.md).

Analysis works on files: it reads runs through :mod:`dvfb.runs` and imports no workflow. The
analyses that roll agents out (``dvfb analyze-value``, ``analyze-exploration``, ``video``) are
workflows (:mod:`dvfb.workflows.value`, :mod:`~dvfb.workflows.exploration`, :mod:`~dvfb.workflows.video`).
"""
