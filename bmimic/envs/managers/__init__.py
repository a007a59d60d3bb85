"""The environment's term managers, after mjlab's: each owns the terms of one kind (resolved from
the env config), their per-term buffers and their logged statistics."""

from bmimic.envs.managers.event_manager import EventManager
from bmimic.envs.managers.observation_manager import ObservationManager
from bmimic.envs.managers.reward_manager import RewardManager
from bmimic.envs.managers.termination_manager import TerminationManager
from bmimic.envs.managers.terms import Terms

__all__ = ["EventManager", "ObservationManager", "RewardManager", "TerminationManager", "Terms"]
