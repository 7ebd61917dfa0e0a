"""``cryptoros demo``: the command (options, live display, table, JSON, report)."""

from __future__ import annotations

import json
import shutil
import signal
import sys
import time
from pathlib import Path
from typing import Any

import click

from cryptoros.demo.attackers import ATTACKS, ROS2_ATTACKS
from cryptoros.errors import CryptorosError


def _sigterm(_sig: int, _frame: Any) -> None:
    raise KeyboardInterrupt  # the same clean-up path as Ctrl-C


@click.command()
@click.option("--robots", default=3, show_default=True, type=click.IntRange(2, 8), help="Robots in the team.")
@click.option("--ros", "ros", type=click.Choice(["1", "2"]), default="1", show_default=True,
              help="ROS 1 nodes (embedded master or --master-uri) or ROS 2 Jazzy rclpy nodes, one DDS domain per "
                   "robot behind its interceptor (needs the ROS 2 venv: scripts/ros2-venv).")
@click.option("--attacks", default="all", show_default=True,
              help=f"Comma-separated attacks, 'all' or 'none': {', '.join(ATTACKS)} "
                   f"(ROS 2: {', '.join(ROS2_ATTACKS)}).")
@click.option("--seconds", default=30.0, show_default=True, type=click.FloatRange(5, 3600),
              help="Wall-clock budget of one mission (one per mode; a monitored mode adds a 12 s calibration "
                   "mission first).")
@click.option("--mode", "mode", type=click.Choice(["all", "both", "plain", "protected", "monitored"]), default="all",
              show_default=True,
              help="plain ROS, protected (cryptoros' interceptors), monitored (the interceptors with the runtime monitor, "
                   "trained first on a clean calibration mission); 'both' is plain and protected, 'all' the three "
                   "(ROS 2: plain and protected).")
@click.option("--isolate", is_flag=True,
              help="Each attack in its own missions, so that their effects do not mix (a mission per attack and mode).")
@click.option("--master-uri", default=None, help="Use this running ROS master (e.g. a real rosmaster) instead of the embedded one.")
@click.option("--keep", is_flag=True, help="Keep the work directory (PKI, database, logs, statuses).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write the results as JSON here.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=Path("demo-out"),
              show_default=True, help="Directory of the report (Markdown + PNG figures).")
@click.option("--scale", default=8.0, show_default=True, type=click.FloatRange(1, 50),
              help="Simulated seconds per wall second.")
@click.option("--seed", default=1, show_default=True, type=int, help="World and robot seed.")
@click.option("--size", default=60, show_default=True, type=click.IntRange(30, 200), help="Arena side in cells of 0.2 m.")
@click.option("--workdir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Work directory (default: a new temporary one).")
@click.option("--netns", is_flag=True,
              help="Protected mode on separate hosts: each robot, the master and the stranger in its own network "
                   "namespace, as robots on a LAN (needs root).")
@click.option("--learn", is_flag=True,
              help="Protected modes with every robot's manager in learning mode (cryptoros-authz learn start) for "
                   "the whole mission: the stranger's attacks must still fail (certificates are checked as "
                   "always); an insider's reach robots that learn too, which is what learning means (ROS 1).")
def demo(robots: int, ros: str, attacks: str, seconds: float, mode: str, isolate: bool, master_uri: str | None, keep: bool,
         json_path: Path | None, out_dir: Path, scale: float, seed: int, size: int, workdir: Path | None, netns: bool,
         learn: bool) -> None:
    """A live robot team under attack: plain ROS, then behind cryptoros interceptors.

    Starts a throwaway PKI, the authorization server, a ROS master and one robot
    process per robot (the simulator's exploration robots as live ROS nodes), runs the
    attacks of seed papers 000 and 001 against the live graph as separate processes,
    and prints what reached the robots in each mode. The held-* attacks misuse grants
    their attacker holds: the interceptors let them through, the runtime monitor
    (mode "monitored") cuts them.

    With --ros 2 the robots are rclpy nodes (ROS 2 Jazzy): plain, all on one DDS domain;
    protected, each on its own localhost-only domain behind its interceptor's ros2 role.
    """
    from rich.console import Console

    from cryptoros.demo import report as rep
    from cryptoros.demo.run import ALL_ATTACKS, DemoError, DemoOptions
    from cryptoros.demo.session import run_demo

    known = ROS2_ATTACKS if ros == "2" else ALL_ATTACKS
    if attacks == "all":
        chosen = known
    elif attacks == "none":
        chosen = ()
    else:
        chosen = tuple(a.strip() for a in attacks.split(",") if a.strip())
        bad = [a for a in chosen if a not in known]
        if bad:
            hint = " (shutdown, hijack, map-erase and held-* have no ROS 2 counterpart: docs/demo.md)" if ros == "2" else ""
            raise click.BadParameter(f"unknown attack {bad[0]!r}; one of {', '.join(known)}{hint}", param_hint="--attacks")
    if ros == "2" and master_uri:
        raise click.BadParameter("ROS 2 has no master", param_hint="--master-uri")
    if netns:
        from cryptoros.lab.netns import netns_unavailable

        reason = netns_unavailable()
        if reason is not None:
            raise click.ClickException(f"--netns: {reason}")
        if ros == "2" or master_uri:
            raise click.BadParameter("runs the ROS 1 demo with its embedded master", param_hint="--netns")
    if learn and ros == "2":
        raise click.BadParameter("the learning demo runs ROS 1 (ROS 2 learning: docs/policy.md)", param_hint="--learn")
    if ros == "2" and mode == "monitored":
        raise click.BadParameter("the monitored demo runs ROS 1 (the ROS 2 role's monitor: docs/monitor.md)",
                                 param_hint="--mode")
    modes = {"both": ("plain", "protected"), "all": ("plain", "protected") if ros == "2" else ("plain", "protected", "monitored")
             }.get(mode, (mode,))
    opts = DemoOptions(robots=robots, attacks=chosen, seconds=seconds, modes=modes, master_uri=master_uri, keep=keep,
                       seed=seed, width=size, height=size, scale=scale, ros=int(ros),
                       workdir=str(workdir) if workdir else None, netns=netns, isolate=isolate,
                       learn=learn)
    console = Console(stderr=False)
    signal.signal(signal.SIGTERM, _sigterm)
    # Ctrl-C stops every child even when the demo was started with SIGINT ignored (a shell
    # starts background jobs so, and children inherit it: Python then never raises
    # KeyboardInterrupt, and the demo ran on to its end)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    live = rep.LiveView(console)
    t0 = time.monotonic()
    result: dict[str, Any] | None = None
    try:
        with live:
            result = run_demo(opts, progress=live.update, note=live.note)
    except KeyboardInterrupt:
        console.print("[yellow]interrupted: every child process was stopped[/yellow]")
        sys.exit(130)
    except (DemoError, CryptorosError) as exc:  # a clear line, never a traceback
        hint = "" if keep or workdir else " (--keep keeps the work directory and its logs)"
        raise click.ClickException(f"{exc}{hint}") from None
    result["wall_s"] = round(time.monotonic() - t0, 1)
    out_dir.mkdir(parents=True, exist_ok=True)
    if (out_dir / "report.md").exists():  # the default --out of every run: say so rather than overwrite silently
        console.print(f"replacing the report of an earlier run in {out_dir} (--out DIR keeps each run's)")
    report_path = rep.write_report(result, out_dir)
    result["report"] = str(report_path)
    console.print(rep.table(result))
    console.print(rep.summary_lines(result))
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(result, indent=1, default=str))
        console.print(f"JSON: {json_path}")
    console.print(f"Report: {report_path}")
    if keep:
        console.print(f"Kept: {result['workdir']}")
    else:
        shutil.rmtree(result["workdir"], ignore_errors=True)
