"""At most one leader drives: the leader of a side of a partition drives only while its side is a quorum.

A dead robot and a robot on the far side of a partition look the same from here: its liveliness token went
away. The failover rule (``Formation.resolve``) makes the first live robot in the failover order (the scenario's
leader, then the lowest id) the leader of whatever this robot can hear, so each side of a partition would get its
own. The quorum rule stops all but one of them:

* ``members``: the robots of the last agreed membership, at the start the whole fleet. A robot that comes back is a
  member again at once.
* A side is a **quorum** when it holds more than half of the members, or exactly half and the first member in the
  failover order. Two disjoint sides of one membership cannot both be one.
* While this robot's side is a quorum, the membership shrinks to that side (a dead robot stops counting), so a fleet
  whose robots die one at a time keeps a leader down to the last two; the last robot of a pair that lost the first
  in the failover order holds (it cannot tell a dead partner from a partitioned one).
* A leader whose side is not a quorum holds: zero velocity, role ``leader``, situation ``no-quorum``. Its followers
  keep their slots about a leader that does not move.

Two leaders drive at once only while the sides' views of each other differ: a partition that forms or heals is
seen by the two sides within one liveliness delivery of each other, and each acts on it at its next control step;
so the bound is the liveliness skew plus one ``dt`` plus the ``CONFIRM_S`` a gone token waits (``stack.comm.link``),
about 0.7 s at ``dt = 0.1 s``. The fleet report measures it (``two_leaders_s``).
"""

from __future__ import annotations


def failover_order(leader: int | None, ids) -> list[int]:
    """The scenario's leader first, then the lowest id (``Formation.resolve``'s order)."""
    return sorted(ids, key=lambda r: (r != leader, r))


def is_quorum(side: set[int], members: set[int], leader: int | None) -> bool:
    """Whether ``side`` (the robots this one can hear, itself included) is a quorum of ``members``."""
    inside = side & members
    if 2 * len(inside) != len(members):
        return 2 * len(inside) > len(members)
    return bool(members) and failover_order(leader, members)[0] in inside


class Membership:
    """The fleet's agreed membership as this robot sees it, step by step (pure: a function of the gone sets)."""

    def __init__(self, ids, leader: int | None):
        self.ids, self.leader = frozenset(ids), leader
        self.members: set[int] = set(self.ids)
        self.quorum = True

    def update(self, gone: set[int]) -> bool:
        """This step's gone set -> whether this robot's side is a quorum now."""
        side = set(self.ids - gone)
        self.members |= side  # back: a member again
        self.quorum = is_quorum(side, self.members, self.leader)
        if self.quorum:
            self.members = side
        return self.quorum
