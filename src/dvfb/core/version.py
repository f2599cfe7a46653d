"""dvfb's version, here in the lowest layer so that the layers that record it in their files
(run metadata, exports, datasets) need not import the package's face, which sits above them all;
``dvfb.__version__`` is the same string."""

__version__ = "0.1.0"  # the same as pyproject.toml's
