"""``cryptoros bench sim``: simulator scale - wall time against robot count.

Targets from the issue: a 4-robot mission in under 5 s wall, 64 robots on a
200 x 200 grid in under 60 s. Prints one row per run; speed is measured here, never
asserted in timed tests.
"""

from __future__ import annotations

import json
from pathlib import Path

import click


@click.command("sim")
@click.option("--robots", default="4,8,16,32,64", show_default=True, help="robot counts for the growth table (200x200 grid)")
@click.option("--security", default="none", show_default=True)
@click.option("--seed", default=1, show_default=True)
@click.option("--max-time", default=1800.0, show_default=True)
@click.option("--json", "json_path", default=None, type=click.Path(dir_okay=False))
def sim(robots: str, security: str, seed: int, max_time: float, json_path: str | None) -> None:
    """Wall time of missions: the 4-robot default and growth with robot count."""
    from cryptoros.sim.scenario import SimConfig, run
    from cryptoros.sim.security import SecurityConfig

    sec = SecurityConfig.parse(security, crypto_cost="nominal")
    rows = []

    def one(label: str, cfg: SimConfig, target: float | None) -> None:
        r = run(cfg)
        o, w = r["outcome"], r["wall"]
        row = {
            "case": label, "robots": cfg.robots, "grid": f"{cfg.width}x{cfg.height}", "security": sec.label, "wall_s": w["seconds"],
            "events": w["events"], "sim_s": o["end_time_s"], "completed": o["completed"], "coverage": o["coverage"],
            "packets": r["packets"]["sent"], "target_s": target, "ok": None if target is None else w["seconds"] < target,
        }
        rows.append(row)
        verdict = "" if target is None else ("  (target < %g s: %s)" % (target, "met" if row["ok"] else "MISSED"))
        click.echo(f"{label:<22} robots={cfg.robots:>3} grid={row['grid']:<8} wall={w['seconds']:7.2f} s  events={w['events']:>8}  "
                   f"sim={o['end_time_s']:7.1f} s  coverage={o['coverage']:.1%}  packets={row['packets']}{verdict}")

    one("mission-4", SimConfig(robots=4, seed=seed, security=sec, max_time=max_time), 5.0)
    for n in [int(x) for x in robots.split(",") if x.strip()]:
        one(f"scale-{n}", SimConfig(robots=n, seed=seed, width=200, height=200, security=sec, max_time=max_time, bases=4 if n >= 16 else 1),
            60.0 if n == 64 else None)
    if json_path:
        Path(json_path).write_text(json.dumps(rows, indent=1))
