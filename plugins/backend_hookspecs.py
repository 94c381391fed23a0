"""Hook specification for model backends (pluggy project ``sssphase``, entry-point group ``sssphase_backends``).

A backend plugin module implements::

    from sssphase_core.backends import hookimpl

    @hookimpl
    def sssphase_model_backends():
        return {"mybackend": MyBackend}

where ``MyBackend(**options)`` follows ``sssphase_core.backends.base.FootprintBackend``
(``pretrain``, ``fit``, ``predict_footprints(patches or (psp, pixels)) -> (N, K, K, 3)``).
"""

from __future__ import annotations

from sssphase_plugins.hookspecs import hookspec


@hookspec
def sssphase_model_backends() -> dict:
    """Return {backend name: factory} of the model backends this plugin provides."""
