"""The lowest layer, which every other imports: dvfb's errors (:mod:`~dvfb.core.errors`), typed
configs and their flags (:mod:`~dvfb.core.config`) and atomic files (:mod:`~dvfb.core.files`)
(docs/architecture.md, "Layers")."""
