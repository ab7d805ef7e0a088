"""Stage packages that are also the front door's functions: ``standgrid.enrich(catalog)``.

``standgrid.enrich`` and ``standgrid.compare`` are stage packages (the algorithms) and, at
the package root, the front door's ``enrich`` and ``compare`` (the pipelines). Python binds
an imported subpackage as an attribute of its parent, so a plain function of that name at
the root would be replaced by the subpackage as soon as anything imported it. Instead the
subpackage itself is callable and calls its pipeline entry point, imported on call (so the
stage never imports ``pipeline/`` when it is imported).
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import Any


class CallableStage(types.ModuleType):
    """A stage package whose call runs its pipeline (``__entry__`` = ``"module:function"``)."""

    __entry__: str

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        module, _, name = self.__entry__.partition(":")
        return getattr(importlib.import_module(module), name)(*args, **kwargs)


def make_callable(package: str, entry: str) -> None:
    """Make the (already imported) ``package`` call ``entry`` (``"module:function"``)."""
    module = sys.modules[package]
    module.__class__ = CallableStage
    assert isinstance(module, CallableStage)
    module.__entry__ = entry
