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

import click

from cryptoros.errors import ConfigError


def _url_from_config(path: str) -> str:
    from interceptor.config import load

    cfg = load(path)
    if cfg.metrics is None:
        raise ConfigError(f"{path} has no [listen] metrics endpoint: status is served there")
    return f"http://{cfg.metrics.host}:{cfg.metrics.port}/status"


def render(status: dict) -> list[str]:
    """The human-readable lines of a ``/status`` answer."""
    token, cert, feed, crl = status.get("token"), status["certificate"], status["feed"], status.get("crl")
    lines = [f"manager {status['manager']} ({', '.join(status['roles'])}), public {status['public']}: "
             f"{status['health']}"]
    if token:
        lines.append(f"token     subject {token['subject']}, expires in {token['expires_in']} s, jti {token['jti']}")
        lines.append(f"grants    {len(token['grants'])}")
        lines += [f"          {node} {action} {name} [{type_}]" for node, action, name, type_ in token["grants"]]
    else:
        lines.append("token     none that verifies")
    lines.append(f"cert      serial {cert['serial']}, valid until {cert['not_after'][:19]} ({cert['days_left']} days)")
    lines.append(f"feed      age {feed['age']} s, {feed['revoked_tokens']} revoked tokens, disabled managers: "
                 f"{', '.join(feed['disabled_managers']) or 'none'}")
    if crl:
        lines.append(f"crl       {crl['file']}, written {crl['age']} s ago")
    peers = status.get("peers") or {}
    lines.append(f"peers     {', '.join(f'{m} ({n} streams)' for m, n in peers.items()) or 'none'}; "
                 f"{status['open_streams']} open streams in all")
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
    if not url:
        if not config_path:
            raise click.UsageError("give --config FILE (or --url http://127.0.0.1:PORT/status)")
        try:
            url = _url_from_config(config_path)
        except ConfigError as exc:
            raise click.ClickException(str(exc)) from None
    try:
        with urllib.request.urlopen(url, timeout=5) as resp:
            body = json.loads(resp.read())
    except (urllib.error.URLError, OSError, ValueError) as exc:
        click.echo(f"cryptoros status: error: cannot read {url}: {getattr(exc, 'reason', exc)}", err=True)
        raise SystemExit(2) from None
    click.echo(json.dumps(body, indent=2) if as_json else "\n".join(render(body)))
    raise SystemExit(0 if body.get("health") == "ok" else 1)
