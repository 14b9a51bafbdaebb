"""Bai 2022 section IV decision layer on hand-made situations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stack.agents.decision import DecisionLayer, Neighbour, obstacle_distance
from stack.estimation.pose import Pose
from stack.scenario import FormationConfig, Slot

F = FormationConfig(leader=0, goal=(30.0, 0.0), slots={1: Slot(3.0, math.radians(180))}, d_safe=3.0)


def nb(i, x, y, role="follower"):
    return Neighbour(i, role, x, y, 0.0, 0.0, 0.0, stamp=0.0, seq=1)


def layer(rid, role, centre=True):
    return DecisionLayer(rid, role, F, goal=None, radius=0.5, comm_range=10.0, scan_range=5.0, dt=0.1, centre_heading=centre)


def test_leader_situations():
    d = layer(0, "leader")
    far = d.decide(Pose(0, 0, 0), 0.0, {1: nb(1, -5, 0)}, np.zeros((1, 0)), d_omin=math.inf)
    assert far.situation == "leader-1" and not far.use_network
    near = d.decide(Pose(0, 0, 0), 0.0, {1: nb(1, -2, 0)}, np.zeros((1, 0)), d_omin=math.inf)
    assert near.situation == "leader-2" and near.use_network
    # close to the goal: d_g < min(d_rmin, d_omin) -> PID even with a robot within d_safe
    home = d.decide(Pose(29.5, 0, 0), 0.0, {1: nb(1, 27.5, 0)}, np.zeros((1, 0)), d_omin=math.inf)
    assert home.situation == "leader-1"
    assert d.counts["leader-1"] == 2 and d.counts["leader-2"] == 1


def test_leader_speed_rule_eq20():
    assert DecisionLayer.leader_speed(1.0, 4.0) == 1.0
    assert DecisionLayer.leader_speed(1.0, 10.0) == 0.5


def test_leader_hold_keeps_the_farthest_robot_in_range():
    """Ours, beyond eq. (20): from start d_com to stop d_com the leader's speed falls linearly to zero."""
    hold = (0.8, 0.95)
    assert DecisionLayer.leader_speed(1.0, 4.0, hold=hold, d_com=10.0) == 1.0  # near: untouched
    assert DecisionLayer.leader_speed(1.0, 8.0, hold=hold, d_com=10.0) == pytest.approx(5 / 8)  # eq. (20) only
    assert DecisionLayer.leader_speed(1.0, 8.75, hold=hold, d_com=10.0) == pytest.approx(5 / 8.75 * 0.5)
    assert DecisionLayer.leader_speed(1.0, 9.5, hold=hold, d_com=10.0) == 0.0  # waits for it
    assert DecisionLayer.leader_speed(1.0, 9.9, hold=hold, d_com=10.0) == 0.0
    assert DecisionLayer.leader_speed(1.0, 9.5, hold=None, d_com=10.0) == pytest.approx(5 / 9.5)  # the paper's rule


def test_follower_situations_and_eq3_target():
    d = layer(1, "follower")
    leader = nb(0, 10, 0, role="leader")
    s1 = d.decide(Pose(5, 0, 0), 0.0, {0: leader}, np.zeros((1, 0)), d_omin=math.inf)
    assert s1.situation == "follower-1" and np.allclose(s1.target, (7.0, 0.0))  # eq. (3): 10 + 3 cos(180 deg)
    s2 = d.decide(Pose(8, 0, 0), 0.0, {0: leader}, np.zeros((1, 0)), d_omin=math.inf)
    assert s2.situation == "follower-2" and s2.use_network
    s3 = d.decide(Pose(5, 0, 0), 0.0, {0: leader, 2: nb(2, 6, 4)}, np.zeros((1, 0)), d_omin=1.0)
    assert s3.situation == "follower-3"
    # eq. (21)-(22): robots ahead (toward the leader) are selected, alpha_g points at their centre (8, 2)
    assert math.isclose(s3.obs.alpha_g, math.atan2(2, 3), abs_tol=1e-9)
    assert math.isclose(s3.obs.d_g, 2.0)
    # a policy without avoidance keeps the slot bearing
    s3_pid = layer(1, "follower", centre=False).decide(Pose(5, 0, 0), 0.0, {0: leader, 2: nb(2, 6, 4)}, np.zeros((1, 0)), 1.0)
    assert s3_pid.situation == "follower-3" and abs(s3_pid.obs.alpha_g) < 1e-12


def test_follower_without_leader_waits():
    d = layer(1, "follower")
    w = d.decide(Pose(0, 0, 0), 0.0, {}, np.zeros((1, 0)), d_omin=math.inf)
    assert w.situation == "waiting" and w.obs is None


def test_obstacle_distance_ignores_beams_on_neighbours():
    ang = np.linspace(-math.pi / 2, math.pi / 2, 181)
    scan = np.full(181, 5.0)
    scan[90] = 1.5  # straight ahead: a neighbour at 2 m (surface at 1.5)
    scan[0] = 2.5   # to the right: a wall
    d = obstacle_distance((0, 0), 0.0, scan, -math.pi / 2, ang[1] - ang[0], 5.0, [(2.0, 0.0)], 0.5)
    assert d == 2.5
    assert obstacle_distance((0, 0), 0.0, np.full(181, 5.0), -math.pi / 2, ang[1] - ang[0], 5.0, [], 0.5) == math.inf


def test_observation_carries_the_neighbours_states_with_their_age():
    """Policies that coordinate on states (Chang 2020's MRC) get them raw, world frame, with their age;
    a robot beyond comm range is not in them."""
    peer = DecisionLayer(5, "peer", None, goal=(10.0, 0.0), radius=0.5, comm_range=10.0, scan_range=5.0, dt=0.1)
    near = Neighbour(1, "peer", 3.0, 4.0, 0.5, 0.8, 0.1, stamp=1.5, seq=3)
    far = Neighbour(2, "peer", 30.0, 0.0, 0.0, 0.5, 0.0, stamp=2.0, seq=1)
    dec = peer.decide(Pose(0.0, 0.0, 0.0, 0.0, 0.0), 2.0, {1: near, 2: far}, np.full((1, 180), 5.0), 5.0)
    assert dec.obs.neighbour_states.shape == (1, 6)
    assert dec.obs.neighbour_states[0] == pytest.approx([3.0, 4.0, 0.5, 0.8, 0.1, 0.5])


def test_observation_carries_what_each_peer_reported_of_its_own_goal():
    """Arrival-time peers broadcast their distance to their own goal (State.d_goal); a sender that did not say is NaN."""
    peer = DecisionLayer(5, "peer", None, goal=(10.0, 0.0), radius=0.5, comm_range=10.0, scan_range=5.0, dt=0.1)
    said = Neighbour(1, "peer", 3.0, 4.0, 0.5, 0.8, 0.1, stamp=1.5, seq=3, d_goal=12.5)
    silent = Neighbour(2, "peer", 1.0, 1.0, 0.0, 0.5, 0.0, stamp=2.0, seq=1)
    dec = peer.decide(Pose(0.0, 0.0, 0.0, 0.0, 0.0), 2.0, {1: said, 2: silent}, np.full((1, 180), 5.0), 5.0)
    assert dec.obs.neighbour_d_goal.shape == (2,)
    assert dec.obs.neighbour_d_goal[0] == pytest.approx(12.5) and math.isnan(dec.obs.neighbour_d_goal[1])
