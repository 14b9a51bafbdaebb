"""Onboard policies, one module (or package) per paper plus ``pid``; chosen by name, imported lazily."""

from __future__ import annotations

import importlib

from .base import Observation, Policy

# name -> "module:factory"; a factory takes (robot_config, **kw) and returns a Policy.
REGISTRY: dict[str, str] = {
    "pid": "stack.policies.factories:make_pid",
    "aina": "stack.policies.factories:make_aina",
    "qlearn": "stack.policies.factories:make_qlearn",
    "drl": "stack.policies.factories:make_drl",
    "fuzzy": "stack.policies.factories:make_fuzzy",
    "fuzzy-lstm": "stack.policies.factories:make_fuzzy_lstm",
}


class PolicyUnavailable(LookupError):
    pass


def available() -> list[str]:
    return sorted(REGISTRY)


def make_policy(name: str, robot, **kw) -> Policy:
    if name not in REGISTRY:
        raise PolicyUnavailable(f"policy {name!r} is not implemented yet (available: {', '.join(available())})")
    module, fn = REGISTRY[name].split(":")
    return getattr(importlib.import_module(module), fn)(robot, **kw)


__all__ = ["Observation", "Policy", "PolicyUnavailable", "REGISTRY", "available", "make_policy"]
