"""Zenoh sessions with the project's network rule built in.

Every session opened through here has multicast scouting off and explicit endpoints;
the defaults are loopback only. Layered like zenoh-python's examples: a base config
(mode, endpoints) plus ``overrides`` of json5 key paths (e.g. from ``deploy/`` files)::

    with open_session(SessionConfig(connect=["tcp/127.0.0.1:7447"])) as session:
        ...
"""

from __future__ import annotations

import json
import logging
import re
import socket
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"

RECONNECT = "{period_init_ms: 250, period_max_ms: 1000, period_increase_factor: 1.5}"
"""A client's retry of its routers once it lost them (zenoh's ``connect/retry``): a restarted router is rejoined
within about a second (zenoh's own default backs off to 4 s). A config file or an override that sets
``connect/retry`` wins."""


class EndpointError(ValueError):
    """An endpoint string that zenoh would not accept, or one off loopback without opt-in."""


class SessionError(RuntimeError):
    """A session that could not open: no router at the endpoint, a port in use, a bad config file."""


class ConfigFileError(SessionError):
    """A ``config_file`` that is missing or is not a zenoh json5 config (a :class:`SessionError`, one line)."""


def one_line(err: object) -> str:
    """A zenoh error as one line: json5 parse reports span several lines and end in the Rust source location."""
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?", "", str(err))
    where = re.search(r"-->\s*(\d+):(\d+)", text)
    what = re.search(r"^\s*=\s*(.+)$", text, re.M)
    if where and what:
        return f"line {where.group(1)}, column {where.group(2)}: {what.group(1).strip()}"
    return " ".join(part.strip() for part in text.splitlines() if part.strip().strip("|^-").strip())


@dataclass
class SessionConfig:
    """One Zenoh session.

    mode: ``client`` (agents, world, tools: through a router) or ``router`` (the fleet's own).
    connect: endpoints to reach, e.g. ``tcp/127.0.0.1:7447``.
    listen: endpoints to accept on (routers).
    config_file: a zenoh json5 file (e.g. from ``deploy/``: TLS, access control) loaded first; our settings
        layer on top: mode, multicast scouting off, and ``connect``/``listen`` replace the file's endpoints
        (where ours are empty, a plain list in the file stays, checked by the same loopback rule). A file
        that is missing or not a zenoh config, or that names a certificate or key that does not exist,
        is a :class:`ConfigFileError` (one line).
    overrides: further ``key/path -> json5 value`` insertions, applied last.
    allow_remote: endpoints off loopback are refused unless this is set (multi-host fleets).
    """

    mode: str = "client"
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=list)
    config_file: str | None = None
    overrides: dict[str, str] = field(default_factory=dict)
    allow_remote: bool = False


def check_endpoint(endpoint: str, allow_remote: bool = False) -> str:
    """Validate ``proto/host:port``; loopback hosts only unless ``allow_remote``."""
    try:
        proto, rest = endpoint.split("/", 1)
        host, port_s = rest.rsplit(":", 1)
        port = int(port_s.split("#")[0])
    except ValueError:
        raise EndpointError(f"endpoint {endpoint!r}: expected PROTO/HOST:PORT, e.g. tcp/127.0.0.1:7447") from None
    if proto not in ("tcp", "udp", "tls", "quic", "ws"):
        raise EndpointError(f"endpoint {endpoint!r}: unknown protocol {proto!r}")
    if not 0 < port < 65536:
        raise EndpointError(f"endpoint {endpoint!r}: port {port} out of range")
    h = host.strip("[]")
    if not allow_remote and not (h == "localhost" or h.startswith("127.") or h == "::1"):
        raise EndpointError(f"endpoint {endpoint!r}: not a loopback address (multi-host fleets use deploy/ configs)")
    return endpoint


def zenoh_config(cfg: SessionConfig) -> zenoh.Config:
    try:
        conf = zenoh.Config.from_file(cfg.config_file) if cfg.config_file else zenoh.Config()
    except (zenoh.ZError, OSError) as e:
        raise ConfigFileError(f"{cfg.config_file}: not a usable zenoh config: {one_line(e)}") from None
    if cfg.config_file:
        _check_tls_files(conf, cfg.config_file)
    for ep in cfg.connect + cfg.listen:
        check_endpoint(ep, cfg.allow_remote)
    conf.insert_json5("mode", json.dumps(cfg.mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if cfg.mode != "router":
        conf.insert_json5("scouting/gossip/enabled", "false")
    for what, ours in (("connect", cfg.connect), ("listen", cfg.listen)):
        # ours replace the file's; with none of ours, the file's stay (checked by the same rule)
        kept = _file_endpoints(conf, what) if cfg.config_file and not ours else []
        for ep in kept:
            check_endpoint(ep, cfg.allow_remote)
        conf.insert_json5(f"{what}/endpoints", json.dumps(ours or kept))
    if cfg.mode == "client" and not _has(conf, "connect/retry") and not any(k.startswith("connect/retry") for k in cfg.overrides):
        conf.insert_json5("connect/retry", RECONNECT)
    for key, value in cfg.overrides.items():
        conf.insert_json5(key, value)
    if "multicast/enabled" in str(cfg.overrides) and "true" in str(cfg.overrides):
        log.warning("zenoh: multicast scouting switched on by an override")
    return conf


def _has(conf: zenoh.Config, key: str) -> bool:
    try:
        return json.loads(conf.get_json(key)) is not None
    except (zenoh.ZError, ValueError):
        return False


def endpoint_list(text: str, allow_remote: bool = False) -> list[str]:
    """``--connect A,B``: one or more router endpoints, comma-separated, each checked (:func:`check_endpoint`). A
    client joins the first it reaches and, having lost it, whichever of them answers first."""
    eps = [e.strip() for e in text.split(",") if e.strip()]
    if not eps:
        raise EndpointError(f"endpoint list {text!r}: no endpoint")
    return [check_endpoint(e, allow_remote) for e in eps]


def _file_endpoints(conf: zenoh.Config, what: str) -> list[str]:
    """The endpoints a config file lists (a plain list; zenoh's per-mode default ``{router: [...], peer: [...]}``
    is not a choice of the file's author and is dropped, as before)."""
    try:
        value = json.loads(conf.get_json(f"{what}/endpoints"))
    except (zenoh.ZError, ValueError):
        return []
    return [str(e) for e in value] if isinstance(value, list) else []


TLS_FILES = ("root_ca_certificate", "listen_private_key", "listen_certificate", "connect_private_key", "connect_certificate")


def _check_tls_files(conf: zenoh.Config, source: str) -> None:
    """Name a missing certificate or key here: zenoh itself only says it cannot connect or listen."""
    for name in TLS_FILES:
        try:
            value = json.loads(conf.get_json(f"transport/link/tls/{name}"))
        except (zenoh.ZError, ValueError):
            continue
        if isinstance(value, str) and not Path(value).is_file():
            raise ConfigFileError(f"{source}: transport.link.tls.{name}: no such file {value}")


def open_session(cfg: SessionConfig) -> zenoh.Session:
    """Open a session (a context manager: ``with open_session(cfg) as s``); :class:`SessionError` if it cannot."""
    conf = zenoh_config(cfg)
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        where = ", ".join(cfg.listen if cfg.mode == "router" else cfg.connect) or "(no endpoint)"
        what = "cannot listen on" if cfg.mode == "router" else "cannot reach a Zenoh router at"
        reason = one_line(e)
        raise SessionError(f"{what} {where}: {reason}") from None


def client(endpoint: str, **kw) -> SessionConfig:
    """A client of the router(s) at ``endpoint`` (one, or several comma-separated)."""
    return SessionConfig(mode="client", connect=[e.strip() for e in endpoint.split(",") if e.strip()], **kw)


def port_free(endpoint: str) -> bool:
    """Whether a TCP endpoint's port can be bound now."""
    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    with socket.socket(socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host.strip("[]"), int(port)))
        except OSError:
            return False
    return True


def free_tcp_endpoint(host: str = LOOPBACK) -> str:
    """A free loopback TCP port, as a zenoh endpoint."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return f"tcp/{host}:{s.getsockname()[1]}"
