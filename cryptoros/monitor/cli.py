"""``cryptoros monitor record``, ``train`` and ``eval``: fit the runtime monitor's model and measure it on
recordings (the group itself is in :mod:`cryptoros.cli`, beside ``dataset`` from the demo)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from cryptoros.errors import CryptorosError
from cryptoros.outputs import writing

_BAGS = click.argument("bags", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path))


@click.command()
@click.option("--ros", "ros", type=click.Choice(["1", "2"]), default="1", show_default=True,
              help="ROS 1 (through the master) or ROS 2 (on this environment's ROS_DOMAIN_ID, by an rclpy node run "
                   "with the ROS 2 venv's python: scripts/ros2-venv, or $CRYPTOROS_ROS2_PYTHON).")
@click.option("--master-uri", envvar="ROS_MASTER_URI", default=None,
              help="ROS 1: the master to record through (default: $ROS_MASTER_URI, the host's interceptor).")
@click.option("--domain", type=click.IntRange(0, 232), default=None,
              help="ROS 2: the domain to record (default: $ROS_DOMAIN_ID).")
@click.option("--topic", "topics", multiple=True, required=True, help="A topic to record (repeat).")
@click.option("--seconds", default=30.0, show_default=True, type=click.FloatRange(0.1, 86400))
@click.option("--out", "-o", required=True, type=click.Path(dir_okay=False, path_type=Path), help="Bag file to write.")
def record(ros: str, master_uri: str | None, domain: int | None, topics: tuple[str, ...], seconds: float, out: Path) -> None:
    """Record TOPICs into a ROS 1 bag, one connection per publisher (what train and eval read).

    ROS 2 samples are converted to the ROS 1 serialization: the features are the same, and
    one model serves both interceptor roles."""
    if ros == "2":
        _record_ros2(topics, seconds, out, domain)
        return
    if not master_uri:
        raise click.BadParameter("ROS 1 records through a master: --master-uri or $ROS_MASTER_URI", param_hint="--master-uri")
    import asyncio

    from cryptoros.monitor.record import record as run

    def ready() -> None:
        click.echo(f"recording {', '.join(topics)} for {seconds:g} s into {out} ...", err=True)

    async def main() -> dict:
        import signal

        stop = asyncio.Event()
        asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)  # the bag is closed, not lost
        return await run(master_uri, list(topics), out, seconds=seconds, on_ready=ready, stop=stop)

    try:
        out.parent.mkdir(parents=True, exist_ok=True)  # as for every output file (cryptoros.outputs)
        counts = asyncio.run(main())
    except (CryptorosError, OSError) as exc:
        raise click.ClickException(str(exc)) from None
    for key, n in sorted(counts.items()):
        click.echo(f"{n:8d}  {key}")
    click.echo(f"bag: {out}")


def _record_ros2(topics: tuple[str, ...], seconds: float, out: Path, domain: int | None) -> None:
    """``cryptoros.ros2.record_node`` under the ROS 2 venv's python, in this environment
    (its domain and DDS profile: run it on the robot, as its nodes run)."""
    import os
    import signal
    import subprocess
    import sys
    import tempfile

    from cryptoros.ros2 import default_ros2_python

    python = default_ros2_python()
    if not python.exists():
        raise click.ClickException(f"{python} does not exist: create the ROS 2 venv with scripts/ros2-venv "
                                   "(or set CRYPTOROS_ROS2_PYTHON)")
    repo = Path(__file__).resolve().parent.parent.parent
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env.update(PYTHONPATH=str(repo), PYTHONUNBUFFERED="1")
    if domain is not None:
        env["ROS_DOMAIN_ID"] = str(domain)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as cfg:
        json.dump({"topics": list(topics), "seconds": seconds, "out": str(out.resolve())}, cfg)
    proc = subprocess.Popen([str(python), "-m", "cryptoros.ros2.record_node", cfg.name], env=env,
                            stdout=subprocess.PIPE, text=True)
    forward = lambda *_: proc.send_signal(signal.SIGTERM)  # noqa: E731  (the bag is closed, not lost)
    signal.signal(signal.SIGTERM, forward)
    signal.signal(signal.SIGINT, forward)
    counts: dict = {}
    try:
        for line in proc.stdout:  # type: ignore[union-attr]
            if line.startswith("recording"):
                click.echo(f"{line.strip()} for {seconds:g} s into {out} ...", err=True)
            elif line.startswith("{"):
                counts = json.loads(line)
            else:
                sys.stderr.write(line)
    finally:
        rc = proc.wait()
        Path(cfg.name).unlink(missing_ok=True)
    if rc != 0:
        raise click.ClickException(f"the ROS 2 recorder exited with {rc}")
    for key, n in sorted(counts.get("counts", {}).items()):
        click.echo(f"{n:8d}  {key}")
    if counts.get("undecodable"):
        click.echo(f"{counts['undecodable']:8d}  samples that did not decode as their type (not recorded)")
    click.echo(f"bag: {out}")


@click.command()
@_BAGS
@click.option("--out", "-o", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Model file to write (JSON).")
@click.option("--quantile", default=0.999, show_default=True, type=click.FloatRange(0.5, 1.0),
              help="Quantile of each feature over the clean messages that sets its limit.")
@click.option("--margin", default=1.5, show_default=True, type=click.FloatRange(1.0, 100.0),
              help="Factor on that quantile.")
@click.option("--consecutive", default=3, show_default=True, type=click.IntRange(1, 1000),
              help="Suspicious messages in a row that make an alert.")
@click.option("--severe", default=5.0, show_default=True, type=float,
              help="A message this many times over its limit makes an alert alone (0: never alone).")
def train(bags: tuple[Path, ...], out: Path, quantile: float, margin: float, consecutive: int, severe: float) -> None:
    """Fit the model on BAGS, recordings of clean traffic only."""
    from cryptoros.monitor.dataset import train as fit

    try:
        model = fit(bags, quantile=quantile, margin=margin, consecutive=consecutive, severe=severe)
    except CryptorosError as exc:
        raise click.ClickException(str(exc)) from None
    with writing(out):
        model.save(out)
    click.echo(f"model: {out} (trained on {', '.join(f'{n} {k}' for k, n in model.trained_on.items())} messages)")
    for kind, limits in model.limits.items():
        click.echo(f"  {kind:6s} " + ", ".join(f"{name} <= {value:g}" for name, value in limits.items()))


@click.command(name="eval")
@_BAGS
@click.option("--model", "model_path", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--attacker", "attackers", multiple=True, metavar="CALLERID",
              help="A publisher whose messages are attacks (repeat); all others are clean.")
@click.option("--json", "as_json", is_flag=True, help="Print the figures as JSON.")
def evaluate(bags: tuple[Path, ...], model_path: Path, attackers: tuple[str, ...], as_json: bool) -> None:
    """Score every message of BAGS as the interceptor would and compare with the labels."""
    from cryptoros.monitor.dataset import evaluate as run
    from cryptoros.monitor.model import MonitorModel

    try:
        figures = run(MonitorModel.load(model_path), bags, attackers).figures()
    except CryptorosError as exc:
        raise click.ClickException(str(exc)) from None
    if as_json:
        click.echo(json.dumps(figures, indent=1))
        return
    for key, value in figures.items():
        click.echo(f"{key:26s} {value}")
