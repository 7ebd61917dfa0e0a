"""Sweep: a grid of robots x scenarios x curves x seeds on all cores, CSV + PNG plots.

A *scenario* is a named (attacks, security) pair; the default set reproduces the
paper's comparisons: ``legacy`` (no attack, no security), ``attack1`` / ``defended1``
(impersonation without / with authentication), ``attack2`` / ``sha256-2`` /
``defended2`` (man in the middle without integrity / with the paper's bare digest /
with a keyed MAC), ``eavesdrop`` / ``defended3`` (with AES-128).
"""

from __future__ import annotations

import csv
import itertools
import multiprocessing as mp
import os
from pathlib import Path
from typing import Any, Callable

from cryptoros.sim.scenario import SimConfig, run
from cryptoros.sim.security import SecurityConfig

SCENARIOS: dict[str, tuple[tuple[str, ...], str]] = {
    "legacy": ((), "none"),
    "attack1": (("impersonate",), "none"),
    "defended1": (("impersonate",), "ecdsa"),
    "attack2": (("mitm",), "none"),
    "sha256-2": (("mitm",), "sha256"),
    "defended2": (("mitm",), "hmac"),
    "eavesdrop": (("eavesdrop",), "none"),
    "defended3": (("eavesdrop",), "aes"),
    "secure": ((), "full"),
}

FIELDS = ["scenario", "robots", "curve", "seed", "attacks", "security", "completed", "task_time_s", "end_time_s", "coverage",
          "map_accuracy", "sent", "delivered", "lost", "rejected", "bytes_sent", "energy_j", "energy_per_robot_j", "crypto_cpu_s",
          "eaves_map_share", "eaves_positions_share", "wall_s"]


def _one(job: tuple[str, int, str, int, dict[str, Any]]) -> dict[str, Any]:
    scen, n, curve, seed, extra = job
    attacks, sec = SCENARIOS[scen]
    cfg = SimConfig(robots=n, seed=seed, attacks=attacks, security=SecurityConfig.parse(sec, curve=curve), **extra)
    r = run(cfg)
    o, p = r["outcome"], r["packets"]
    eav = next((a for a in r["attack"].values() if a["kind"] == "eavesdrop"), {})
    return {
        "scenario": scen, "robots": n, "curve": curve, "seed": seed, "attacks": "+".join(attacks) or "none", "security": cfg.security.label,
        "completed": int(o["completed"]), "task_time_s": o["task_time_s"] if o["completed"] else o["end_time_s"], "end_time_s": o["end_time_s"],
        "coverage": o["coverage"], "map_accuracy": o["mean_map_accuracy"], "sent": p["sent_by_honest"], "delivered": p["delivered"],
        "lost": p["lost"], "rejected": p["rejected"], "bytes_sent": p["bytes_sent"], "energy_j": r["energy"]["total_j"],
        "energy_per_robot_j": r["energy"]["mean_per_robot_j"], "crypto_cpu_s": r["crypto"]["cpu_s_total"],
        "eaves_map_share": eav.get("map_share", ""), "eaves_positions_share": eav.get("positions_share", ""), "wall_s": r["wall"]["seconds"],
    }


def jobs(robots: list[int], scenarios: list[str], curves: list[str], seeds: list[int], extra: dict[str, Any]) -> list[tuple]:
    out = []
    for scen, n, curve, seed in itertools.product(scenarios, robots, curves, seeds):
        uses_curve = SCENARIOS[scen][1] not in ("none", "sha256", "hmac", "aes")
        if not uses_curve and curve != curves[0]:
            continue  # the curve only matters when something signs
        out.append((scen, n, curve, seed, extra))
    return out


def sweep(robots: list[int], scenarios: list[str], curves: list[str], seeds: list[int], out: Path, *, workers: int | None = None,
          extra: dict[str, Any] | None = None, progress: Callable[[int, int], None] | None = None) -> list[dict[str, Any]]:
    out.mkdir(parents=True, exist_ok=True)
    todo = jobs(robots, scenarios, curves, seeds, extra or {})
    rows: list[dict[str, Any]] = []
    workers = workers or os.cpu_count() or 1
    if workers == 1:
        for i, j in enumerate(todo):
            rows.append(_one(j))
            if progress:
                progress(i + 1, len(todo))
    else:
        with mp.get_context("spawn").Pool(workers) as pool:
            for i, row in enumerate(pool.imap(_one, todo)):
                rows.append(row)
                if progress:
                    progress(i + 1, len(todo))
    rows.sort(key=lambda r: (r["scenario"], r["robots"], r["curve"], r["seed"]))
    with open(out / "sweep.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS)
        w.writeheader()
        w.writerows(rows)
    return rows


def figures(rows: list[dict[str, Any]], out: Path, prefix: str = "sim-") -> list[Path]:
    from cryptoros.sim import plots

    out.mkdir(parents=True, exist_ok=True)
    made = []
    base_curve = sorted({r["curve"] for r in rows})[0] if rows else "secp256k1"
    one_curve = [r for r in rows if r["curve"] == base_curve or r["security"] in ("none", "sha256", "hmac", "aes128")]

    def sel(*names: str) -> list[dict[str, Any]]:
        return [r for r in one_curve if r["scenario"] in names]

    if sel("legacy", "attack1", "defended1"):
        made.append(plots.line_plot(sel("legacy", "attack1", "defended1"), "robots", "task_time_s", "scenario", out / f"{prefix}task-time-attack1.png",
                                    title="Task time (to coverage target; end time if never) - attack 1 (Fig. 3)", ylabel="seconds"))
        made.append(plots.line_plot(sel("legacy", "attack1", "defended1"), "robots", "coverage", "scenario", out / f"{prefix}coverage-attack1.png",
                                    title="Final true coverage - attack 1 (Fig. 5)", ylabel="fraction of explorable cells"))
        pk = []
        for r in sel("legacy", "attack1"):
            pk.append({**r, "series": f"{r['scenario']} sent", "v": r["sent"]})
            pk.append({**r, "series": f"{r['scenario']} lost", "v": r["lost"]})
        made.append(plots.line_plot(pk, "robots", "v", "series", out / f"{prefix}packets-attack1.png",
                                    title="Packets sent and lost - attack 1 (Fig. 4)", ylabel="packets"))
    if sel("legacy", "attack2", "sha256-2", "defended2"):
        made.append(plots.line_plot(sel("legacy", "attack2", "sha256-2", "defended2"), "robots", "task_time_s", "scenario", out / f"{prefix}task-time-attack2.png",
                                    title="Task time - man in the middle (Fig. 7)", ylabel="seconds"))
    if rows:
        made.append(plots.line_plot(one_curve, "robots", "energy_per_robot_j", "scenario", out / f"{prefix}energy.png",
                                    title="Energy per robot", ylabel="joules"))
    curved = [r for r in rows if r["scenario"] in ("secure", "defended1")]
    if len({r["curve"] for r in curved}) > 1:
        made.append(plots.line_plot(curved, "robots", "task_time_s", "curve", out / f"{prefix}task-time-curves.png",
                                    title="Task time by ECC curve, signed traffic (Fig. 8)", ylabel="seconds"))
        made.append(plots.line_plot(curved, "robots", "crypto_cpu_s", "curve", out / f"{prefix}crypto-cpu-curves.png",
                                    title="Crypto CPU time by curve (team total)", ylabel="seconds"))
    eav = sel("eavesdrop", "defended3")
    if eav:
        made.append(plots.bar_plot(eav, "scenario", "eaves_map_share", out / f"{prefix}eavesdropper.png",
                                   title="Share of the map the eavesdropper reconstructs", ylabel="fraction"))
    return made
