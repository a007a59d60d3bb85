"""The tracking MDP as plain term functions: `f(env, **params) -> Tensor[num_envs, ...]` for
observations, rewards and terminations, `f(env, envs, **params)` for events.

Terms read the per-step state the environment computed once (`env.state`, see
`bmimic.envs.state.TrackingState`), so no term repeats another's work. A config names a term
by its function name in one of these modules, or by `package.module:function` for user code.
"""

from __future__ import annotations

import importlib
from typing import Callable

from bmimic.envs.mdp import events, observations, rewards, terminations

_MODULES = {"observations": observations, "rewards": rewards, "terminations": terminations, "events": events}


def resolve_term(kind: str, name: str) -> Callable:
    """The function a config entry names; LookupError with the available names if there is none."""
    if ":" in name:
        module_name, attr = name.split(":", 1)
        if module_name == "bmimic" or module_name.startswith("bmimic."):
            # bmimic's own functions: only the terms of this kind (a reward named as a termination,
            # or any other bmimic function, would fail inside the step).
            if module_name != _MODULES[kind].__name__ or attr not in _MODULES[kind].__all__:
                raise LookupError(f"{name!r} is not a {kind[:-1]} term; bmimic's are in {_MODULES[kind].__name__}: "
                                  f"{', '.join(sorted(_MODULES[kind].__all__))}")
            return getattr(_MODULES[kind], attr)
        try:
            return getattr(importlib.import_module(module_name), attr)
        except (ImportError, AttributeError) as e:
            raise LookupError(f"cannot import {name!r}: {e}") from None
    module = _MODULES[kind]
    fn = getattr(module, name, None)
    if fn is None or name not in module.__all__ or not callable(fn):
        available = sorted(n for n in module.__all__)
        raise LookupError(f"no {kind[:-1]} term {name!r}; available: {', '.join(available)}")
    return fn
