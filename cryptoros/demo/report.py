"""What the demo shows: the live view, the side-by-side table, the Markdown report."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from cryptoros.consoles import for_logs

MODE_LABEL = {"plain": "plain ROS", "protected": "cryptoros", "monitored": "cryptoros + monitor"}


class LiveView:
    """A live table on a terminal; a line every few seconds otherwise (logs, CI)."""

    def __init__(self, console: Console) -> None:
        self.console = for_logs(console)  # and so the table printed on it after the run
        self.live: Live | None = None
        self._last_line = 0.0
        self._notes: list[str] = []

    def __enter__(self) -> LiveView:
        if self.console.is_terminal:
            self.live = Live(Text("starting..."), console=self.console, refresh_per_second=4, transient=True)
            self.live.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.live is not None:
            self.live.__exit__(None, None, None)

    def note(self, message: str) -> None:
        self.console.print(f"[bold]{message}[/bold]" if self.live else message)

    def update(self, e: dict[str, Any]) -> None:
        if self.live is None:
            now = time.monotonic()
            if now - self._last_line >= 5.0:
                self._last_line = now
                states = " ".join(f"{r}:{s.get('state')}{'(shut down)' if s.get('shut_down') else ''}"
                                  for r, s in sorted(e["statuses"].items()))
                self.console.print(f"  {MODE_LABEL[e['mode']]:10s} {e['wall']:5.1f}/{e['budget']:.0f} s  sim {e['sim']:6.1f} s"
                                   f"  coverage {e['coverage']:6.1%}  {states}")
            return
        t = Table(title=f"{MODE_LABEL[e['mode']]}: {e['wall']:.1f} / {e['budget']:.0f} s wall, {e['sim']:.0f} s simulated")
        for col in ("robot", "state", "rx msgs", "spoofed pose", "noise scans", "stop cmds", "false maps", "shutdown"):
            t.add_column(col)
        for r, s in sorted(e["statuses"].items()):
            st = s["stats"]
            t.add_row(r, s.get("state", "?"), str(st["rx_messages"]), str(st["pose_foreign"]), str(st["scan_foreign"]),
                      str(st["cmd_foreign"]), str(st["map_from_non_team"]), "yes" if s.get("shut_down") else "no")
        width = 40
        filled = int(width * min(1.0, e["coverage"] / max(1e-9, e["target"])))
        bar = Text(f"coverage {e['coverage']:6.1%} [" + "#" * filled + "." * (width - filled) + f"] target {e['target']:.0%}")
        self.live.update(Group(t, bar))  # type: ignore[union-attr]


def _yes(ok: bool | None, mode: str = "") -> str:
    if ok is None:
        return "-"
    if not ok and mode == "plain":  # nothing blocks in plain ROS: the attack found nothing to act on
        return "no effect"
    return "[red]SUCCEEDED[/red]" if ok else "[green]blocked[/green]"


def _verdict(cell: dict[str, Any], mode: str = "") -> str:
    """One attack in one mode: the verdict, and in an isolated run its mission's coverage.
    An attack without effect in plain ROS (its liar shut down by another attack) is "no
    effect", not "blocked": nothing there blocks."""
    out = _yes(cell["succeeded"], mode)
    if cell.get("cut_after_s") is not None:  # the monitor quarantined it: how long it had
        out = f"{out}, [yellow]cut after {cell['cut_after_s']:.1f} s[/yellow]"
    if "coverage" in cell:
        out += f" ({cell['coverage']:.0%})"
    return out


def _modes(result: dict[str, Any]) -> list[str]:
    return list(result["config"]["modes"])


def _kb(n: float) -> str:
    return f"{n / 1024:.0f} KiB" if n < 10 * 1024 * 1024 else f"{n / 1048576:.1f} MiB"


def ros_label(result: dict[str, Any]) -> str:
    return "ROS 2 Jazzy (rclpy nodes, a DDS domain per robot)" if result["config"].get("ros") == 2 else "ROS 1"


def table(result: dict[str, Any]) -> Table:
    modes = _modes(result)
    isolated = "isolated" in result
    t = Table(title=f"cryptoros demo, {ros_label(result)}: {result['config']['robots']} robots, same mission, "
                    f"{' vs '.join(MODE_LABEL[m] for m in modes)}"
                    + (" (each attack in its own missions; coverage of that mission)" if isolated else ""))
    t.add_column("")
    for m in modes:
        t.add_column(MODE_LABEL[m], overflow="fold")  # a narrow terminal folds a denial reason, never cuts it
    if isolated:
        for k, a in result["attacks"].items():
            t.add_row(f"{k} (seed {a['seed']})", *[_verdict(a[m], m) if m in a else "-" for m in modes])
        return t
    rows: list[tuple[str, list[str]]] = []
    R = result["modes"]
    rows.append(("coverage reached", [f"{R[m]['coverage']:.1%} (target {R[m]['coverage_target']:.0%})" for m in modes]))
    rows.append(("mission time", [f"{R[m]['mission_time_sim_s']:.0f} s sim / {R[m]['mission_time_wall_s']:.1f} s wall"
                                  if R[m]["target_reached"] else f"not reached ({R[m]['end_reason']})" for m in modes]))
    for k, a in result["attacks"].items():
        rows.append((f"{k} (seed {a['seed']})", [_verdict(a[m], m) if m in a else "-" for m in modes]))
    rows.append(("messages tx / rx", [f"{R[m]['messages']['tx']} / {R[m]['messages']['rx']}" for m in modes]))
    rows.append(("bytes tx / rx", [f"{_kb(R[m]['messages']['tx_bytes'])} / {_kb(R[m]['messages']['rx_bytes'])}" for m in modes]))
    rows.append(("denials by reason", [", ".join(f"{k} {v}" for k, v in R[m]["denials"].items()) or "-" for m in modes]))
    if "monitored" in modes:
        rows.append(("monitor alerts / quarantines / dropped", [
            f"{R[m]['monitor']['alerts']} / {R[m]['monitor']['quarantines']} / {R[m]['monitor'].get('dropped', 0)}"
            if m == "monitored" else "-" for m in modes]))
        rows.append(("monitor's share of interceptor CPU", [_monitor_share(R[m]) if m == "monitored" else "-"
                                                           for m in modes]))
    rows.append(("interceptor CPU", [f"{R[m]['interceptors']['cpu_s_total']:.1f} s ({R[m]['interceptors']['cpu_share_of_one_core']:.0%}"
                                     f" of a core), {_kb(R[m]['interceptors']['bytes_relayed'])} relayed"
                                     if R[m]["interceptors"]["cpu_s"] else "-" for m in modes]))
    rows.append(("set-up time", [f"{R[m]['setup_s']:.1f} s" for m in modes]))
    for name, vals in rows:
        t.add_row(name, *vals)
    return t


def summary_lines(result: dict[str, Any]) -> Text:
    out = Text()
    modes = _modes(result)
    if "protected" in modes or "monitored" in modes:
        out.append("Attackers behind the interceptors:\n", style="bold")
        for k, a in result["attacks"].items():
            out.append(f"  {k:15s} {a['what']}: {a['protected_attacker']}\n")
    out.append("Evidence (from the victims' side):\n", style="bold")
    for k, a in result["attacks"].items():
        for m in modes:
            if m in a:
                out.append(f"  {k:15s} {MODE_LABEL[m]:19s} {a[m]['evidence']}\n")
    return out


# ----------------------------------------------------------------------------- report


def _figures(result: dict[str, Any], out: Path) -> list[tuple[str, str]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figs = []
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for m, res in result["modes"].items():
        tl = np.asarray(res["timeline"] or [[0, 0, 0]], dtype=float)
        ax.plot(tl[:, 0], tl[:, 2] * 100, label=MODE_LABEL[m])
    target = result["config"].get("coverage_target", 0.9) * 100
    ax.axhline(target, ls="--", color="grey", lw=0.8, label="target")
    ax.set_xlabel("simulated time (s)")
    ax.set_ylabel("team coverage (%)")
    ax.set_ylim(0, 100)
    ax.legend()
    ax.set_title("Coverage over time, under attack")
    fig.tight_layout()
    fig.savefig(out / "coverage_over_time.png", dpi=110)
    plt.close(fig)
    figs.append(("Coverage over time", "coverage_over_time.png"))

    from cryptoros.demo.robot import make_world

    cfg = result["config"]
    world = make_world({"seed": cfg["seed"], "width": cfg["width"], "height": cfg["height"]})
    maps = {}
    for m in result["modes"]:
        p = Path(result["workdir"]) / m / "coverage_map.npy"
        if p.exists():
            maps[m] = np.load(p)
    if maps:
        fig, axes = plt.subplots(1, len(maps), figsize=(3.6 * len(maps), 3.6))
        axes = np.atleast_1d(axes)
        for ax, (m, seen) in zip(axes, maps.items()):
            img = np.full(world.shape + (3,), 0.85)
            img[seen & ~world.occupied] = (0.55, 0.8, 0.55)
            img[world.occupied] = (0.2, 0.2, 0.2)
            ax.imshow(img, origin="lower")
            ax.set_title(f"{MODE_LABEL[m]}: {result['modes'][m]['coverage']:.0%}")
            ax.set_xticks([])
            ax.set_yticks([])
        fig.suptitle("Explored cells (green), walls (dark), unexplored (grey)")
        fig.tight_layout()
        fig.savefig(out / "coverage_maps.png", dpi=110)
        plt.close(fig)
        figs.append(("Coverage maps", "coverage_maps.png"))
    return figs


def _md_verdict(cell: dict[str, Any], mode: str = "") -> str:
    out = "**succeeded**" if cell["succeeded"] else ("no effect" if mode == "plain" else "blocked")
    if cell.get("cut_after_s") is not None:
        out += f", cut after {cell['cut_after_s']:.1f} s"
    return out


def _mission_rows(R: dict[str, Any], modes: list[str], result: dict[str, Any], row: Any) -> None:
    row("coverage reached", [f"{R[m]['coverage']:.1%}" for m in modes])
    row("mission time", [f"{R[m]['mission_time_sim_s']:.0f} s simulated, {R[m]['mission_time_wall_s']:.1f} s wall"
                         if R[m]["target_reached"] else f"target not reached ({R[m]['end_reason']})" for m in modes])
    for k, a in result["attacks"].items():
        row(f"{k} (seed {a['seed']})", [_md_verdict(a[m], m) if m in a else "-" for m in modes])
    row("messages tx / rx", [f"{R[m]['messages']['tx']} / {R[m]['messages']['rx']}" for m in modes])
    row("bytes tx / rx", [f"{_kb(R[m]['messages']['tx_bytes'])} / {_kb(R[m]['messages']['rx_bytes'])}" for m in modes])
    row("denials by reason", [", ".join(f"{k} {v}" for k, v in R[m]["denials"].items()) or "-" for m in modes])
    row("interceptor CPU", [f"{R[m]['interceptors']['cpu_s_total']:.1f} s" if R[m]["interceptors"]["cpu_s"] else "-" for m in modes])
    if "monitored" in modes:
        row("monitor alerts / quarantines / dropped", [
            f"{R[m]['monitor']['alerts']} / {R[m]['monitor']['quarantines']} / {R[m]['monitor'].get('dropped', 0)}"
            if m == "monitored" else "-" for m in modes])
        row("monitor's share of interceptor CPU", [_monitor_share(R[m]) if m == "monitored" else "-" for m in modes])


def write_report(result: dict[str, Any], out: Path) -> Path:
    figs = _figures(result, out)
    modes = _modes(result)
    R = result["modes"]
    isolated = "isolated" in result
    lines = ["# cryptoros demo report", "",
             f"{result['config']['robots']} exploration robots (random seed {result['config']['seed']}, "
             f"{result['config']['width']}x{result['config']['height']} cells of 0.2 m), live {ros_label(result)} on loopback, "
             f"clock x{result['config']['scale']:.0f}; attacks as separate processes.", "",
             "| | " + " | ".join(MODE_LABEL[m] for m in modes) + " |", "|---|" + "---|" * len(modes)]

    def row(name: str, vals: list[str]) -> None:
        lines.append(f"| {name} | " + " | ".join(vals) + " |")

    if isolated:
        lines.insert(-2, "Each attack ran in its own missions (`--isolate`); in brackets, that mission's coverage.\n")
        for k, a in result["attacks"].items():
            row(f"{k} (seed {a['seed']})", [_md_verdict(a[m], m) + f" ({a[m]['coverage']:.0%})" if m in a else "-" for m in modes])
    else:
        _mission_rows(R, modes, result, row)
    lines += ["", "## Attacks", "", "| attack | what | attacker in protected mode | " + " | ".join(f"evidence ({MODE_LABEL[m]})" for m in modes) + " |",
              "|---|---|---|" + "---|" * len(modes)]
    for k, a in result["attacks"].items():
        lines.append(f"| {k} | {a['what']} | {a['protected_attacker']} | " + " | ".join(a[m]["evidence"] if m in a else "-" for m in modes) + " |")
    lines.append("")
    denied = result["modes"].get("protected", {}).get("deny_log")
    if denied:
        lines += ["## What the interceptors refused (distinct DENY log lines)", ""]
        for name, entries in denied.items():
            lines += [f"- **{name}**"] + [f"  - `{e}`" for e in entries]
        lines += ["", "A robot's own `/rN/*` topics are `[ros2] local` on its interceptor: they stay on its "
                  "domain and are not listed here.", ""]
    exits = [(f"{m} mission" + (f" of {k}" if k else ""), r, log)
             for k, mission in ([(None, R)] + [(k, v) for k, v in result.get("isolated", {}).items()])
             for m, cell in mission.items() for r, log in cell.get("exit_log", {}).items()]
    if exits:
        lines += ["## Robots that exited during a mission (the last lines of their logs)", ""]
        for where, robot, log in exits:
            lines += [f"- **{robot}**, {where}:", "", "  ```", *(f"  {line}" for line in log), "  ```", ""]
    for title, path in figs:
        lines += [f"## {title}", "", f"![{title}]({path})", ""]
    report = out / "report.md"
    report.write_text("\n".join(lines) + "\n")
    return report


def _monitor_share(mode: dict[str, Any]) -> str:
    """The monitor's busy time over the interceptors' CPU in one mode."""
    busy, cpu = mode["monitor"].get("busy_s", 0.0), mode["interceptors"]["cpu_s_total"]
    return f"{busy:.2f} s of {cpu:.1f} s ({busy / cpu:.1%})" if cpu else "-"
