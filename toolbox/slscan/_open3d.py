"""``import open3d`` without Dash and Plotly.

Open3D's package ``__init__`` imports ``open3d.visualization``, whose ``draw_plotly``
module imports Dash and Plotly for a browser viewer that slscan never uses: about half
of ``import open3d`` (0.7 of 1.5 s CPU here), paid by every worker process that
rasterises or registers. :func:`install` (run when slscan is imported) gives that one
module a stand-in whose functions load the real module on their first call, so
``open3d.visualization.draw_plotly(...)`` still works, and costs its imports only then.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import importlib.util
import sys
import types

DEFERRED = "open3d.visualization.draw_plotly"
_NAMES = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")  # what open3d.visualization imports


def _load_real() -> types.ModuleType:
    """The real ``draw_plotly`` module, loaded now (imports Dash and Plotly)."""
    module = sys.modules.get(DEFERRED)
    if module is not None and not getattr(module, "__slscan_stand_in__", False):
        return module
    spec = importlib.machinery.PathFinder.find_spec(DEFERRED, sys.modules["open3d.visualization"].__path__)
    real = importlib.util.module_from_spec(spec)
    sys.modules[DEFERRED] = real
    try:
        spec.loader.exec_module(real)
    except BaseException:
        sys.modules[DEFERRED] = module
        raise
    return real


def _deferred(name: str):
    def call(*args, **kwargs):
        return getattr(_load_real(), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    call.__module__ = DEFERRED
    call.__doc__ = f"Open3D's ``{DEFERRED}.{name}``, loaded (with Dash and Plotly) on the first call."
    return call


class _StandInLoader(importlib.abc.Loader):
    def create_module(self, spec):
        return None

    def exec_module(self, module: types.ModuleType) -> None:
        module.__slscan_stand_in__ = True
        for name in _NAMES:
            setattr(module, name, _deferred(name))
        module.__getattr__ = _module_getattr


def _module_getattr(name: str):
    if name.startswith("__"):  # the import system probes these (``__path__``): not the real module's
        raise AttributeError(name)
    return getattr(_load_real(), name)


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path, target=None):
        if fullname != DEFERRED:
            return None
        real = importlib.machinery.PathFinder.find_spec(fullname, path)
        if real is None:
            return None
        return importlib.util.spec_from_loader(fullname, _StandInLoader(), origin=real.origin)


def install() -> None:
    """Defer ``draw_plotly``'s imports in this process (no effect once Open3D is imported)."""
    if not any(isinstance(finder, _Finder) for finder in sys.meta_path):
        sys.meta_path.insert(0, _Finder())
