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
        try:
            return getattr(importlib.import_module(module_name), attr)
        except (ImportError, AttributeError) as e:
            raise LookupError(f"cannot import {name!r}: {e}") from None
    module = _MODULES[kind]
    fn = getattr(module, name, None)
    if fn is None or name.startswith("_") or not callable(fn):
        available = sorted(n for n in module.__all__)
        raise LookupError(f"no {kind[:-1]} term {name!r}; available: {', '.join(available)}")
    return fn
