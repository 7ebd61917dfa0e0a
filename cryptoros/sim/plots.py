"""Figures: ground truth beside each robot's belief (paper Figs 5, 6) and sweep curves
(paper Figs 3, 4, 7, 8) with confidence intervals over seeds. matplotlib, Agg."""

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

from cryptoros.sim.world import OCC, UNKNOWN  # noqa: E402


def map_png(mission: Any, path: str | Path) -> Path:
    """Truth, then each robot's belief; unexplored (unknown) cells hatched."""
    robots = list(mission.robots.values())
    n = 1 + len(robots)
    cols = min(n, 5)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3 * cols, 3 * rows), squeeze=False)
    cmap = ListedColormap(["#ffffff", "#303030"])
    truth = mission.world.occupied.astype(int)
    panels = [("ground truth", truth, None)] + [(f"{r.name} ({r.belief.known.__ne__(UNKNOWN).mean():.0%} known)", (r.belief.known == OCC).astype(int), r.belief.known == UNKNOWN) for r in robots]
    for ax in axes.flat:
        ax.axis("off")
    for ax, (title, img, unknown) in zip(axes.flat, panels):
        ax.imshow(img, cmap=cmap, vmin=0, vmax=1, interpolation="nearest")
        if unknown is not None and unknown.any():
            ax.contourf(unknown.astype(float), levels=[0.5, 1.5], colors="none", hatches=["////"])
            ax.contour(unknown.astype(float), levels=[0.5], colors="#888888", linewidths=0.4)
        for b in mission.world.bases:
            ax.plot(b[1], b[0], "s", color="tab:green", ms=5)
        for r in robots:
            ax.plot(r.cell[1], r.cell[0], "o", ms=3, color="tab:red" if unknown is None or r.name not in title else "tab:blue")
        ax.set_title(title, fontsize=8)
    fig.suptitle(f"{mission.world.name}: attacks={','.join(mission.cfg.attacks) or 'none'} security={mission.cfg.security.label}", fontsize=9)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _ci(values: list[float]) -> tuple[float, float]:
    a = np.asarray([v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))], dtype=float)
    if a.size == 0:
        return float("nan"), 0.0
    if a.size == 1:
        return float(a[0]), 0.0
    return float(a.mean()), float(1.96 * a.std(ddof=1) / math.sqrt(a.size))


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
}


def line_plot(rows: list[dict[str, Any]], x: str, y: str, series: str, path: Path, *, title: str, ylabel: str, xlabel: str | None = None) -> Path:
    fig, ax = plt.subplots(figsize=(5, 3.4))
    agg = aggregate(rows, y, (series, x))
    names = sorted({k[0] for k in agg})
    for name in names:
        pts = sorted((k[1], v) for k, v in agg.items() if k[0] == name)
        xs = [p[0] for p in pts]
        ms = np.array([p[1][0] for p in pts])
        es = np.array([p[1][1] for p in pts])
        ax.errorbar(xs, ms, yerr=es, marker="o", capsize=3, label=LABELS.get(str(name), str(name)))
    if all(isinstance(k[1], int) for k in agg):  # robot counts: whole numbers only
        from matplotlib.ticker import MaxNLocator

        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel(xlabel or x)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
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
