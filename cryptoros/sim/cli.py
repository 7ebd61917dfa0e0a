"""``cryptoros sim``: run one mission or sweep a grid of them."""

from __future__ import annotations

import json
from pathlib import Path

import click

from cryptoros.consoles import for_logs
from cryptoros.errors import ConfigError
from cryptoros.outputs import write_output, writing


def _csv(value: str, cast=str) -> list:
    return [cast(v.strip()) for v in value.split(",") if v.strip()]


@click.group()
def sim() -> None:
    """Deterministic simulator of secure multi-robot exploration (seed paper 000)."""


@sim.command("run")
@click.option("--robots", default=4, show_default=True, help="number of honest robots")
@click.option("--attack", default="none", show_default=True, help="comma list: impersonate, impersonate-insider, mitm, eavesdrop, replay, flood, false-recruit, blackhole")
@click.option("--security", default="none", show_default=True, help="none or comma list of ecdsa|rsa, sha256|hmac, aes; 'full' = ecdsa,hmac,aes")
@click.option("--curve", default="secp256k1", show_default=True, type=click.Choice(["secp192r1", "secp256k1", "secp384r1"]))
@click.option("--crypto-cost", default="measured", show_default=True, type=click.Choice(["measured", "nominal"]),
              help="measured: time each primitive once on this machine; nominal: fixed figures (reproducible anywhere)")
@click.option("--plausibility/--no-plausibility", default=False, help="reject map claims beyond what the sender could have seen")
@click.option("--seed", default=1, show_default=True)
@click.option("--size", default="100x100", show_default=True, help="generated grid WxH (cells of --resolution m)")
@click.option("--resolution", default=0.2, show_default=True)
@click.option("--map", "map_yaml", default="", help="map_server YAML to load instead of generating")
@click.option("--bases", default=1, show_default=True)
@click.option("--idle", default=0, show_default=True, help="robots that start idle at a base (recruitable)")
@click.option("--battery-j", default=0.0, help="battery capacity in J (default: TurtleBot3 Burger, ~72 kJ)")
@click.option("--resume-after", default=20.0, show_default=True,
              help="seconds a recharged robot stays idle (recruitable) at its base before it resumes exploring")
@click.option("--range-m", default=6.0, show_default=True, help="radio range of the robots")
@click.option("--loss", default=0.0, show_default=True, help="random loss probability per reception")
@click.option("--target", default=0.95, show_default=True, help="coverage target that ends the task")
@click.option("--max-time", default=1800.0, show_default=True)
@click.option("--json", "json_path", default=None, type=click.Path(dir_okay=False), help="write every metric as JSON")
@click.option("--map-png", default=None, type=click.Path(dir_okay=False), help="draw truth beside each robot's belief")
@click.option("--trace", default=None, type=click.Path(dir_okay=False), help="write the per-packet channel trace (JSON lines)")
@click.option("--quiet", is_flag=True)
def run_cmd(robots, attack, security, curve, crypto_cost, plausibility, seed, size, resolution, map_yaml, bases, idle, battery_j, resume_after, range_m,
            loss, target, max_time, json_path, map_png, trace, quiet) -> None:
    """Run one mission and print a summary."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.table import Table

    from cryptoros.sim.scenario import Mission, SimConfig
    from cryptoros.sim.security import SecurityConfig

    try:
        w, h = (int(v) for v in size.lower().split("x"))
        cfg = SimConfig(
            robots=robots, seed=seed, width=w, height=h, map_yaml=map_yaml, resolution=resolution, bases=bases,
            attacks=tuple(a for a in _csv(attack) if a != "none"), security=SecurityConfig.parse(security, curve=curve, crypto_cost=crypto_cost),
            plausibility=plausibility, coverage_target=target, max_time=max_time, range_m=range_m, loss=loss, idle=idle, battery_j=battery_j,
            resume_after=resume_after, trace=bool(trace),
        )
        mission = Mission(cfg)
    except (ConfigError, ValueError) as err:
        raise click.UsageError(str(err)) from err
    console = for_logs(Console(stderr=True, quiet=quiet))
    with Progress(TextColumn("sim t={task.fields[t]:>7.1f}s"), BarColumn(), TextColumn("coverage {task.fields[cov]:.1%}"), TimeElapsedColumn(),
                  console=console, transient=True, disable=quiet) as prog:
        task = prog.add_task("sim", total=max_time, t=0.0, cov=0.0)
        result = mission.run(lambda t, cov: prog.update(task, completed=t, t=t, cov=cov))
    o, p = result["outcome"], result["packets"]
    out = for_logs(Console())
    table = Table(title=f"{cfg.robots} robots, attacks={','.join(cfg.attacks) or 'none'}, security={cfg.security.label}, seed={seed}")
    table.add_column("metric")
    table.add_column("value", justify="right")
    rows = [
        ("task completed", str(o["completed"])),
        ("task time (s)", f"{o['task_time_s']}" if o["completed"] else f"never (ended {o['end_time_s']} s: {o['end_reason']})"),
        ("true coverage", f"{o['coverage']:.1%}"),
        ("mean map accuracy", f"{o['mean_map_accuracy']:.1%}"),
        ("packets sent / delivered / lost", f"{p['sent']} / {p['delivered']} / {p['lost']}"),
        ("rejected by security", f"{p['rejected']} {p['rejected_by_reason'] or ''}"),
        ("bytes sent", str(p["bytes_sent"])),
        ("energy per robot (J)", f"{result['energy']['mean_per_robot_j']:.0f}"),
        ("crypto CPU (s, all robots)", f"{result['crypto']['cpu_s_total']:.3f}"),
        ("recruit requests / recruited", f"{result['recruit']['requests']} / {result['recruit']['recruited']}"),
        ("returns home / charges / resumed", f"{result['recruit']['returns_home']} / {result['recruit']['charges']} / {result['recruit']['resumed']}"),
        ("end reason", o["end_reason"]),
        ("wall time (s)", f"{result['wall']['seconds']:.2f}"),
    ]
    for a in result["attack"].values():
        if a["kind"] == "eavesdrop":
            rows.append(("eavesdropper: map share / positions share", f"{a['map_share']:.1%} / {a['positions_share']:.1%}"))
        else:
            rows.append((f"attacker {a['name']} ({a['kind']})", json.dumps({k: v for k, v in a.items() if k not in ("kind", "name")})))
    for k, v in rows:
        table.add_row(k, v)
    out.print(table)
    if json_path:
        write_output(json_path, json.dumps(result, indent=1, sort_keys=True))
        out.print(f"metrics: {json_path}")
    if map_png:
        from cryptoros.sim.plots import map_png as draw

        with writing(map_png):
            draw(mission, map_png)
        out.print(f"map: {map_png}")
    if trace:
        with writing(trace) as path, path.open("w") as fh:
            for t, ev, src, dst, typ, size_b, why in mission.channel.trace:
                fh.write(json.dumps({"t": round(t, 6), "event": ev, "from": src, "to": dst, "type": typ, "bytes": size_b, "reason": why}) + "\n")
        out.print(f"trace: {trace}")


@sim.command("sweep")
@click.option("--robots", default="2,3,4", show_default=True, help="comma list of robot counts")
@click.option("--scenarios", default="legacy,attack1,defended1,attack2,sha256-2,defended2,eavesdrop,defended3,secure,secure-rsa,battery",
              show_default=True, help="secure-rsa: full security with RSA key negotiation; battery: 3 kJ batteries and one idle robot "
              "(returns home, recharges, recruits)")
@click.option("--curves", default="secp192r1,secp256k1,secp384r1", show_default=True)
@click.option("--seeds", default=10, show_default=True, help="seeds 1..N (error bars are Student's t 95% intervals: use >= 10)")
@click.option("--out", default="sim-out/sweep", show_default=True, type=click.Path(file_okay=False))
@click.option("--workers", default=0, help="processes (0: all cores)")
@click.option("--size", default="100x100", show_default=True)
@click.option("--max-time", default=900.0, show_default=True)
@click.option("--prefix", default="sim-", show_default=True, help="figure file name prefix")
@click.option("--maps/--no-maps", default=True, show_default=True, help="draw each scenario's map (first seed, most robots) into OUT/maps")
def sweep_cmd(robots, scenarios, curves, seeds, out, workers, size, max_time, prefix, maps) -> None:
    """Run robots x scenarios x curves x seeds on all cores; write sweep.csv (one row per
    mission), paired.csv (scenario pairs compared seed by seed) and PNG figures."""
    from rich.progress import Progress

    from cryptoros.sim.sweep import SCENARIOS, figures, sweep

    scen = _csv(scenarios)
    bad = [s for s in scen if s not in SCENARIOS]
    if bad:
        raise click.UsageError(f"unknown scenarios {bad}; known: {', '.join(SCENARIOS)}")
    w, h = (int(v) for v in size.lower().split("x"))
    extra = {"width": w, "height": h, "max_time": max_time}
    outp = Path(out)
    if seeds < 2:
        raise click.UsageError("--seeds must be at least 2 (intervals need a spread)")

    def tick(i: int, n: int) -> None:
        prog.update(task, completed=i, total=n)
        if not prog.console.is_terminal and (i == n or i % max(1, n // 20) == 0):
            click.echo(f"sweep: {i}/{n} missions", err=True)  # progress in logs too

    with Progress(transient=True) as prog:
        task = prog.add_task("sweep", total=None)
        rows = sweep(_csv(robots, int), scen, _csv(curves), list(range(1, seeds + 1)), outp, workers=workers or None, extra=extra,
                     progress=tick, maps=maps)
    made = figures(rows, outp, prefix)
    click.echo(f"{len(rows)} runs -> {outp / 'sweep.csv'}, seed-by-seed comparisons -> {outp / 'paired.csv'}")
    if maps:
        for m in sorted((outp / "maps").glob("*.png")):
            click.echo(f"map: {m}")
    for m in made:
        click.echo(f"figure: {m}")
