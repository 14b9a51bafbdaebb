"""What a changed replay leaves to look at: a plot (recorded vs replayed v, w and the estimate) and an MCAP with
both, to open in Foxglove / Lichtblick beside the original recording (the same sim or wall times)."""

from __future__ import annotations

from pathlib import Path

from .run import Result


def plot(res: Result, path: Path, title: str) -> Path:
    """``path`` (PNG): v and w over time, recorded and replayed, the first divergence marked; the estimate's path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [r.t for r in res.rows]
    fig = plt.figure(figsize=(11, 6.5))
    grid = fig.add_gridspec(2, 2, width_ratios=(1.6, 1))
    axes = [fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[1, 0])]
    for ax, what, unit in zip(axes, ("v", "w"), ("m/s", "rad/s")):
        ax.plot(t, [getattr(r.recorded, what) for r in res.rows], label="recorded", color="tab:blue", lw=1.6)
        ax.plot(t, [getattr(r.replayed, what) for r in res.rows], label="replayed", color="tab:orange", lw=1.2, ls="--")
        ax.set_ylabel(f"{what} [{unit}]")
        ax.grid(alpha=0.3)
        if res.first is not None:
            ax.axvline(res.first.t, color="tab:red", lw=1, alpha=0.8, label=f"first divergence (step {res.first.step})")
    axes[0].legend(loc="best", fontsize=8)
    axes[1].set_xlabel("run time [s]")
    ax = fig.add_subplot(grid[:, 1])
    ax.plot([r.recorded.pose[0] for r in res.rows], [r.recorded.pose[1] for r in res.rows], color="tab:blue",
            label="recorded estimate")
    ax.plot([r.replayed.pose[0] for r in res.rows], [r.replayed.pose[1] for r in res.rows], color="tab:orange",
            ls="--", label="replayed estimate")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.text(0.02, 0.02, "open-loop: the inputs are the recorded robot's", transform=ax.transAxes, fontsize=7,
            color="0.4")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_mcap(res: Result, path: Path) -> Path:
    """``path``: per step, ``/robot_<id>/{recorded,replayed}/cmd_vel`` (JSON) and ``.../estimate`` (PoseInFrame), and
    a ``/replay/events`` line at the first divergence, each at its record's log time in the original."""
    import foxglove
    from foxglove import Channel, Context
    from foxglove.channels import LogChannel, PoseInFrameChannel
    from foxglove.messages import Log, LogLevel

    from ..viz import messages as vm

    ctx = Context()
    rid = res.robot
    writer = foxglove.open_mcap(path, allow_overwrite=True, context=ctx)
    cmd = {k: Channel(f"/robot_{rid}/{k}/cmd_vel", schema=vm.JSON_SCHEMAS["cmd_vel"], message_encoding="json",
                      context=ctx) for k in ("recorded", "replayed")}
    est = {k: PoseInFrameChannel(f"/robot_{rid}/{k}/estimate", context=ctx) for k in ("recorded", "replayed")}
    events = LogChannel("/replay/events", context=ctx)
    try:
        for row in res.rows:
            ns = row.ns
            for k, o in (("recorded", row.recorded), ("replayed", row.replayed)):
                cmd[k].log({"id": rid, "step": row.step, "stamp": ns / 1e9, "v": o.v, "w": o.w}, log_time=ns)
                est[k].log(vm.pose_in_world(o.pose[0], o.pose[1], o.pose[2], ns), log_time=ns)
            if row is res.first:
                events.log(Log(timestamp=vm.ts(ns), level=LogLevel.Warning, name="replay", file="", line=0,
                               message=f"robot {rid}: first divergence at step {row.step}"), log_time=ns)
    finally:
        writer.close()
    return path
