"""Bai 2022 (IEEE T-ITS 23(8)): dueling double DQN collision avoidance, the network of the hybrid
leader-follower strategy. Observation/actions in :mod:`.observation`, reward eq. (14)-(17) in
:mod:`.reward`, Fig. 5 in :mod:`.network`, the onboard policy in :mod:`.policy`; training in
:mod:`stack.train.drl` (``stack-train drl``)."""

from .observation import ACTIONS, N_ACTIONS

__all__ = ["ACTIONS", "N_ACTIONS", "DrlPolicy", "make_drl"]


def __getattr__(name):  # torch only when the policy is used
    if name in ("DrlPolicy", "make_drl"):
        from . import policy

        return getattr(policy, name)
    raise AttributeError(name)
