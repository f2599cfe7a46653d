"""Tables, curves and analyses built from run directories.

* :mod:`~dvfb.analysis.common` -- run discovery, method names (:func:`method_name`), result records;
* :mod:`~dvfb.analysis.tables` -- the paper's Table 1 / Table 2 layout, statistics, markdown and CSV;
* :mod:`~dvfb.analysis.curves` -- fine-tuning curves (PNG);
* :mod:`~dvfb.analysis.report` -- ``dvfb report``: tables and curves from run directories;
* :mod:`~dvfb.analysis.value` -- ``dvfb analyze-value``: skill value vs return (paper §4, Fig. 3b);
* :mod:`~dvfb.analysis.exploration` -- ``dvfb analyze-exploration``: skill trajectories and state
  coverage (paper Fig. 2);
* :mod:`~dvfb.analysis.video` -- ``dvfb video``: rendered evaluation episodes (GIF / MP4).

Modules import torch, dm_control and matplotlib lazily where they can, so that ``dvfb report``
stays quick.
"""
