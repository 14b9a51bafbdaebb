"""Zenoh key expressions of the contract (INTERFACES.md section 4)."""

from __future__ import annotations

import re
from dataclasses import dataclass

ROBOT_TOPICS = ("state", "cmd_vel", "answer", "scan", "odom", "imu", "fix", "diag", "step_io", "virtual_scan")


@dataclass(frozen=True)
class Keys:
    """Key expressions of one fleet: ``stack/<fleet>/...``."""

    fleet: str = "default"

    @property
    def prefix(self) -> str:
        return f"stack/{self.fleet}"

    def robot(self, robot_id: int | str, topic: str) -> str:
        if topic not in ROBOT_TOPICS:
            raise ValueError(f"unknown robot topic {topic!r}")
        return f"{self.prefix}/{robot_id}/{topic}"

    def all_robots(self, topic: str) -> str:
        return self.robot("*", topic)

    def world(self, topic: str) -> str:
        return f"{self.prefix}/world/{topic}"

    def alive(self, robot_id: int | str) -> str:
        return f"{self.prefix}/alive/{robot_id}"

    @property
    def all_alive(self) -> str:
        return self.alive("*")

    @staticmethod
    def id_of(key: str) -> int | None:
        """The robot id in ``stack/<fleet>/<id>/<topic>`` or ``stack/<fleet>/alive/<id>``; None if not a number."""
        parts = str(key).split("/")
        if len(parts) < 4:
            return None
        token = parts[3] if parts[2] == "alive" else parts[2]
        return int(token) if token.isascii() and token.isdigit() else None


_CHUNK = re.compile(r"[^/*$?#\s]+")


def check_key_expr(key: str) -> str | None:
    """Why ``key`` is not a concrete Zenoh key (chunks separated by '/', no wildcards, no spaces); None if it is."""
    if key.startswith("/") or key.endswith("/"):
        return "no leading or trailing '/'"
    if not all(_CHUNK.fullmatch(c) for c in key.split("/")):
        return "empty chunk, a wildcard ('*', '$', '?', '#') or a space"
    return None
