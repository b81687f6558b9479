"""The report's figures (matplotlib, Agg): bytes over time, AUROC over time, final map vs ground truth,
and the server's memory, tile latency and pose-graph bytes over the mission.

matplotlib is the optional extra `gmmap[sim]`: it is imported when a figure is drawn, so that
`gmmap sim` without --report runs without it, and `require_matplotlib` lets --report fail before
the run rather than after it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.sim.report import AurocPoint, MissionWindow

MISSING_MATPLOTLIB = "--report draws its figures with matplotlib, which is not installed: install gmmap[sim]"


def require_matplotlib() -> None:
    """ValueError (which the CLI prints as its message) when matplotlib cannot be imported."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ValueError(MISSING_MATPLOTLIB) from None


def _pyplot():
    """matplotlib.pyplot on the file-only Agg backend (no display on a headless harness)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


STYLES = {
    "wire": ("-", "GMM on the wire"),
    "raw": ("--", "raw scans"),
    "grid": (":", "0.1 m grid deltas"),
    "octomap": ("-.", "OctoMap .bt deltas"),
}


def bytes_over_time(path: Path, per_scan: dict, wire_times: dict) -> None:
    """Cumulative bytes per robot: what went on the wire (measured) against the alternatives."""
    from matplotlib.lines import Line2D

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (robot, series) in enumerate(per_scan.items()):
        colour = colours[i % len(colours)]
        t, sizes = wire_times[robot]
        ax.step(t, np.cumsum(sizes), STYLES["wire"][0], where="post", color=colour)
        order = np.argsort(series["t"])
        for key in ("raw", "grid", "octomap"):
            if key in series:
                ax.step(series["t"][order], np.cumsum(series[key][order]), STYLES[key][0], where="post", color=colour)
    handles = [Line2D([], [], color=colours[i % len(colours)], label=robot) for i, robot in enumerate(per_scan)]
    handles += [
        Line2D([], [], color="k", linestyle=style, label=label)
        for key, (style, label) in STYLES.items()
        if key == "wire" or any(key in s for s in per_scan.values())
    ]
    ax.set(yscale="log", xlabel="time since the first scan (s)", ylabel="cumulative bytes", title="Bytes per robot")
    ax.legend(handles=handles, fontsize=8, ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def auroc_over_time(path: Path, timeline: list[AurocPoint], corrections: list[float]) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 4))
    t = [row.t_s for row in timeline]
    for key, label in (
        ("served", "served map (pose-graph updates applied)"),
        ("published_estimates", "published estimates (updates withheld)"),
        ("odometry", "odometry only (no loop closure)"),
    ):
        values = [getattr(row, key) for row in timeline]
        ax.plot(t, [np.nan if v is None else v for v in values], "o-", ms=3, label=label)
    for i, c in enumerate(corrections):
        ax.axvline(c, color="grey", lw=0.6, alpha=0.5, label="pose-graph update" if i == 0 else None)
    ax.set(
        xlabel="time since the first scan (s)", ylabel="AUROC at 0.1 m vs ground truth", title="Map quality over time"
    )
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def map_vs_truth(path: Path, maps: dict, grid, z: float | None) -> None:
    """Odometry-only map, served map and ground truth side by side; 3D: the horizontal slice at z."""

    def plane(a):
        if a.ndim == 2:
            return a
        return a[int(np.clip((z - grid.origin[2]) // grid.resolution, 0, a.shape[0] - 1))]

    truth = np.where(maps["observed"], maps["truth"].astype(float), 0.5)
    panels = [
        ("odometry only (before correction)", maps["odometry"]),
        ("served (after correction)", maps["served"]),
        ("ground truth (observed cells)", truth),
    ]
    extent = [grid.origin[0], grid.upper[0], grid.origin[1], grid.upper[1]]
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6 * (extent[3] - extent[2]) / (extent[1] - extent[0]) + 0.8))
    for ax, (title, a) in zip(axes, panels):
        ax.imshow(plane(a), cmap="gray_r", vmin=0, vmax=1, origin="lower", extent=extent, interpolation="nearest")
        ax.set(title=title + ("" if z is None else f", z = {z:.1f} m"), xlabel="x (m)", ylabel="y (m)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def over_mission_time(path: Path, windows: list[MissionWindow]) -> None:
    """What must flatten over a long mission, against simulated time: the server's memory, the
    tile latency (p99 per window) and the pose-graph bytes per window beside the scan bytes."""
    plt = _pyplot()
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    t = [w.mission_s for w in windows]
    rss = [np.nan if w.server_rss_mb is None else w.server_rss_mb for w in windows]
    p99 = [np.nan if w.tile_latency_p99_s is None else w.tile_latency_p99_s for w in windows]
    axes[0].plot(t, rss, "-", color="k")
    axes[0].set(ylabel="resident memory (MiB)", title="Map server over the mission", ylim=(0, None))
    axes[1].plot(t, p99, "-", color="k")
    axes[1].set(ylabel="tile latency p99 (s)", ylim=(0, None))
    axes[2].plot(t, [w.scan_payload_bytes / 1e3 for w in windows], "-", color="k", label="scans")
    axes[2].plot(t, [w.pose_payload_bytes / 1e3 for w in windows], "--", color="k", label="pose-graph updates")
    axes[2].set(xlabel="mission time (simulated s)", ylabel="payload per window (kB)", ylim=(0, None))
    axes[2].legend(loc="upper left", frameon=False)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
