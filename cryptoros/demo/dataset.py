"""``cryptoros monitor dataset``: labelled recordings of the demo's robots for the monitor.

Each run is one plain-ROS mission of the demo's team (the embedded master, no
interceptors: the messages are the same), recorded by ``cryptoros monitor record`` on
every robot's ``pose``, ``scan`` and ``cmd_vel`` and the team topics (``/team/*``, the
simulator's own types: rate and size only) from before the start. A clean run has
no compromise; an attacked run has robot ``r0`` compromised (:mod:`cryptoros.demo.
compromise`): from ``onset`` seconds after the start, its own base or explorer misuses
the grants it holds. Beside each ``run.bag`` a ``run.bag.labels.json`` names the
compromised publisher, topic and onset (Unix time), and the run's seed and kind:
``cryptoros monitor train`` takes the clean runs, ``cryptoros monitor eval`` any runs
(split by seed: train on some seeds' clean runs, evaluate on the others').
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import click

from cryptoros.demo.compromise import COMPROMISES
from cryptoros.demo.run import TEAM_TYPES as TEAM_TOPICS
from cryptoros.demo.run import Children, DemoError, DemoOptions, Graph, Mission


#: tries of one run before the dataset fails (a mission that ends at once is run again)
ATTEMPTS = 2


class RecordingMission(Mission):
    """A plain mission with ``cryptoros monitor record`` running from before the start."""

    def __init__(self, *args: Any, bag: Path, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.bag = bag

    def _arm_attacks(self, g: Graph) -> dict[str, subprocess.Popen]:
        topics = [f"/{r}/{t}" for r in self.team for t in ("pose", "scan", "cmd_vel")] + \
            [f"/team/{short}" for short in TEAM_TOPICS]
        cmd = [sys.executable, "-m", "cryptoros.cli", "monitor", "record", "--master-uri", g.robot_master[self.team[0]],
               "--seconds", str(self.opts.seconds + 60), "-o", str(self.bag)]
        for topic in topics:
            cmd += ["--topic", topic]
        log = self.dir / "recorder.log"
        proc = self.children.start(cmd, log, _recorder_env())
        deadline = time.monotonic() + 30
        while "recording" not in log.read_text():  # subscribed to every topic: the mission may start
            if proc.poll() is not None or time.monotonic() > deadline:
                raise DemoError(f"the recorder did not start: {log.read_text()[-500:]}")
            time.sleep(0.05)
        return {"recorder": proc}


def _recorder_env() -> dict[str, str]:
    from cryptoros.demo.run import _env

    return _env()


def record_run(out: Path, *, seed: int, kind: str | None, seconds: float, onset: float,
               say=lambda _m: None) -> dict[str, Any]:
    """One run into ``out`` (``run.bag``, ``run.bag.labels.json``); returns its summary."""
    out.mkdir(parents=True, exist_ok=True)
    compromise = {"robot": "r0", "kind": kind, "onset": onset} if kind else None
    opts = DemoOptions(attacks=(), seconds=seconds, modes=("plain",), seed=seed, compromise=compromise,
                       coverage_target=1.01)  # run the whole budget: every run as long as the others
    work = out / "work"
    bag = out / "run.bag"
    for attempt in range(1, ATTEMPTS + 1):
        children = Children()
        try:
            mission = RecordingMission(opts, "plain", work, children, lambda _p: None, bag=bag)
            result = mission.run()
            t0 = float(json.loads((mission.dir / "go.json").read_text())["t0"])
        finally:
            children.kill_all()
        if result["wall_s"] >= 0.5 * seconds:
            break
        # a mission that ended at once recorded nothing worth labelling: never a silent empty run
        why = f"the mission ended after {result['wall_s']:.1f} s of {seconds:g} ({result.get('end_reason', '?')})"
        if attempt == ATTEMPTS:
            raise DemoError(f"{out.name}: {why}, {ATTEMPTS} times; logs in {work}")
        say(f"  {out.name}: {why}; recording it again")
        shutil.rmtree(work, ignore_errors=True)
    attacks = []
    if kind:
        topic, who = COMPROMISES[kind]
        attacks.append({"publisher": "/r0_base" if who == "base" else "/r0",
                        "topic": topic if topic.startswith("/") else f"/r0/{topic}", "onset": t0 + onset, "kind": kind})
    Path(f"{bag}.labels.json").write_text(json.dumps({"seed": seed, "kind": kind or "clean", "t0": t0,
                                                      "attacks": attacks}, indent=1))
    shutil.rmtree(work, ignore_errors=True)
    summary = {"run": out.name, "seed": seed, "kind": kind or "clean", "wall_s": result["wall_s"],
               "bag_bytes": bag.stat().st_size if bag.exists() else 0}
    say(f"  {out.name}: {summary['wall_s']:.0f} s, {summary['bag_bytes'] // 1024} KiB")
    return summary


@click.command()
@click.option("--out", "-o", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Directory of the dataset (one sub-directory per run).")
@click.option("--seeds", default="1,2,3", show_default=True, help="World and robot seeds, comma-separated.")
@click.option("--kinds", default=",".join(COMPROMISES), show_default=True,
              help="Compromises to record, comma-separated (each seed also gets a clean run).")
@click.option("--seconds", default=20.0, show_default=True, type=click.FloatRange(5, 600),
              help="Wall seconds of each run.")
@click.option("--onset", default=6.0, show_default=True, type=click.FloatRange(0, 600),
              help="Wall seconds after the start when the compromised robot turns.")
def dataset(out: Path, seeds: str, kinds: str, seconds: float, onset: float) -> None:
    """Record labelled runs of the demo's robots: a clean run per seed, and per seed one run
    per compromise of robot r0 (spoofed or drifting or replayed poses, noise scans, a stop
    flood, false "map explored" claims), each misusing grants the robot holds. Progress on
    stderr."""
    try:
        seed_list = [int(s) for s in seeds.split(",") if s.strip()]
    except ValueError:
        raise click.BadParameter(f"{seeds!r}: expected integers such as 1,2,3", param_hint="--seeds") from None
    kind_list = [k.strip() for k in kinds.split(",") if k.strip()]
    unknown = [k for k in kind_list if k not in COMPROMISES]
    if unknown:
        raise click.BadParameter(f"unknown {', '.join(unknown)}; known: {', '.join(COMPROMISES)}", param_hint="--kinds")
    if onset >= seconds:
        raise click.BadParameter("the onset must come before the end of the run", param_hint="--onset")
    plan = [(seed, kind) for seed in seed_list for kind in (None, *kind_list)]
    say = lambda m: click.echo(m, err=True)  # noqa: E731
    say(f"{len(plan)} runs of {seconds:g} s into {out} (about {len(plan) * (seconds + 8) / 60:.0f} min)")
    summaries = []
    for i, (seed, kind) in enumerate(plan, 1):
        say(f"[{i}/{len(plan)}] seed {seed}, {kind or 'clean'}")
        try:
            summaries.append(record_run(out / f"seed{seed}-{kind or 'clean'}", seed=seed, kind=kind, seconds=seconds,
                                        onset=onset, say=say))
        except DemoError as exc:
            raise click.ClickException(str(exc)) from None
    (out / "dataset.json").write_text(json.dumps({"runs": summaries, "seconds": seconds, "onset": onset}, indent=1))
    click.echo(f"dataset: {out} ({len(summaries)} runs; clean runs: {out}/seed*-clean/run.bag)")
