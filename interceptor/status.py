"""``cryptoros status``: what one host's interceptor is to the registry right now.

Reads the interceptor's ``/status`` (on its loopback metrics endpoint, ``[listen]
metrics``): token subject, grants and expiry, feed and CRL age, certificate lifetime,
peers with open streams. Exit status 0 when healthy, 1 when not, 2 when it cannot be
asked.
"""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from typing import NoReturn

import click

from cryptoros.errors import ConfigError


def _url_from_config(path: str) -> tuple[str, str]:
    """The ``/status`` URL of the interceptor ``path`` configures, and its manager.

    Only ``manager`` and ``[listen] metrics`` are read: reading a running interceptor's
    status needs nothing else, and the rest (a ``[ros2] python`` that exists on the
    robot, key files) need not be valid in the shell the operator asks from."""
    from pathlib import Path

    from interceptor.config import metrics_endpoint, read_toml

    raw = read_toml(Path(path).absolute())
    manager = raw.get("manager")
    if not isinstance(manager, str) or not manager:
        raise ConfigError(f"{path}: manager is required: the name of the manager whose token this interceptor holds")
    listen = raw.get("listen", {})
    if not isinstance(listen, dict):
        raise ConfigError(f"{path}: [listen] must be a table")
    metrics = metrics_endpoint(listen)
    if metrics is None:
        raise ConfigError(f"{path} has no [listen] metrics endpoint: status is served there")
    return f"http://{metrics.host}:{metrics.port}/status", manager


def render(status: dict) -> list[str]:
    """The human-readable lines of a ``/status`` answer."""
    token, cert, feed, crl = status.get("token"), status["certificate"], status["feed"], status.get("crl")
    lines = [f"manager {status['manager']} ({', '.join(status['roles'])}), public {status['public']}: "
             f"{status['health']}"]
    learning = status.get("learning")
    if learning:
        lines.append(f"LEARNING  {learning['left']} s left: {learning['learned']} requests no grant covers let "
                     f"through here and recorded, each still refused by a peer that is not learning "
                     f"(cryptoros-authz learn propose {status['manager']})")
    if token:
        lines.append(f"token     subject {token['subject']}, expires in {token['expires_in']} s, jti {token['jti']}")
        lines.append(f"grants    {len(token['grants'])}")
        lines += [f"          {node} {action} {name} [{type_}]" for node, action, name, type_ in token["grants"]]
    else:
        lines.append("token     none that verifies")
    refresh = status.get("token_refresh")
    if refresh:
        lines.append(f"warning   token refresh failing for {refresh['failing_for']} s: {refresh['reason']}")
    lines.append(f"cert      serial {cert['serial']}, valid until {cert['not_after'][:19]} ({cert['days_left']} days)")
    lines.append(f"feed      age {feed['age']} s, {feed['revoked_tokens']} revoked tokens, disabled managers: "
                 f"{', '.join(feed['disabled_managers']) or 'none'}")
    if crl:
        lines.append(f"crl       {crl['file']}, written {crl['age']} s ago"
                     + (f", next update due in {crl['days_left']} days" if "days_left" in crl else ""))
        if crl.get("warning"):
            lines.append(f"warning   the CRL is {crl['warning']}")
    peers = status.get("peers") or {}
    lines.append(f"peers     {', '.join(f'{m} ({n} streams)' for m, n in peers.items()) or 'none'}; "
                 f"{status['open_streams']} open streams in all")
    if "message_rate" in status:
        rate, held = status["message_rate"], status.get("throttled") or {}
        lines.append(f"rate      {f'{rate:g} messages a second per peer' if rate else 'no limit (max_messages_per_second = 0)'}"
                     f"; held back: {', '.join(f'{m} ({n} waits)' for m, n in held.items()) or 'none'}")
    lines += [f"warning   {warning}" for warning in status.get("warnings", ())]
    refusals = status.get("denials") or []
    lines.append(f"denials   {sum(r['count'] for r in refusals)} refused, {len(refusals)} distinct"
                 f"{' (cryptoros denials: each with the grant that would allow it)' if refusals else ''}")
    monitor = status.get("monitor")
    if monitor:
        held = ", ".join(f"{q['publisher']} of {q['manager']} ({q['seconds_left']} s)" for q in monitor["quarantined"])
        lines.append(f"monitor   {monitor['action']}, {monitor['watched_streams']} streams watched; "
                     f"quarantined: {held or 'none'}")
    return lines


@click.command()
@click.option("--config", "config_path", help="The interceptor's configuration (its [listen] metrics endpoint).")
@click.option("--url", help="The /status URL instead (default: from --config).")
@click.option("--json", "as_json", is_flag=True, help="Print the raw JSON.")
def status(config_path: str | None, url: str | None, as_json: bool) -> None:
    """Show this host's interceptor: token subject, grants, expiry, feed and CRL age, peers."""
    body = _read_status(config_path, url, "cryptoros status")
    click.echo(json.dumps(body, indent=2) if as_json else "\n".join(render(body)))
    raise SystemExit(0 if body.get("health") == "ok" else 1)


def render_denials(status: dict) -> list[str]:
    """The recent refusals of a ``/status`` answer, grouped (one line per kind, peer,
    reason and target, most recent first), each with the grant that would allow it."""
    rows = status.get("denials") or []
    if not rows:
        return [f"no refusals recorded by {status.get('manager', 'this interceptor')} since it started"]
    lines = [f"{len(rows)} distinct refusals on {status.get('manager', 'this interceptor')}, most recent first:"]
    for row in rows:
        lines.append(f"{row['count']:6d}x  {row['kind']} from {row['peer']}: {row['target']} "
                     f"(last {row['last_ago']:g} s ago, first {row['first_ago']:g} s ago)")
        if row.get("grant"):
            lines.append(f"         to allow: {row['grant']}")
    return lines


def _read_status(config_path: str | None, url: str | None, prog: str = "cryptoros") -> dict:
    expected = None  # the manager the configuration names: the interceptor answering must be its
    if not url:
        if not config_path:
            raise click.UsageError("give --config FILE (or --url http://127.0.0.1:PORT/status)")
        try:
            url, expected = _url_from_config(config_path)
        except ConfigError as exc:
            click.echo(f"{prog}: error: {exc}", err=True)
            raise SystemExit(2) from None
    try:
        with urllib.request.urlopen(url, timeout=5) as resp:
            raw = resp.read()
    except urllib.error.HTTPError as exc:
        _not_a_status(prog, url, f"HTTP {exc.code} {exc.reason}")
    except (urllib.error.URLError, OSError, ValueError) as exc:
        reason = getattr(exc, "reason", exc)
        click.echo(f"{prog}: error: cannot read {url}: {reason}{_not_running_hint(reason, config_path, expected)}",
                   err=True)
        raise SystemExit(2) from None
    try:
        body = json.loads(raw)
    except ValueError:
        _not_a_status(prog, url, "not JSON")
    missing = _missing_fields(body)
    if missing:
        _not_a_status(prog, url, missing)
    answered = body["manager"]
    if expected is not None and answered != expected:
        # another interceptor on this host answers on the port the file names: its state is
        # not this one's (two configurations sharing one [listen] metrics port)
        click.echo(f"{prog}: error: {url} is the interceptor of manager {answered}, not {expected} as "
                   f"{config_path} says: is {expected}'s interceptor running, and does another use its "
                   "[listen] metrics port?", err=True)
        raise SystemExit(2)
    return body


#: What every interceptor's ``/status`` answer holds, and what ``render`` and
#: ``render_denials`` read without a default: a field, its type, the fields inside it.
_STATUS_FIELDS: dict[str, tuple[type | tuple[type, ...], tuple[str, ...]]] = {
    "manager": (str, ()),
    "roles": (list, ()),
    "public": (str, ()),
    "health": (str, ()),
    "certificate": (dict, ("serial", "not_after", "days_left")),
    "feed": (dict, ("age", "revoked_tokens", "disabled_managers")),
    "open_streams": ((int, float), ()),
    "denials": (list, ()),
}
_TYPE_NAMES = {str: "a string", list: "a list", dict: "an object", (int, float): "a number"}


def _missing_fields(body: object) -> str:
    """What ``body`` lacks of an interceptor's ``/status`` answer ("" when nothing)."""
    if not isinstance(body, dict):
        return "not a JSON object"
    absent = [name for name in _STATUS_FIELDS if name not in body]
    problems = [f"no {', '.join(absent)}"] if absent else []
    for name, (kind, inner) in _STATUS_FIELDS.items():
        if name not in body:
            continue
        if not isinstance(body[name], kind) or (kind is not str and isinstance(body[name], bool)):
            problems.append(f"{name} is not {_TYPE_NAMES[kind]}")
        elif inner and (lacking := [key for key in inner if key not in body[name]]):
            problems.append(f"{name} has no {', '.join(lacking)}")
    return "; ".join(problems)


def _not_a_status(prog: str, url: str, what: str) -> NoReturn:
    click.echo(f"{prog}: error: {url} did not answer as an interceptor's /status ({what}): give its "
               "[listen] metrics endpoint's /status", err=True)
    raise SystemExit(2)


def _not_running_hint(reason: object, config_path: str | None, manager: str | None) -> str:
    """What to try when nothing listens at the status endpoint: the usual cause is an
    interceptor not started yet (or stopped), or a configuration of another host's
    interceptor; not a wrong port."""
    if not isinstance(reason, ConnectionRefusedError):
        return ""
    who = f"{manager}'s interceptor" if manager else "the interceptor"
    return (f" (is {who} running on this host? start it with cryptoros-interceptor "
            f"--config {config_path or 'FILE'})")


@click.command()
@click.option("--config", "config_path", help="The interceptor's configuration (its [listen] metrics endpoint).")
@click.option("--url", help="The /status URL instead (default: from --config).")
@click.option("--json", "as_json", is_flag=True, help="Print the raw JSON rows.")
def denials(config_path: str | None, url: str | None, as_json: bool) -> None:
    """Show the refusals this host's interceptor made lately, grouped by who, why and
    what, with the `cryptoros-authz grant ...` that would allow each (run it on the
    authorization server's host; nothing is granted from here)."""
    body = _read_status(config_path, url, "cryptoros denials")
    click.echo(json.dumps(body.get("denials") or [], indent=2) if as_json else "\n".join(render_denials(body)))


def _write_release(path, manager: str, publisher: str | None) -> None:
    """Add one release request to the file the interceptor applies on SIGHUP (0600)."""
    from interceptor.statefile import write_private_json

    asked = []
    if path.exists():
        try:
            asked = list(json.loads(path.read_text())["release"])
        except (OSError, ValueError, KeyError, TypeError):
            asked = []  # an unreadable earlier request is replaced
    asked.append({"manager": manager, "publisher": publisher})
    write_private_json(path, {"version": 1, "release": asked})


def _interceptor_at(url: str) -> tuple[int, list[dict]]:
    """(pid, quarantines) of the interceptor serving ``url``; OSError when it cannot be
    asked or the pid it gives is not an interceptor's."""
    from pathlib import Path

    try:
        with urllib.request.urlopen(url, timeout=5) as resp:
            body = json.loads(resp.read())
        pid = int(body["pid"])
        held = list((body.get("monitor") or {}).get("quarantined", []))
    except urllib.error.URLError as exc:
        raise OSError(str(exc.reason)) from None
    except (ValueError, KeyError, TypeError) as exc:
        raise OSError(f"{url} is not an interceptor's status: {exc}") from None
    if b"interceptor" not in Path(f"/proc/{pid}/cmdline").read_bytes():
        raise OSError(f"pid {pid} from {url} is not an interceptor")
    return pid, held


@click.command()
@click.option("--config", "config_path", required=True,
              help="The interceptor's configuration (its state_dir, [monitor] and [listen] metrics).")
@click.option("--timeout", default=10.0, show_default=True, help="Seconds to wait for the interceptor to lift it.")
@click.argument("manager")
@click.argument("publisher", required=False)
def unquarantine(config_path: str, timeout: float, manager: str, publisher: str | None) -> None:
    """Lift the runtime monitor's quarantine of PUBLISHER (a node, e.g. /teleop) of
    MANAGER on this host's interceptor, or of every publisher of MANAGER: after a false
    alert on a publisher a robot needs, without a restart (a restart keeps quarantines).

    The request is written to the interceptor's state_dir and the running interceptor
    (found at its /status) is sent SIGHUP, which lifts it and logs what it lifted; an
    interceptor that is not running lifts it when it starts."""
    import os
    import signal
    import time

    from interceptor.config import load
    from interceptor.monitor import quarantine_path, release_path_for

    try:
        cfg = load(config_path)
    except ConfigError as exc:
        raise click.ClickException(str(exc)) from None
    if cfg.monitor is None:
        raise click.ClickException(f"{config_path} has no [monitor]: nothing is quarantined there")
    if cfg.state_dir is None:
        raise click.ClickException(f"{config_path} has no state_dir: quarantines are not kept there, and a "
                                   "release is handed to the interceptor there (set state_dir, restart)")
    path = release_path_for(quarantine_path(cfg.state_dir, cfg.manager))
    who = f"{publisher} of {manager}" if publisher else f"every publisher of {manager}"

    def matching(held: list[dict]) -> list[dict]:
        return [q for q in held if q.get("manager") == manager and publisher in (None, q.get("publisher"))]

    url = f"http://{cfg.metrics.host}:{cfg.metrics.port}/status" if cfg.metrics else None
    try:
        if url is None:
            raise OSError("no [listen] metrics endpoint")
        pid, held = _interceptor_at(url)
    except OSError as exc:
        _write_release(path, manager, publisher)
        click.echo(f"release of {who} written to {path}; the interceptor could not be asked now ({exc}): "
                   "it lifts it on its next SIGHUP or start")
        return
    if not matching(held):
        click.echo(f"no quarantine of {who} on this interceptor (pid {pid}): nothing to lift")
        return
    _write_release(path, manager, publisher)
    os.kill(pid, signal.SIGHUP)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        time.sleep(0.1)
        try:
            pid_now, held = _interceptor_at(url)
        except OSError:
            continue
        if not path.exists() and not matching(held):
            click.echo(f"lifted: {who} (interceptor pid {pid_now})")
            return
    raise click.ClickException(f"the interceptor (pid {pid}) did not lift {who} within {timeout:g} s: see its log")
