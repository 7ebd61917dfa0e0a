"""The daemons' log lines: one record, one line, whatever a peer put in it.

Refusal reasons quote what a peer sent (a TCPROS header's topic, an XML-RPC caller id,
a token's ``kid``). A newline in such a value wrote a second, well-formed log line of the
attacker's choosing (``... INFO ALLOW topic from robot_c``) into the interceptor's log.
:class:`OneLineFormatter` escapes every control character of a record's message and cuts
a message longer than :data:`MAX_MESSAGE` characters; a traceback the daemon itself
attaches (``log.exception``) keeps its lines.
"""

from __future__ import annotations

import logging
from typing import TextIO

#: characters of one record's message kept (a peer's value can be up to a header's 1 MB)
MAX_MESSAGE = 4096
_ESCAPES = {c: f"\\x{c:02x}" for c in (*range(0x20), 0x7F)}
_ESCAPES |= {ord("\n"): "\\n", ord("\r"): "\\r", ord("\t"): "\\t"}
_ESCAPES |= {c: f"\\u{c:04x}" for c in (0x85, 0x2028, 0x2029)}


def one_line(text: str, limit: int = MAX_MESSAGE) -> str:
    """``text`` with every control character escaped, cut to ``limit`` characters."""
    if len(text) > limit:
        text = f"{text[:limit]}... ({len(text) - limit} more characters)"
    return text.translate(_ESCAPES)


class OneLineFormatter(logging.Formatter):
    """A :class:`logging.Formatter` whose messages are :func:`one_line`."""

    def formatMessage(self, record: logging.LogRecord) -> str:
        record.message = one_line(record.message)
        return super().formatMessage(record)


def configure(level: str, fmt: str, stream: TextIO | None = None) -> None:
    """:func:`logging.basicConfig` (a no-op where the root logger has handlers) with one
    stream handler (stderr by default) formatting with :class:`OneLineFormatter`."""
    handler = logging.StreamHandler(stream)
    handler.setFormatter(OneLineFormatter(fmt))
    logging.basicConfig(level=level.upper(), handlers=[handler])
