"""``stack-fleet replay RUN_DIR``: an animation of a run from its recording (``run.mcap``), without any app.

Reads the MCAP back with the ``mcap`` package, decoding every message with the schema it was written
with (protobuf for the Foxglove types), and draws frame by frame: obstacles (from ``/scene/obstacles``),
the robots at their true poses (``/tf``) and their own estimates (``/tf_estimate``), each robot's scan
(``/robot_<id>/scan``, placed at its true pose), the formation's slots (``/formation/slots``), the comm
graph (``/comm/links``) and the time. Bounded: at most ``max_frames`` frames of ``width`` pixels.
matplotlib and Pillow are imported only here, when a replay is drawn (a robot's core install has neither).
"""

from __future__ import annotations

import bisect
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

from . import viz_messages as vm

LINK_COLOR = {k: tuple(v) for k, v in vm.LINK_COLORS.items()}


class ReplayError(ValueError):
    """No recording to replay, or one that is not ours (one line)."""


def _yaw(q) -> float:
    return 2.0 * math.atan2(q.z, q.w)


@dataclass
class Recording:
    """The series a replay draws, each a list of (time ns, value) in time order."""

    truth: list = field(default_factory=list)  # {rid: (x, y, yaw)}
    estimates: dict = field(default_factory=dict)  # rid -> [(ns, (x, y, yaw))]
    scans: dict = field(default_factory=dict)  # rid -> [(ns, (start_angle, end_angle, ranges))]
    slots: list = field(default_factory=list)  # [(x, y)]
    links: list = field(default_factory=list)  # [(x0, y0, x1, y1, worst)]
    obstacles: list = field(default_factory=list)  # ("circle", x, y, r) | ("box", x, y, hx, hy, yaw)
    radius: dict = field(default_factory=dict)  # rid -> body radius
    range_max: float = math.inf


def _robot_id(frame_id: str) -> int | None:
    name = frame_id.split("/")[0]
    return int(name[6:]) if name.startswith("robot_") and name[6:].isdigit() else None


def _take_scene(rec: Recording, topic: str, ns: int, msg) -> None:
    if topic == vm.TOPICS["obstacles"] and not rec.obstacles:
        for e in msg.entities:
            for c in e.cylinders:
                rec.obstacles.append(("circle", c.pose.position.x, c.pose.position.y, c.size.x / 2))
            for c in e.cubes:
                rec.obstacles.append(("box", c.pose.position.x, c.pose.position.y, c.size.x / 2, c.size.y / 2,
                                      _yaw(c.pose.orientation)))
    elif topic == vm.TOPICS["robots"] and not rec.radius:
        for e in msg.entities:
            if e.id.startswith("robot-") and e.cylinders:
                rec.radius[int(e.id[6:])] = e.cylinders[0].size.x / 2
    elif topic == vm.TOPICS["slots"]:
        rec.slots.append((ns, [(c.pose.position.x, c.pose.position.y) for e in msg.entities for c in e.cylinders]))
    elif topic == vm.TOPICS["links"]:
        rec.links.append((ns, [(ln.points[0].x, ln.points[0].y, ln.points[1].x, ln.points[1].y,
                                {kv.key: kv.value for kv in e.metadata}.get("worst", "delivered"))
                               for e in msg.entities for ln in e.lines]))


def decoder_factories() -> list:
    """Decoders for a recording's two encodings: protobuf (the Foxglove schemas) and JSON (ours)."""
    import json

    from mcap.decoder import DecoderFactory as McapDecoderFactory
    from mcap_protobuf.decoder import DecoderFactory

    class JsonDecoderFactory(McapDecoderFactory):
        def decoder_for(self, message_encoding, schema):
            return (lambda data: json.loads(data)) if message_encoding == "json" else None

    return [DecoderFactory(), JsonDecoderFactory()]


def read_recording(path: Path) -> Recording:
    """Decode what a replay needs from ``run.mcap`` (every message through its schema's decoder)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    rec = Recording()
    wanted = {vm.TOPICS[k] for k in ("tf", "tf_estimate", "obstacles", "robots", "slots", "links")}
    try:
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=decoder_factories())
            summary = reader.get_summary()
            topics = sorted(wanted | {c.topic for c in (summary.channels.values() if summary else ()) if c.topic.endswith("/scan")})
            for _, channel, message, msg in reader.iter_decoded_messages(topics=topics, log_time_order=True):
                topic, ns = channel.topic, message.log_time
                if topic == vm.TOPICS["tf"]:
                    rec.truth.append((ns, {_robot_id(t.child_frame_id): (t.translation.x, t.translation.y, _yaw(t.rotation))
                                           for t in msg.transforms}))
                elif topic == vm.TOPICS["tf_estimate"]:
                    for t in msg.transforms:
                        rec.estimates.setdefault(_robot_id(t.child_frame_id), []).append(
                            (ns, (t.translation.x, t.translation.y, _yaw(t.rotation))))
                elif topic.endswith("/scan"):
                    rec.scans.setdefault(_robot_id(msg.frame_id), []).append((ns, (msg.start_angle, msg.end_angle, list(msg.ranges))))
                elif topic in wanted:
                    _take_scene(rec, topic, ns, msg)
    except (OSError, McapError, ValueError) as e:
        raise ReplayError(f"{path}: not a readable recording: {e}") from None
    if not rec.truth:
        raise ReplayError(f"{path}: no robot poses (/tf) in this recording")
    return rec


def _at(series: list, ns: int):
    """The newest value of a time-ordered [(ns, value)] at or before ``ns`` (None before the first)."""
    i = bisect.bisect_right(series, ns, key=lambda p: p[0]) - 1
    return series[i][1] if i >= 0 else None


def frame_times(rec: Recording, max_frames: int) -> list[int]:
    """At most ``max_frames`` of the recorded steps, evenly spread, first and last included."""
    times = [ns for ns, _ in rec.truth]
    if len(times) <= max_frames:
        return times
    return [times[round(i * (len(times) - 1) / (max_frames - 1))] for i in range(max_frames)]


def _bounds(rec: Recording, aspect: float, margin: float = 2.0) -> tuple[float, float, float, float]:
    """Where the robots went (plus a margin), widened to the picture's height/width ``aspect``."""
    xs = [p[0] for _, d in rec.truth for p in d.values()]
    ys = [p[1] for _, d in rec.truth for p in d.values()]
    x0, x1, y0, y1 = min(xs) - margin, max(xs) + margin, min(ys) - margin, max(ys) + margin
    w, h = max(x1 - x0, (y1 - y0) / aspect), max(y1 - y0, (x1 - x0) * aspect)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    return cx - w / 2, cx + w / 2, cy - h / 2, cy + h / 2


def _scene(ax, rec: Recording):
    """The static obstacles and the artists every frame updates."""
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Circle, Polygon

    for o in rec.obstacles:
        if o[0] == "circle":
            ax.add_patch(Circle(o[1:3], o[3], color="tab:brown", alpha=0.7))
        else:
            _, cx, cy, hx, hy, yaw = o
            c, s = math.cos(yaw), math.sin(yaw)
            ax.add_patch(Polygon([(cx + c * dx - s * dy, cy + s * dx + c * dy)
                                  for dx, dy in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))], color="tab:brown", alpha=0.7))
    ids = sorted(r for r in rec.truth[0][1] if r is not None)
    bodies = {rid: ax.add_patch(Circle((0, 0), rec.radius.get(rid, 0.3), color="tab:blue", alpha=0.8, zorder=4)) for rid in ids}
    art = {
        "bodies": bodies,
        "labels": {rid: ax.text(0, 0, str(rid), color="white", ha="center", va="center", fontsize=7, zorder=6) for rid in ids},
        "heading": ax.add_collection(LineCollection([], colors="white", linewidths=1.2, zorder=5)),
        "links": ax.add_collection(LineCollection([], linewidths=1.0, alpha=0.7, zorder=2)),
        "scan": ax.scatter([], [], s=1.5, color="tab:red", zorder=3),
        "estimates": ax.scatter([], [], s=18, marker="x", color="darkorange", zorder=7, label="estimate"),
        "slots": ax.scatter([], [], s=60, facecolors="none", edgecolors="tab:cyan", linewidths=1.5, zorder=6, label="slot"),
        "trails": {rid: ax.plot([], [], lw=0.8, alpha=0.5, color="tab:blue")[0] for rid in ids},
        "time": ax.text(0.01, 0.98, "", transform=ax.transAxes, va="top", fontsize=9, family="monospace"),
    }
    return art


def _artists(art: dict) -> list:
    """Every artist a frame moves (the values of ``art``, its per-robot dicts flattened)."""
    return [x for v in art.values() for x in (v.values() if isinstance(v, dict) else (v,))]


def _scan_points(rec: Recording, ns: int, poses: dict) -> list[tuple[float, float]]:
    pts = []
    for rid, series in rec.scans.items():
        scan, p = _at(series, ns), poses.get(rid)
        if scan is None or p is None:
            continue
        a0, a1, ranges = scan
        inc = (a1 - a0) / (len(ranges) - 1) if len(ranges) > 1 else 0.0
        for i, r in enumerate(ranges):
            if math.isfinite(r):  # a hit (beams that saw nothing are +inf)
                a = p[2] + a0 + i * inc
                pts.append((p[0] + r * math.cos(a), p[1] + r * math.sin(a)))
    return pts


def _draw(art: dict, rec: Recording, ns: int, t0: int) -> None:
    poses = _at(rec.truth, ns) or {}
    upto = rec.truth[:bisect.bisect_right(rec.truth, ns, key=lambda p: p[0])]
    for rid, line in art["trails"].items():
        line.set_data([d[rid][0] for _, d in upto if rid in d], [d[rid][1] for _, d in upto if rid in d])
    heads = []
    for rid, body in art["bodies"].items():
        if rid in poses:
            x, y, yaw = poses[rid]
            body.center = (x, y)
            art["labels"][rid].set_position((x, y))
            r = body.radius
            heads.append([(x, y), (x + 1.6 * r * math.cos(yaw), y + 1.6 * r * math.sin(yaw))])
    art["heading"].set_segments(heads)
    est = [e[:2] for e in (_at(s, ns) for s in rec.estimates.values()) if e is not None]
    art["estimates"].set_offsets(est or [(math.nan, math.nan)])
    art["scan"].set_offsets(_scan_points(rec, ns, poses) or [(math.nan, math.nan)])
    art["slots"].set_offsets(_at(rec.slots, ns) or [(math.nan, math.nan)])
    links = _at(rec.links, ns) or []
    art["links"].set_segments([[(a, b), (c, d)] for a, b, c, d, _ in links])
    art["links"].set_colors([LINK_COLOR.get(w, (0.5, 0.5, 0.5)) for *_, w in links])
    art["time"].set_text(f"t = {(ns - t0) / 1e9:6.1f} s")


def render_replay(run_dir: str | Path, out: str | Path = "replay.gif", *, max_frames: int = 150, fps: float = 10.0,
                  width: int = 640) -> Path:
    """Draw ``run_dir/run.mcap`` as a GIF (``out`` relative to ``run_dir``); returns its path.
    At most ``max_frames`` frames (evenly spread over the run), ``width`` x 3/4 ``width`` pixels."""
    if max_frames < 1 or width < 64 or not fps > 0:
        raise ReplayError("replay: max_frames must be >= 1, width >= 64 px, fps > 0")
    run_dir = Path(run_dir)
    src = run_dir / "run.mcap" if run_dir.is_dir() else run_dir
    if not src.is_file():
        raise ReplayError(f"{src}: no recording (a run writes run.mcap unless --no-record)")
    rec = read_recording(src)
    target = (run_dir if run_dir.is_dir() else run_dir.parent) / out
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    dpi = 100
    fig, ax = plt.subplots(figsize=(width / dpi, 0.75 * width / dpi), dpi=dpi)
    x0, x1, y0, y1 = _bounds(rec, aspect=0.75)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    art = _scene(ax, rec)
    ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    moving = sorted(_artists(art), key=lambda a: a.get_zorder())
    for a in moving:
        a.set_animated(True)  # left out of the background: the axes, ticks, legend and obstacles are drawn once
    fig.canvas.draw()
    background = fig.canvas.copy_from_bbox(fig.bbox)
    frames = []
    for ns in frame_times(rec, max_frames):
        _draw(art, rec, ns, rec.truth[0][0])
        fig.canvas.restore_region(background)
        for a in moving:  # in z-order, over the background (every one of them above the obstacles)
            ax.draw_artist(a)
        frames.append(Image.frombuffer("RGBA", fig.canvas.get_width_height(), fig.canvas.buffer_rgba()).convert("RGB")
                      .quantize(colors=64, method=Image.Quantize.FASTOCTREE))
    plt.close(fig)
    frames[0].save(target, save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
    return target


def main(argv: list[str] | None = None) -> int:
    """``stack-fleet replay RUN_DIR [--out FILE] [--max-frames N] [--fps F] [--width PX]``: 0, or 2 with one line."""
    import argparse

    ap = argparse.ArgumentParser(prog="stack-fleet replay", description="Animate a run from its run.mcap (a GIF).")
    ap.add_argument("run_dir", type=Path, help="a run's folder (or its run.mcap)")
    ap.add_argument("--out", default="replay.gif", help="GIF to write, relative to RUN_DIR (default replay.gif)")
    ap.add_argument("--max-frames", type=int, default=150)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--width", type=int, default=640, help="pixels (height: 3/4 of it)")
    a = ap.parse_args(argv)
    try:
        path = render_replay(a.run_dir, a.out, max_frames=a.max_frames, fps=a.fps, width=a.width)
    except ReplayError as e:
        print(f"stack-fleet replay: {e}", file=sys.stderr)
        return 2
    print(f"replay: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
