"""Figures: ground truth beside each robot's belief (paper Figs 5, 6) and sweep curves
(paper Figs 3, 4, 7, 8) with Student's t 95% intervals over seeds, and the energy
spent by component. matplotlib, Agg."""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from cryptoros.sim.world import OCC, UNKNOWN  # noqa: E402


def map_png(mission: Any, path: str | Path) -> Path:
    """Truth, then each robot's belief. Hatched: on the truth, explorable cells no robot
    ever scanned (paper Fig. 5's unexplored area); on a belief, cells the robot does not
    know. A robot fooled by a false map believes cells known that nobody scanned."""
    robots = list(mission.robots.values())
    n = 1 + len(robots)
    cols = min(n, 5)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3 * cols, 3 * rows), squeeze=False)
    cmap = ListedColormap(["#ffffff", "#303030"])
    truth = mission.world.occupied.astype(int)
    unscanned = mission.world.explorable() & ~mission.observed
    panels = [(f"ground truth (team scanned {mission.coverage():.0%})", truth, unscanned)] + [(f"{r.name} ({r.belief.known.__ne__(UNKNOWN).mean():.0%} known)", (r.belief.known == OCC).astype(int), r.belief.known == UNKNOWN) for r in robots]
    for ax in axes.flat:
        ax.axis("off")
    for ax, (title, img, unknown) in zip(axes.flat, panels):
        ax.imshow(img, cmap=cmap, vmin=0, vmax=1, interpolation="nearest")
        ax.add_patch(Rectangle((-0.5, -0.5), img.shape[1], img.shape[0], fill=False, lw=0.6, ec="#999999", clip_on=False))  # the grid's edge
        if unknown is not None and unknown.any():
            ax.contourf(unknown.astype(float), levels=[0.5, 1.5], colors="none", hatches=["////"])
            ax.contour(unknown.astype(float), levels=[0.5], colors="#888888", linewidths=0.4)
        for b in mission.world.bases:
            ax.plot(b[1], b[0], "s", color="tab:green", ms=5)
        for r in robots:
            ax.plot(r.cell[1], r.cell[0], "o", ms=3, color="tab:blue" if title.startswith(f"{r.name} ") else "tab:red")
        ax.set_title(title, fontsize=8)
    fig.suptitle(f"{mission.world.name}: attacks={','.join(mission.cfg.attacks) or 'none'} security={mission.cfg.security.label}", fontsize=9)
    fig.legend(handles=_map_legend(), loc="lower center", ncol=5, fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _map_legend() -> list:
    """What the marks on a map panel mean (one legend for the figure)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    return [Patch(facecolor="#303030", label="obstacle"),
            Patch(facecolor="white", edgecolor="#888888", hatch="////", label="never scanned / unknown"),
            Line2D([], [], marker="s", ls="", color="tab:green", label="base"),
            Line2D([], [], marker="o", ls="", color="tab:blue", label="this robot"),
            Line2D([], [], marker="o", ls="", color="tab:red", label="other robots")]


def t_interval(values: list[float], confidence: float = 0.95) -> tuple[float, float]:
    """Mean and half-width of the Student's t interval (n - 1 degrees of freedom): with
    few seeds the normal 1.96 is far too narrow (n = 3: t = 4.30)."""
    from scipy import stats

    a = np.asarray([v for v in values if v is not None and v != "" and not (isinstance(v, float) and math.isnan(v))], dtype=float)
    if a.size == 0:
        return float("nan"), 0.0
    if a.size == 1:
        return float(a[0]), 0.0
    t = float(stats.t.ppf(0.5 + confidence / 2, a.size - 1))
    return float(a.mean()), t * float(a.std(ddof=1)) / math.sqrt(a.size)


_ci = t_interval


def aggregate(rows: list[dict[str, Any]], key: str, group: tuple[str, ...]) -> dict[tuple, tuple[float, float, int]]:
    g: dict[tuple, list] = defaultdict(list)
    for r in rows:
        g[tuple(r[k] for k in group)].append(r[key])
    return {k: (*_ci(v), len(v)) for k, v in sorted(g.items())}


#: Legend names of the sweep's scenarios.
LABELS = {
    "legacy": "no attack, no security",
    "attack1": "impersonation, no security",
    "defended1": "impersonation, ECDSA",
    "attack2": "man in the middle, no integrity",
    "sha256-2": "man in the middle, bare SHA-256",
    "defended2": "man in the middle, HMAC",
    "eavesdrop": "eavesdropper, no security",
    "defended3": "eavesdropper, AES-128",
    "secure": "no attack, full security",
    "secure-rsa": "no attack, full security, RSA key negotiation",
    "battery": "3 kJ batteries, one robot idle at the base",
}


def line_plot(rows: list[dict[str, Any]], x: str, y: str, series: str, path: Path, *, title: str, ylabel: str, xlabel: str | None = None) -> Path:
    fig, ax = plt.subplots(figsize=(5, 3.4))
    _series_on(ax, rows, x, y, series)
    ax.set_xlabel(xlabel or x)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _series_on(ax, rows: list[dict[str, Any]], x: str, y: str, series: str) -> None:
    """Each series of ``rows`` on ``ax``: means over seeds with their t intervals."""
    agg = aggregate(rows, y, (series, x))
    for name in sorted({k[0] for k in agg}):
        pts = sorted((k[1], v) for k, v in agg.items() if k[0] == name)
        ax.errorbar([p[0] for p in pts], [p[1][0] for p in pts], yerr=[p[1][1] for p in pts], marker="o", capsize=3,
                    label=LABELS.get(str(name), str(name)))
    if all(isinstance(k[1], int) for k in agg):  # robot counts: whole numbers only
        from matplotlib.ticker import MaxNLocator

        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.grid(alpha=0.3)


def small_multiples(panels: list[tuple[str, list[dict[str, Any]]]], x: str, y: str, series: str, path: Path, *,
                    title: str, ylabel: str, xlabel: str | None = None, sharey: bool = True,
                    log_panels: frozenset[str] = frozenset()) -> Path:
    """One panel per (panel title, rows), the same series in each: a figure a reader
    compares across panels instead of untangling nine lines in one. A panel named in
    ``log_panels`` gets a symmetric-log y axis (counts near zero stay visible)."""
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.4), sharey=sharey, squeeze=False)
    for ax, (name, rows) in zip(axes[0], panels):
        _series_on(ax, rows, x, y, series)
        if name in log_panels:
            ax.set_yscale("symlog", linthresh=1)
        ax.set_title(name, fontsize=8)
        ax.set_xlabel(xlabel or x)
    axes[0][0].set_ylabel(ylabel)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 4), fontsize=7, frameon=False)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def bar_plot(rows: list[dict[str, Any]], x: str, y: str, path: Path, *, title: str, ylabel: str) -> Path:
    fig, ax = plt.subplots(figsize=(5, 3.4))
    agg = aggregate(rows, y, (x,))
    labels = [str(k[0]) for k in agg]
    ms = [v[0] for v in agg.values()]
    es = [v[1] for v in agg.values()]
    ax.bar(labels, ms, yerr=es, capsize=4, color="tab:blue", alpha=0.8)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.tick_params(axis="x", labelsize=7, rotation=20)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


#: Energy components of the sweep CSV, in stacking order, with their legend names.
ENERGY_COMPONENTS = [("energy_base_j", "base load: computer, lidar (6 W)"), ("energy_motion_j", "motion"),
                     ("energy_radio_j", "radio tx + rx"), ("energy_crypto_j", "crypto CPU")]


def energy_bars(rows: list[dict[str, Any]], path: Path, *, title: str) -> Path:
    """Mean team energy per scenario, stacked by component, with the crypto share
    written on each bar (it is too thin to see at this scale)."""
    scen = sorted({r["scenario"] for r in rows}, key=lambda s: list(LABELS).index(s) if s in LABELS else 99)
    fig, ax = plt.subplots(figsize=(7, 3.8))
    bottom = np.zeros(len(scen))
    means = {}
    for col, label in ENERGY_COMPONENTS:
        m = np.array([t_interval([r[col] for r in rows if r["scenario"] == s])[0] for s in scen]) / 1000.0
        means[col] = m
        ax.bar(scen, m, bottom=bottom, label=label)
        bottom += m
    for i, s in enumerate(scen):
        share = means["energy_crypto_j"][i] / bottom[i] if bottom[i] else 0.0
        ax.text(i, bottom[i], f"crypto {share:.2%}", ha="center", va="bottom", fontsize=6)
    ax.set_ylabel("team energy (kJ)")
    ax.set_title(title, fontsize=9)
    ax.tick_params(axis="x", labelsize=7, rotation=25)
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
