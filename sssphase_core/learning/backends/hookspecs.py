"""Hook specification for model backends (pluggy project ``sssphase``, entry-point group ``sssphase_backends``).

It lives in core, with the backends, so that core never imports the plugin layer: the plugin manager
(``sssphase_plugins.manager``) adds this spec and, when it is loaded, hands core its hook results
(``sssphase_core.learning.backends.use_plugin_backends``).

A backend plugin module implements::

    from sssphase_core.learning.backends import hookimpl

    @hookimpl
    def sssphase_model_backends():
        return {"mybackend": MyBackend}

where ``MyBackend(**options)`` follows ``sssphase_core.learning.backends.base.FootprintBackend``
(``pretrain``, ``fit``, ``predict_footprints(patches or (psp, pixels)) -> (N, K, K, 3)``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import pluggy

if TYPE_CHECKING:
    from sssphase_core.learning.backends.base import FootprintBackend

#: pluggy project of every sssphase hook (``sssphase_plugins.hookspecs.PROJECT`` is the same name).
hookspec = pluggy.HookspecMarker("sssphase")


@hookspec
def sssphase_model_backends() -> dict[str, Callable[..., FootprintBackend]]:
    """Return the model backends this plugin provides.

    :return: ``{name: factory}``; ``factory(**options)`` (e.g. ``checkpoint=...``) builds a
        :class:`~sssphase_core.learning.backends.base.FootprintBackend`. A name belongs to its first owner: a
        built-in's name, or an earlier plugin's, is not replaced (the later one is left out with a warning), and
        a hook that raises leaves only its own plugin's backends out. ``sss plugins`` lists them.
    """
