"""``bench/soak.py`` for a few seconds: it reads every process of a real-time fleet, fits the growth, runs the
lock-step soak and says whether the bounds held. A long run's numbers are in the README (its command there)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from conftest import ROOT

pytestmark = pytest.mark.fleet


def test_a_short_soak_samples_every_process_and_checks_its_bounds(tmp_path):
    out = tmp_path / "soak"
    p = subprocess.run([sys.executable, "bench/soak.py", "--robots", "3", "--duration", "8", "--every", "0.5",
                        "--lockstep-s", "2", "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=180)
    assert p.returncode in (0, 1), p.stdout + p.stderr
    res = json.loads((out / "soak.json").read_text())
    assert {"router", "world", "agent 0", "agent 1", "agent 2"} <= set(res["series"]), res["series"].keys()
    for name in ("world", "agent 0"):
        rows = res["series"][name]
        assert len(rows) >= 8 and all(r["rss_mb"] > 10 and r["fds"] > 3 and r["threads"] > 1 for r in rows[len(rows) // 2:])
        g = res["growth"][name]
        assert set(g) == {"rss_mb", "fds", "threads"} and all("per_h" in v for v in g.values())
    assert res["crashed"] == [] and res["lockstep"]["late_steps"] == 0 and res["lockstep"]["steps"] >= 20
    assert ("bounds kept" in p.stdout) == (p.returncode == 0) and (out / "soak.png").stat().st_size > 5000
    assert "| world |" in (out / "soak.md").read_text()
