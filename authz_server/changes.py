"""The record of registry changes, with no database in it: who made a change, the
canonical form and hash of a change row, the before/after of a manager, and the
one-line summary the CLI prints.

A change row's hash is the SHA-256 of the canonical JSON (sorted keys, no spaces,
ASCII) of all of its fields, the previous row's hash among them: the rows form a chain
that :meth:`authz_server.registry.Registry.verify_changes` walks. The chain shows a
row deleted, inserted or edited by someone who did not also recompute every hash
after it; to hold against that too, keep the head hash that ``audit --verify`` prints
somewhere the database's writers cannot reach.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import socket
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

#: the prev_hash of the first row
GENESIS = "0" * 64
_AGE = re.compile(r"^(\d+)([smhdw])$")
_UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400, "w": 7 * 86400}


@dataclass(frozen=True)
class ChangeSource:
    """Who makes the changes of one registry handle: the OS user, the host and the
    command line."""

    os_user: str
    host: str
    command: str

    @classmethod
    def here(cls, command: str) -> ChangeSource:
        """This process's effective OS user (``root (sudo: alice)`` under sudo) and host."""
        uid = os.geteuid()
        try:
            import pwd

            user = pwd.getpwuid(uid).pw_name
        except (ImportError, KeyError):
            user = f"uid {uid}"
        sudo = os.environ.get("SUDO_USER")
        if uid == 0 and sudo and sudo != user:
            user = f"{user} (sudo: {sudo})"
        return cls(user[:128], socket.gethostname()[:255] or "-", command)


def to_json(value: Any) -> str | None:
    """Canonical JSON of a before/after value; None stays None (SQL NULL)."""
    return None if value is None else json.dumps(value, sort_keys=True, separators=(",", ":"))


def utc_text(at: datetime) -> str:
    """A timestamp as hashed: UTC, microseconds (a naive one, as SQLite returns it, is UTC)."""
    at = at.replace(tzinfo=UTC) if at.tzinfo is None else at.astimezone(UTC)
    return at.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def row_hash(*, seq: int, at: datetime, os_user: str, host: str, command: str, target: str,
             before: str | None, after: str | None, prev_hash: str) -> str:
    """SHA-256 (hex) of a change row's canonical content."""
    content = {"seq": seq, "at": utc_text(at), "os_user": os_user, "host": host, "command": command,
               "target": target, "before": before, "after": after, "prev_hash": prev_hash}
    return hashlib.sha256(json.dumps(content, sort_keys=True, separators=(",", ":")).encode("ascii")).hexdigest()


def diff(before: dict | None, after: dict | None) -> tuple[dict | None, dict | None]:
    """What changed between two states of one thing: the keys whose values differ;
    for ``grants`` (a list) the ones removed (in before) and added (in after). A thing
    created or removed keeps its whole state. Two empty dicts mean nothing changed."""
    if before is None or after is None:
        return before, after
    b: dict = {}
    a: dict = {}
    for key in sorted(before.keys() | after.keys()):
        old, new = before.get(key), after.get(key)
        if key == "grants":
            gone, added = sorted(set(old or ()) - set(new or ())), sorted(set(new or ()) - set(old or ()))
            if gone or added:
                b[key], a[key] = gone, added
        elif old != new:
            b[key], a[key] = old, new
    return b, a


def summary(before: Any, after: Any) -> str:
    """One line for the table of ``audit --changes``."""
    if before is None and after is None:
        return "-"
    if before is None:
        return "created " + _compact(after)
    if after is None:
        return "removed " + _compact(before)
    if not (isinstance(before, dict) and isinstance(after, dict)):
        return f"{_compact(before)} -> {_compact(after)}"
    parts = []
    for key in sorted(before.keys() | after.keys()):
        old, new = before.get(key), after.get(key)
        if key == "grants":
            parts += [f"-grant {g}" for g in old or ()] + [f"+grant {g}" for g in new or ()]
        elif isinstance(old, dict) or isinstance(new, dict):  # import: one entry per manager
            parts.append(f"{key}: {summary(old, new)}")
        elif key not in before:  # a fact of the change only (tokens_revoked)
            parts.append(f"{key}={_compact(new)}")
        else:
            parts.append(f"{key}: {_compact(old)} -> {_compact(new)}")
    return "; ".join(parts)


def _compact(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"))


def parse_since(text: str, *, now: datetime | None = None) -> datetime:
    """``7d``, ``12h``, ``30m``, ``90s``, ``2w`` ago, or an ISO 8601 time (UTC if it names no zone)."""
    now = now or datetime.now(UTC)
    m = _AGE.match(text.strip())
    if m:
        return now - timedelta(seconds=int(m.group(1)) * _UNITS[m.group(2)])
    try:
        at = datetime.fromisoformat(text.strip())
    except ValueError:
        raise ValueError(f"{text!r}: expected an age such as 7d, 12h, 30m or an ISO time "
                         "such as 2026-11-27T15:00:00Z") from None
    return at.replace(tzinfo=UTC) if at.tzinfo is None else at.astimezone(UTC)
