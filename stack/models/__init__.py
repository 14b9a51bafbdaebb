"""Shared models: one copy of each, used by the world, the agent, the EKF and the training worlds.

* :mod:`.kinematics`  the differential drive: wheel speeds <-> (v, w), and the unicycle's exact arc
  (Bai 2022 eq. (1) integrated over one period), in a scalar and a vectorised numpy form;
* :mod:`.geometry`    angle wrap, and the formation's slot geometry (Bai 2022 eq. (3));
* :mod:`.observation` what a robot sees of its target and its neighbours: the fields of the
  policies' :class:`stack.policies.base.Observation`, built once for the agent and the training worlds.

numpy and the standard library only; this room imports nothing else of ours, and every room may import it.
"""
