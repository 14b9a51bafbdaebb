"""The radio model: range, Bernoulli and burst loss, latency, reproducibility."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stack.comm.radio import RadioConfig, RadioModel


def _drops(cfg: RadioConfig, n: int, sender: int = 1) -> np.ndarray:
    radio = RadioModel(cfg, receiver_id=0)
    out = np.zeros(n, bool)
    for i in range(n):
        out[i] = not radio.offer(sender, (1.0, 0.0), (0.0, 0.0), stamp=i * 0.1, payload=i)
    return out


@pytest.mark.parametrize("p", [0.05, 0.2, 0.5])
def test_bernoulli_loss_rate_within_bounds(p):
    n = 20_000
    d = _drops(RadioConfig(loss=p, seed=7), n)
    sigma = math.sqrt(p * (1 - p) / n)
    assert abs(d.mean() - p) < 4 * sigma, (d.mean(), p)


def test_range_edge():
    r = RadioModel(RadioConfig(comm_range=10.0), receiver_id=0)
    assert not r.offer(1, (10.01, 0.0), (0.0, 0.0), 0.0, "far")
    assert r.offer(2, (9.99, 0.0), (0.0, 0.0), 0.0, "near")
    # range is from the sender's reported position to the receiver's own estimate, in 2D
    assert r.offer(3, (3.0, 4.0), (-4.0, -2.0), 0.0, "diagonal 9.22 -> in")
    assert r.counters.dropped_range == 1
    assert r.ready(0.0) == ["near", "diagonal 9.22 -> in"]


def _mean_run(d: np.ndarray) -> float:
    runs, cur = [], 0
    for x in d:
        if x:
            cur += 1
        elif cur:
            runs.append(cur)
            cur = 0
    return float(np.mean(runs))


def test_burst_loss_has_longer_runs_than_bernoulli_at_the_same_mean():
    # Gilbert-Elliott: stationary P(bad) = p_gb / (p_gb + p_bg) = 0.2, loss 1.0 in bad, 0 in good -> mean 0.2
    burst = RadioConfig(burst=(0.05, 0.2, 0.0, 1.0), seed=3)
    bern = RadioConfig(loss=0.2, seed=3)
    db, dn = _drops(burst, 40_000), _drops(bern, 40_000)
    assert abs(db.mean() - 0.2) < 0.02 and abs(dn.mean() - 0.2) < 0.01
    assert _mean_run(db) > 3 * _mean_run(dn)  # ~5 vs ~1.25


def test_latency_and_jitter_delay_delivery():
    r = RadioModel(RadioConfig(latency_ms=200, jitter_ms=100, seed=1), receiver_id=0)
    for i in range(50):
        r.offer(1, (1, 0), (0, 0), stamp=0.0, payload=i)
    assert r.ready(0.199) == []
    got = r.ready(0.25)
    assert 0 < len(got) < 50  # some jitters elapsed, some not
    assert len(got) + len(r.ready(0.3001)) == 50
    assert r.counters.delivered == 50


def test_seeded_per_sender_streams_do_not_depend_on_interleaving():
    cfg = RadioConfig(loss=0.4, seed=11)
    a, b = RadioModel(cfg, 0), RadioModel(cfg, 0)
    seq_a = {1: [], 2: []}
    seq_b = {1: [], 2: []}
    for i in range(200):  # a: 1,2,1,2...   b: all of 1 then all of 2
        for s in (1, 2):
            seq_a[s].append(a.offer(s, (1, 0), (0, 0), i, i))
    for s in (1, 2):
        for i in range(200):
            seq_b[s].append(b.offer(s, (1, 0), (0, 0), i, i))
    assert seq_a == seq_b
    assert seq_a[1] != seq_a[2]
