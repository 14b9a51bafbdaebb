"""The live view's endpoint (``--viz [tcp/HOST:PORT]``): loopback unless allowed, like every other endpoint."""

from __future__ import annotations

from ..comm.session import EndpointError, check_endpoint

DEFAULT_VIZ = "tcp/127.0.0.1:8765"


def parse_viz_endpoint(text: str | None, allow_remote: bool = False) -> tuple[str, int]:
    """``tcp/HOST:PORT`` (or ``ws/HOST:PORT``) of ``--viz`` -> (host, port); loopback unless ``allow_remote``.
    None or empty: the default, :data:`DEFAULT_VIZ`. A bad one is a ValueError (one line)."""
    text = text or DEFAULT_VIZ
    try:
        check_endpoint(text, allow_remote)
    except EndpointError as e:
        raise ValueError(f"--viz: {e}") from None
    proto, rest = text.split("/", 1)
    if proto not in ("tcp", "ws"):
        raise ValueError(f"--viz: endpoint {text!r}: the live view speaks WebSocket over tcp (tcp/HOST:PORT)")
    host, port = rest.rsplit(":", 1)
    return host.strip("[]"), int(port)
