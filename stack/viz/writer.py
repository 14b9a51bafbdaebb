"""One recording: an MCAP file and/or a live server (Foxglove WebSocket protocol), both sinks of one Foxglove
SDK context, fed by one writer thread from a bounded queue.

Whoever produces samples (Zenoh callbacks, a control loop) only calls :meth:`QueuedWriter.put`: it never
blocks; a sample that finds the queue full is dropped and counted. The writer thread hands each sample to
the subclass's :meth:`QueuedWriter.handle`, which builds Foxglove messages (:mod:`.messages`) and
:meth:`QueuedWriter.write`\\ s them. The fleet's recorder (``stack.fleet.record``) and a robot's own view
(``stack.agents.view``) are the two subclasses.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import foxglove
import msgspec
from foxglove import Capability, Context
from foxglove.mcap import MCAPCompression, MCAPWriteOptions

from . import RecorderError
from .endpoint import parse_viz_endpoint

log = logging.getLogger("stack.record")

REFUSED_HINT = ("the live server speaks the foxglove.sdk.v1 WebSocket subprotocol (foxglove-sdk 0.30); a viewer that "
                "offers only foxglove.websocket.v1 (older Foxglove and Lichtblick releases) is refused: see "
                "docs/visualisation.md, 'Which viewers connect'")


class _RefusedHint(logging.Filter):
    """The SDK's server logs a refused client as "handshake failed" and no more: say why, on the same line."""

    def filter(self, record: logging.LogRecord) -> bool:
        if "handshake failed" in record.getMessage() and REFUSED_HINT not in record.getMessage():
            record.msg, record.args = f"{record.getMessage()}: {REFUSED_HINT}", ()
        return True


def install_refused_hint() -> None:
    """Once per process: the hint on the SDK server's logger."""
    server_log = logging.getLogger("foxglove.websocket.server")
    if not any(isinstance(f, _RefusedHint) for f in server_log.filters):
        server_log.addFilter(_RefusedHint())


COMPRESSION = {"zstd": MCAPCompression.Zstd, "lz4": MCAPCompression.Lz4, "none": None}
_STOP = object()
_JSON = msgspec.json.Encoder()


@dataclass
class SinkConfig:
    """Where one recording goes and how much it may hold back."""

    out: Path | None = None
    """The MCAP file to write (e.g. ``runs/x/run.mcap``); None: live view only."""
    viz: str | None = None
    """Live server endpoint ``tcp/HOST:PORT`` (see :func:`.endpoint.parse_viz_endpoint`); None: no live server."""
    allow_remote: bool = False
    """Let the live server listen off loopback."""
    queue_size: int = 20_000
    """Samples waiting for the writer thread at most; past that, new ones are dropped and counted."""
    compression: str = "zstd"
    """MCAP chunk compression: zstd, lz4 or none."""
    batch_s: float = 0.02
    """The writer thread sleeps this long after each batch (what is queued meanwhile waits, up to ``queue_size``)."""

    def __post_init__(self) -> None:
        if self.compression not in COMPRESSION:
            raise ValueError(f"recorder: compression {self.compression!r}: expected one of {', '.join(COMPRESSION)}")
        if self.queue_size < 1:
            raise ValueError("recorder: queue_size must be >= 1")
        if not 0 <= self.batch_s <= 1:
            raise ValueError(f"recorder: batch_s must be in [0, 1] s, got {self.batch_s}")
        if self.viz is not None:
            parse_viz_endpoint(self.viz, self.allow_remote)


class QueuedWriter:
    """The sinks, the queue and the writer thread; subclasses make the channels and handle the samples."""

    def __init__(self, cfg: SinkConfig, server_name: str):
        self.cfg, self.server_name = cfg, server_name
        self.dropped = 0  # samples that found the queue full
        self.malformed = 0  # samples that could not be recorded
        self.counts: dict[str, int] = {}  # messages written per topic
        self.last_ns = 0  # the newest time written
        self._q: queue.Queue = queue.Queue(maxsize=cfg.queue_size)
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._writer = self._server = self._ctx = None
        self._cpu0 = 0.0

    # --- what subclasses provide -------------------------------------------------------------
    def open_channels(self, ctx: Context) -> None:
        """Create every channel on ``ctx`` (in a fixed order: their ids in the file)."""
        raise NotImplementedError

    def handle(self, *item) -> None:
        """One queued sample, on the writer thread."""
        raise NotImplementedError

    def finish(self) -> None:
        """After the last sample, on the writer thread: closing events, metadata; close the channels."""

    # --- life cycle ----------------------------------------------------------------------------
    def open(self) -> None:
        """Open the file and/or the server, the channels, and start the writer thread (RecorderError: one line)."""
        ctx = self._ctx = Context()  # kept: channels of a context that is gone are closed
        try:
            if self.cfg.out is not None:
                self.cfg.out.parent.mkdir(parents=True, exist_ok=True)
                opts = MCAPWriteOptions(compression=COMPRESSION[self.cfg.compression])
                self._writer = foxglove.open_mcap(self.cfg.out, allow_overwrite=True, context=ctx, writer_options=opts)
            if self.cfg.viz is not None:
                host, port = parse_viz_endpoint(self.cfg.viz, self.cfg.allow_remote)
                install_refused_hint()
                self._server = foxglove.start_server(name=self.server_name, host=host, port=port,
                                                     capabilities=[Capability.Time], context=ctx)
        except (RuntimeError, OSError) as e:
            self._close_sinks()
            raise RecorderError(f"recorder: {str(e).splitlines()[0]}") from None
        self.open_channels(ctx)
        self._thread = threading.Thread(target=self._write_loop, name="recorder", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Write what is queued and the closing records; close the file and the server."""
        if self._thread is not None:
            self._q.put(_STOP)  # blocks only if full: the writer is draining it
            self._thread.join()
            self._thread = None
        self._close_sinks()

    @property
    def port(self) -> int | None:
        """The live server's port (useful with port 0), None without one."""
        return self._server.port if self._server is not None else None

    def _close_sinks(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        if self._server is not None:
            self._server.stop()
            self._server = None

    # --- producers: never block ------------------------------------------------------------------
    def put(self, item) -> bool:
        """Queue a sample for the writer thread; False (and counted) if the queue is full."""
        try:
            self._q.put_nowait(item)
            return True
        except queue.Full:
            with self._lock:
                self.dropped += 1
            return False

    def dropped_now(self) -> int:
        with self._lock:
            return self.dropped

    # --- the writer thread --------------------------------------------------------------------------
    def _write_loop(self) -> None:
        """Wake at most every ``cfg.batch_s``, take everything queued by then: a handful of wake-ups a second, not
        one per sample (each would be a context switch on a core the fleet's processes are waiting for)."""
        self._cpu0 = time.thread_time()
        while True:
            batch = [self._q.get()]
            while True:
                try:
                    batch.append(self._q.get_nowait())
                except queue.Empty:
                    break
            for item in batch:
                if item is _STOP:
                    self.finish()
                    return
                self._handle_one(item)
            time.sleep(self.cfg.batch_s)

    def _handle_one(self, item) -> None:
        try:
            self.handle(*item)
        except Exception:  # noqa: BLE001 - one bad sample must not end the recording
            log.exception("recorder: a %s sample not recorded", item[0])
            self.malformed += 1

    def cpu_s(self) -> float:
        """CPU seconds the writer thread has spent so far (call it on the writer thread: :meth:`finish`)."""
        return time.thread_time() - self._cpu0

    def write(self, channel, topic: str, msg, ns: int) -> None:
        """Log ``msg`` (a Foxglove message, or a dict for a JSON channel) at ``ns`` and count it."""
        channel.log(_JSON.encode(msg) if isinstance(msg, dict) else msg, log_time=ns)
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.last_ns = max(self.last_ns, ns)

    def broadcast_time(self, ns: int) -> None:
        """Live clients follow the recording's clock (sim time in lock-step)."""
        if self._server is not None:
            self._server.broadcast_time(ns)

    def write_metadata(self, name: str, data: dict[str, str]) -> None:
        if self._writer is not None:
            self._writer.write_metadata(name, data)

    def attach(self, name: str, media_type: str, data: bytes, create_ns: int) -> None:
        if self._writer is not None:
            self._writer.attach(log_time=0, create_time=create_ns, name=name, media_type=media_type, data=data)
