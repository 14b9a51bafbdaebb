"""Router ports for fleets started side by side on one host: never the same port to two runs.

A fleet's router is told its port before it binds it (``free_tcp_endpoint``: bind port 0, read it,
close). Two runs starting at once could draw the same port in that gap; so every port handed out
here is written to a per-user file under the temp folder (``fcntl`` lock) and not handed out
again for ``HOLD_S``, across every process on the host (``--jobs`` children, Dask workers,
other sweeps).
"""

from __future__ import annotations

import fcntl
import json
import os
import tempfile
import threading
import time
from pathlib import Path

HOLD_S = 120.0
"""How long a handed-out port stays reserved [s]: far longer than a router takes to bind it."""
_LOCK = threading.Lock()


def registry_path() -> Path:
    return Path(tempfile.gettempdir()) / f"stack-fleet-ports-{os.getuid()}.json"


def _read(f) -> dict[str, float]:
    f.seek(0)
    try:
        held = json.loads(f.read() or "{}")
    except ValueError:  # a file cut short by a killed writer: start over
        return {}
    return held if isinstance(held, dict) else {}


def allocate_endpoint(host: str = "127.0.0.1") -> str:
    """A free TCP port on ``host`` as a zenoh endpoint, one no other caller on this host got in the last ``HOLD_S``."""
    from ..comm.session import free_tcp_endpoint

    with _LOCK, open(registry_path(), "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        now = time.time()
        held = {p: t for p, t in _read(f).items() if isinstance(t, (int, float)) and now - t < HOLD_S}
        for _ in range(200):
            endpoint = free_tcp_endpoint(host)
            port = endpoint.rsplit(":", 1)[1]
            if port not in held:
                break
        else:
            raise OSError(f"no free TCP port on {host} outside the {len(held)} reserved ones ({registry_path()})")
        held[port] = now
        f.seek(0)
        f.truncate()
        f.write(json.dumps(held))
        f.flush()
    return endpoint
