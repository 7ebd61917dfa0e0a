"""Sweep: a grid of robots x scenarios x curves x seeds on all cores, CSV + PNG plots.

A *scenario* is a named (attacks, security) pair; the default set reproduces the
paper's comparisons: ``legacy`` (no attack, no security), ``attack1`` / ``defended1``
(impersonation without / with authentication), ``attack2`` / ``sha256-2`` /
``defended2`` (man in the middle without integrity / with the paper's bare digest /
with a keyed MAC), ``eavesdrop`` / ``defended3`` (with AES-128), ``secure`` (ECDSA,
HMAC, AES-128, no attack) and ``secure-rsa`` (the same with the paper's RSA key
negotiation: session keys RSA-OAEP-wrapped to each neighbour). ``battery`` changes the
mission rather than the security: small batteries (3 kJ) and one robot idle at the base,
so robots go home, recharge, resume and recruit (columns ``returns_home``, ``charges``,
``recruit_requests``, ``recruit_successes``).

Statistics: every figure's error bar is a Student's t 95% interval over seeds, and
``paired.csv`` compares scenarios seed by seed (same seed = same building and start).
"""

from __future__ import annotations

import csv
import itertools
import multiprocessing as mp
import os
from pathlib import Path
from typing import Any, Callable

from cryptoros.sim.scenario import Mission, SimConfig
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
    "secure-rsa": ((), "rsa,hmac,aes"),
    "battery": ((), "none"),
}

#: Mission settings a scenario changes besides attacks and security.
SCENARIO_CONFIG: dict[str, dict[str, Any]] = {
    "battery": {"battery_j": 3000.0, "idle": 1},
}

#: Scenarios whose frames are signed: they run once per curve (paper Fig. 8).
SIGNED_SCENARIOS = ("defended1", "secure", "secure-rsa")

#: Scenario pairs compared seed by seed in paired.csv: (baseline, treatment).
PAIRS = [("legacy", "attack1"), ("attack1", "defended1"), ("legacy", "attack2"), ("attack2", "sha256-2"), ("attack2", "defended2"),
         ("legacy", "defended2"), ("legacy", "secure"), ("secure", "secure-rsa"), ("legacy", "battery")]

FIELDS = ["scenario", "robots", "curve", "seed", "attacks", "security", "completed", "task_time_s", "end_time_s", "coverage",
          "map_accuracy", "sent", "delivered", "lost", "rejected", "bytes_sent", "energy_j", "energy_per_robot_j", "crypto_cpu_s",
          "energy_motion_j", "energy_base_j", "energy_radio_j", "energy_crypto_j", "returns_home", "charges", "resumed",
          "recruit_requests", "recruit_successes", "eaves_map_share", "eaves_positions_share", "wall_s"]

#: Battery components (``Battery.used`` keys) summed into each energy column.
ENERGY_PARTS = {"energy_motion_j": ("move",), "energy_base_j": ("idle",), "energy_radio_j": ("tx", "rx"), "energy_crypto_j": ("crypto",)}


def _one(job: tuple[str, int, str, int, dict[str, Any], str]) -> dict[str, Any]:
    scen, n, curve, seed, extra, map_png = job
    attacks, sec = SCENARIOS[scen]
    over = dict(SCENARIO_CONFIG.get(scen, {}))
    if "idle" in over:
        over["idle"] = min(over["idle"], n - 1)  # at least one robot explores
    cfg = SimConfig(robots=n, seed=seed, attacks=attacks, security=SecurityConfig.parse(sec, curve=curve), **{**extra, **over})
    mission = Mission(cfg)
    r = mission.run()
    if map_png:
        from cryptoros.sim.plots import map_png as draw

        draw(mission, map_png)
    o, p, rc = r["outcome"], r["packets"], r["recruit"]
    eav = next((a for a in r["attack"].values() if a["kind"] == "eavesdrop"), {})
    parts = {col: round(sum(rb["energy_by_kind_j"][k] for rb in r["robots"].values() for k in kinds), 3) for col, kinds in ENERGY_PARTS.items()}
    return {
        "scenario": scen, "robots": n, "curve": curve, "seed": seed, "attacks": "+".join(attacks) or "none", "security": cfg.security.label,
        "completed": int(o["completed"]), "task_time_s": o["task_time_s"] if o["completed"] else o["end_time_s"], "end_time_s": o["end_time_s"],
        "coverage": o["coverage"], "map_accuracy": o["mean_map_accuracy"], "sent": p["sent_by_honest"], "delivered": p["delivered"],
        "lost": p["lost"], "rejected": p["rejected"], "bytes_sent": p["bytes_sent"], "energy_j": r["energy"]["total_j"],
        "energy_per_robot_j": r["energy"]["mean_per_robot_j"], "crypto_cpu_s": r["crypto"]["cpu_s_total"], **parts,
        "returns_home": rc["returns_home"], "charges": rc["charges"], "resumed": rc["resumed"], "recruit_requests": rc["requests"],
        "recruit_successes": rc["recruited"],
        "eaves_map_share": eav.get("map_share", ""), "eaves_positions_share": eav.get("positions_share", ""), "wall_s": r["wall"]["seconds"],
    }


def jobs(robots: list[int], scenarios: list[str], curves: list[str], seeds: list[int], extra: dict[str, Any], maps: Path | None = None) -> list[tuple]:
    """One job per mission; with ``maps``, the first seed's mission of each scenario at
    the largest robot count (first curve) also draws its map (paper Figs 5-6)."""
    out = []
    for scen, n, curve, seed in itertools.product(scenarios, robots, curves, seeds):
        uses_curve = SCENARIOS[scen][1] not in ("none", "sha256", "hmac", "aes")
        if not uses_curve and curve != curves[0]:
            continue  # the curve only matters when something signs
        png = ""
        if maps is not None and seed == seeds[0] and n == max(robots) and curve == curves[0]:
            png = str(maps / f"map-{scen}-{n}robots-seed{seed}.png")
        out.append((scen, n, curve, seed, extra, png))
    return out


def sweep(robots: list[int], scenarios: list[str], curves: list[str], seeds: list[int], out: Path, *, workers: int | None = None,
          extra: dict[str, Any] | None = None, progress: Callable[[int, int], None] | None = None, maps: bool = True) -> list[dict[str, Any]]:
    """Run the grid; write ``sweep.csv``, ``paired.csv`` and (``maps``) ``maps/*.png``."""
    out.mkdir(parents=True, exist_ok=True)
    if maps:
        (out / "maps").mkdir(exist_ok=True)
    todo = jobs(robots, scenarios, curves, seeds, extra or {}, out / "maps" if maps else None)
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
    write_paired(rows, out / "paired.csv")
    return rows


PAIRED_METRICS = ["task_time_s", "coverage", "sent", "lost", "energy_j", "crypto_cpu_s"]
PAIRED_FIELDS = ["baseline", "treatment", "robots", "curve", "metric", "n", "mean_baseline", "mean_treatment", "mean_diff", "ci95_low", "ci95_high", "p_value"]


def paired(rows: list[dict[str, Any]], pairs: list[tuple[str, str]] = PAIRS, metrics: list[str] = PAIRED_METRICS) -> list[dict[str, Any]]:
    """Treatment minus baseline, seed by seed (same seed: same building, same starts),
    per robot count and curve: mean difference, its Student's t 95% interval and the
    paired t-test p-value. A scenario without signatures is matched to every curve."""
    from cryptoros.sim.plots import t_interval

    from scipy import stats

    by: dict[tuple, dict[str, dict[str, Any]]] = {}
    for r in rows:
        by.setdefault((r["scenario"], r["robots"], r["seed"]), {})[r["curve"]] = r
    curves = sorted({r["curve"] for r in rows})
    seeds = sorted({r["seed"] for r in rows})

    def pick(scen: str, n: int, curve: str, seed: int) -> dict[str, Any] | None:
        runs = by.get((scen, n, seed), {})
        if curve in runs:
            return runs[curve]
        return next(iter(runs.values())) if len(runs) == 1 else None  # a scenario that signs nothing ran once

    out = []

    def compare(base: str, treat: str, n: Any, curve: str, matched: list[tuple[dict[str, Any], dict[str, Any]]]) -> None:
        for m in metrics:
            a = [float(x[m]) for x, _ in matched]
            b = [float(y[m]) for _, y in matched]
            d = [y - x for x, y in zip(a, b)]
            mean, half = t_interval(d)
            p = float(stats.ttest_rel(b, a).pvalue) if any(d) else 1.0
            out.append({"baseline": base, "treatment": treat, "robots": n, "curve": curve, "metric": m, "n": len(d),
                        "mean_baseline": round(sum(a) / len(a), 4), "mean_treatment": round(sum(b) / len(b), 4),
                        "mean_diff": round(mean, 4), "ci95_low": round(mean - half, 4), "ci95_high": round(mean + half, 4),
                        "p_value": round(p, 6) if p == p else ""})

    for base, treat in pairs:
        for n in sorted({r["robots"] for r in rows}):
            for curve in curves:
                matched = [(pick(base, n, curve, s), pick(treat, n, curve, s)) for s in seeds]
                matched = [(a, b) for a, b in matched if a is not None and b is not None]
                if len(matched) < 2 or all(a["curve"] != curve and b["curve"] != curve for a, b in matched):
                    continue  # neither side signs: its one row per robot count is under its own curve
                compare(base, treat, n, curve, matched)
    # Fig. 8 seed by seed: each signed scenario under each curve against its first curve
    for scen in SIGNED_SCENARIOS:
        for n in sorted({r["robots"] for r in rows}):
            for curve in curves[1:]:
                matched = [(by.get((scen, n, s), {}).get(curves[0]), by.get((scen, n, s), {}).get(curve)) for s in seeds]
                matched = [(a, b) for a, b in matched if a is not None and b is not None]
                if len(matched) >= 2:
                    compare(f"{scen} {curves[0]}", f"{scen} {curve}", n, curve, matched)
    return out


def write_paired(rows: list[dict[str, Any]], path: Path) -> list[dict[str, Any]]:
    out = paired(rows)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=PAIRED_FIELDS)
        w.writeheader()
        w.writerows(out)
    return out


def curve_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows of Fig. 8, each labelled with its series: every (scenario, curve) pair
    is its own series, so scenarios with different traffic are never averaged together."""
    return [{**r, "series": f"{r['scenario']} {r['curve']}"} for r in rows if r["scenario"] in SIGNED_SCENARIOS]


def figures(rows: list[dict[str, Any]], out: Path, prefix: str = "sim-") -> list[Path]:
    from cryptoros.sim import plots

    out.mkdir(parents=True, exist_ok=True)
    made = []
    # the curve the text quotes (secp256k1) where the sweep has it, else the first
    curves = sorted({r["curve"] for r in rows})
    base_curve = "secp256k1" if "secp256k1" in curves or not curves else curves[0]
    one_curve = [r for r in rows if r["curve"] == base_curve or r["security"] in ("none", "sha256", "hmac", "aes128")]

    def sel(*names: str) -> list[dict[str, Any]]:
        return [r for r in one_curve if r["scenario"] in names]

    if sel("attack1", "defended1"):
        made.append(plots.line_plot(sel("legacy", "attack1", "defended1"), "robots", "task_time_s", "scenario", out / f"{prefix}task-time-attack1.png",
                                    title="Task time (to coverage target; end time if never) - attack 1 (Fig. 3)", ylabel="seconds"))
        made.append(plots.line_plot(sel("legacy", "attack1", "defended1"), "robots", "coverage", "scenario", out / f"{prefix}coverage-attack1.png",
                                    title="Final true coverage - attack 1 (Fig. 5)", ylabel="fraction of explorable cells"))
        # sent and lost apart: losses are tens where sends are thousands, so on one linear
        # axis the lost line lies flat on zero
        pk = sel("legacy", "attack1")
        made.append(plots.small_multiples([("sent", [{**r, "v": r["sent"]} for r in pk]),
                                           ("lost (symlog)", [{**r, "v": r["lost"]} for r in pk])],
                                          "robots", "v", "scenario", out / f"{prefix}packets-attack1.png",
                                          title="Packets sent and lost - attack 1 (Fig. 4)", ylabel="packets",
                                          sharey=False, log_panels=frozenset({"lost (symlog)"})))
    if sel("attack2", "sha256-2", "defended2"):
        made.append(plots.line_plot(sel("legacy", "attack2", "sha256-2", "defended2"), "robots", "task_time_s", "scenario", out / f"{prefix}task-time-attack2.png",
                                    title="Task time - man in the middle (Fig. 7)", ylabel="seconds"))
    if rows:
        n_max = max(r["robots"] for r in rows)
        made.append(plots.energy_bars([r for r in one_curve if r["robots"] == n_max], out / f"{prefix}energy.png",
                                      title=f"Team energy by component, {n_max} robots ({base_curve} where signed)"))
    curved = curve_rows(rows)
    if len({r["curve"] for r in curved}) > 1:
        # one panel per signed scenario, the three curves in each (nine series on one
        # axis could not be read)
        panels = [(plots.LABELS.get(s, s), [r for r in curved if r["scenario"] == s])
                  for s in SIGNED_SCENARIOS if any(r["scenario"] == s for r in curved)]
        made.append(plots.small_multiples(panels, "robots", "task_time_s", "curve", out / f"{prefix}task-time-curves.png",
                                          title="Task time by ECC curve, signed traffic (Fig. 8)", ylabel="seconds"))
        made.append(plots.small_multiples(panels, "robots", "crypto_cpu_s", "curve", out / f"{prefix}crypto-cpu-curves.png",
                                          title="Crypto CPU time by curve (team total)", ylabel="seconds"))
    bat = sel("battery")
    if bat:
        rc = []
        for r in bat:
            for col in ("returns_home", "charges", "recruit_requests", "recruit_successes"):
                rc.append({**r, "series": col, "v": r[col]})
        made.append(plots.line_plot(rc, "robots", "v", "series", out / f"{prefix}battery-recruit.png",
                                    title="Battery scenario (3 kJ, one robot idle at the base)", ylabel="count per mission"))
    eav = sel("eavesdrop", "defended3")
    if eav:
        made.append(plots.bar_plot(eav, "scenario", "eaves_map_share", out / f"{prefix}eavesdropper.png",
                                   title="Share of the map the eavesdropper reconstructs", ylabel="fraction"))
    return made
