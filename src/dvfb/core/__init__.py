"""The lowest layer, which every other imports: dvfb's errors (:mod:`~dvfb.core.errors`), typed
configs and their flags (:mod:`~dvfb.core.config`), atomic files (:mod:`~dvfb.core.files`) and the
version the runs record (:mod:`~dvfb.core.version`) (docs/architecture.md, "Layers")."""
