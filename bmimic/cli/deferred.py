"""`defer("torch")`: a module imported only when something first uses it, for a command that may not;
`names_on_first_use`, the lazy names of a package (PEP 562); and `import_on_first_use`, a module's own
`torch` global that imports torch when the module first uses it.

The sweep dry run (`bmimic-launch list`) checks every arm's config as the sweep will, which reads the
env terms' signatures and the sampler classes' signals (bmimic.config.checks.validate): those
modules `import torch` at their top, but a check calls nothing of torch's, and importing it is about
half of the dry run's time on a small machine. Deferred, the module is a stand-in in `sys.modules`
that `import torch` binds as usual; the first attribute read beyond the import system's own (`__spec__`,
`__path__`, ...) runs the module's code in that same object (as the standard library's
importlib.util.LazyLoader does, which instead runs it on `import torch` itself), so every name bound
to it is then the real module. Only a command's entry point defers, before anything imports the
module; a training process never does.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import types
from typing import Any, Callable

IMPORT_METADATA = frozenset({"__name__", "__spec__", "__loader__", "__package__", "__path__", "__file__"})
"""What the import system reads of a module in sys.modules (`import x`, `import x.y`): served without
running the module."""


class DeferredModule(types.ModuleType):
    """A module whose code runs at the first read of an attribute outside IMPORT_METADATA."""

    def __getattribute__(self, attr: str):
        namespace = object.__getattribute__(self, "__dict__")
        if attr in IMPORT_METADATA and attr in namespace:
            return namespace[attr]
        object.__setattr__(self, "__class__", types.ModuleType)  # from here on an ordinary module
        namespace["__spec__"].loader.exec_module(self)
        return getattr(self, attr)


def defer(name: str) -> None:
    """Put a DeferredModule for the top-level module `name` in sys.modules, unless it is imported
    already or cannot be found (an import of it then fails as it would have)."""
    if name in sys.modules:
        return
    spec = importlib.util.find_spec(name)
    if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
        return
    module = DeferredModule(name)
    module.__spec__ = spec
    module.__loader__ = spec.loader
    module.__package__ = name
    if spec.submodule_search_locations is not None:
        module.__path__ = list(spec.submodule_search_locations)
    if spec.origin is not None:
        module.__file__ = spec.origin
    sys.modules[name] = module


def names_on_first_use(package: str, sources: dict[str, str], namespace: dict) -> Callable[[str], Any]:
    """A package's module `__getattr__` (PEP 562) that imports each name of `sources` (name -> module)
    from its module when first read, then keeps it in `namespace` (the package's globals()), so the
    package imports none of its heavy modules itself (bmimic.motion, bmimic.robot)."""

    def __getattr__(name: str) -> Any:
        source = sources.get(name)
        if source is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(source), name)
        namespace[name] = value  # later lookups skip this function
        return value

    return __getattr__


class _ImportOnFirstUse:
    """Stands for a module in another module's globals until that module first reads one of its attributes."""

    def __init__(self, name: str, namespace: dict, binding: str) -> None:
        self._name, self._namespace, self._binding = name, namespace, binding

    def __getattr__(self, attr: str) -> Any:
        module = importlib.import_module(self._name)
        self._namespace[self._binding] = module  # every later read of the global is the module itself
        return getattr(module, attr)


def import_on_first_use(name: str, namespace: dict, binding: str | None = None) -> Any:
    """A stand-in for `import name` at a module's top, bound as `namespace[binding]` (the module's
    globals(); binding defaults to `name`): the module's first read of an attribute imports `name` and
    rebinds the global to the real module. So a module whose classes use torch only inside their
    methods (a sampler: its schema and class in one file) imports, and registers its schema for
    composing a config, without torch; unlike `defer` nothing outside that module changes, and after
    the first use (a sampler's constructor) the global is torch itself, as torch.compile expects.
    Type checkers should see the real import (``if TYPE_CHECKING: import torch``)."""
    if name in sys.modules and type(sys.modules[name]) is not DeferredModule:
        return sys.modules[name]
    return _ImportOnFirstUse(name, namespace, binding or name)


def is_deferred(name: str) -> bool:
    """`name` sits in sys.modules as a DeferredModule whose code has not run."""
    return type(sys.modules.get(name)) is DeferredModule
