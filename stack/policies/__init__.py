"""Onboard policies, one module (or package) per paper plus ``pid``; chosen by name, imported lazily.

Adding a policy is one module (its config dataclass, its Policy, its factory) and one line below
(see ``docs/extending.md``); out-of-tree policies come from entry points (``stack.plugins``).
"""

from __future__ import annotations

from ..plugins import Plugin, PluginError, Registry
from .base import Observation, Policy

# a factory takes (robot_config, **kw) and returns a Policy; its settings are robot.<key> in a scenario
POLICIES = Registry("policies", [
    Plugin("pid", "stack.policies.pid:PidConfig", "stack.policies.pid:make_pid", summary="go-to-goal PID (Bai 2022, situation 1)"),
    Plugin("drl", "stack.policies.drl.config:DrlConfig", "stack.policies.drl.policy:make_drl", summary="dueling double DQN (Bai 2022)"),
    Plugin("aina", "stack.policies.aina:AinaConfig", "stack.policies.aina:make_aina", summary="immune-network steering (Deng 2016)"),
    Plugin("fuzzy", "stack.policies.fuzzy.policy:FuzzyConfig", "stack.policies.fuzzy.policy:make_fuzzy",
           summary="fuzzy boundary following + FLC_SR arrival-time coordination (Chang 2020)"),
    Plugin("fuzzy-lstm", "stack.policies.fuzzy.policy:FuzzyConfig", "stack.policies.fuzzy.policy:make_fuzzy_lstm", key="fuzzy",
           summary="as fuzzy, with the LSTM coordinator (Chang 2020)"),
    Plugin("qlearn", "stack.policies.qlearn:QlearnPolicyConfig", "stack.policies.qlearn:make_qlearn",
           summary="Q-learning grid planning on a lidar map + eq. (12)-(13) tracking (Fan 2021)"),
])
REGISTRY = POLICIES


class PolicyUnavailable(PluginError):
    pass


def available() -> list[str]:
    return sorted(POLICIES)


def make_policy(name: str, robot, **kw) -> Policy:
    return factory(name)(robot, **kw)


def factory(name: str):
    """The factory of policy ``name`` (imported now): PolicyUnavailable, one line, if it is not registered or
    needs a package this install lacks (an extra), so an agent can say so before it connects to anything."""
    try:
        rec = POLICIES[name]
    except PluginError:
        raise PolicyUnavailable(f"policy {name!r} is not implemented yet (available: {', '.join(available())})") from None
    try:
        return rec.make()
    except ModuleNotFoundError as e:  # a policy from an extra this install does not have
        raise unavailable(name, e) from None


def unavailable(name: str, e: ModuleNotFoundError) -> PolicyUnavailable:
    """Policy ``name`` cannot run here because ``e.name`` is missing: the one line saying which extra has it."""
    extra = EXTRA_OF.get((e.name or "").split(".")[0])
    hint = f" (install the '{extra}' extra: pip install 'formation-stack[{extra}]')" if extra else ""
    return PolicyUnavailable(f"policy {name!r} needs the Python package {e.name!r}, not installed here{hint}")


EXTRA_OF = {"torch": "drl", "pybullet": "sim", "matplotlib": "sim"}
"""Packages that only an extra installs -> that extra (``pyproject.toml``)."""


def settings_class(key: str) -> type | None:
    """The config dataclass of the policies whose settings sit under ``robot.<key>`` (None: no such policy)."""
    rec = POLICIES.by_key(key)
    return rec.config_class() if rec is not None else None


__all__ = ["Observation", "POLICIES", "Policy", "PolicyUnavailable", "REGISTRY", "available", "make_policy", "settings_class"]
