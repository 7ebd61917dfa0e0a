"""The per-stream gate of the public listener, with no I/O (in the spirit of h11).

Every stream another interceptor opens to this one passes the same steps before a
role sees a byte of it::

    bytes --receive_data--> [preamble] --PreambleReceived--> (the edge verifies the token)
          --admit(access, ...)--> Admitted | PolicyDenied --accept(own token) / refuse()--> bytes
          --trailing_data--> whatever the peer sent behind its preamble, for the role

The gate never touches a socket or a clock: the edge (``interceptor/gateway.py``)
reads, verifies the token (which may need the authorization server's JWKS), and hands
the facts in; the gate decides, in a fixed order, and says why with a reason code.
:class:`PendingStreams` bounds the streams whose token is not verified yet, per source
address and per certificate; :func:`feed_problem` is the fail-closed rule for a stale
revocation feed (for the streams this interceptor opens too), :data:`FEED_HINTS` what to
do about it. Both are plain state, tested without sockets (tests/unit/test_gate.py).
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass

from cryptoros.errors import LocalProtocolError, PolicyDenied
from cryptoros.grants import Grants
from cryptoros.tokens import AccessToken
from cryptoros.tunnel import NEED_DATA, Preamble, PreambleReader, PreambleReply, encode

#: The purpose with which two interceptors only show each other their tokens.
REFRESH = "refresh"


@dataclass(frozen=True, kw_only=True, slots=True)
class PreambleReceived:
    """The peer's preamble, parsed: its token must be verified before :meth:`StreamGate.admit`."""

    preamble: Preamble


@dataclass(frozen=True, kw_only=True, slots=True)
class Admitted:
    """What the gate let through: whose stream, for what, to which target."""

    access: AccessToken
    purpose: str
    target: str
    #: what the role's target check resolved the target to (an exported endpoint), if anything
    resolved: object = None
    #: the stream's judge, when its target alone tells which grant it needs (:class:`Target`)
    judge: Callable[[Grants], None] | None = None


@dataclass(frozen=True)
class Target:
    """What a role's target check returns: the target resolved (handed to the role with
    the stream) and, when the target alone tells which of the peer's grants the stream
    needs, its judge: run by the gate on the peer's token before the reply, and by the
    verifier again on every fresher token it shows (a removed grant cuts the stream).
    A stream whose grant is known only later (a TCPROS header) declares its judge on its
    watch then (:meth:`~interceptor.verifier.StreamWatch.judge_by`)."""

    resolved: object = None
    judge: Callable[[Grants], None] | None = None


class _State(enum.Enum):
    PREAMBLE = "awaiting preamble"
    TOKEN = "awaiting token verification"
    ADMITTED = "admitted"
    REPLIED = "replied"
    REFUSED = "refused"


#: Checks a role registers per purpose: raise PolicyDenied for a target it does not
#: serve, else return the :class:`Target` it resolves to.
TargetCheck = Callable[[Preamble], Target]


class StreamGate:
    """One inbound stream's admission: preamble -> token -> purpose, feed, limits -> reply.

    ``purposes`` maps every purpose some role serves to its target check; a purpose
    no role registered is refused (``bad_purpose``): fail closed by construction.
    """

    def __init__(self, purposes: Mapping[str, TargetCheck]) -> None:
        self._purposes = purposes
        self._reader = PreambleReader(Preamble)
        self._state = _State.PREAMBLE
        self._preamble: Preamble | None = None

    @property
    def state(self) -> str:
        return self._state.value

    def receive_data(self, data: bytes) -> None:
        if self._state is not _State.PREAMBLE:
            raise LocalProtocolError(f"receive_data while {self._state.value}: later bytes are the role's")
        self._reader.receive_data(data)

    def next_event(self):
        """:class:`PreambleReceived` once the preamble is whole, else ``NEED_DATA``.
        A malformed preamble raises RemoteProtocolError (the caller refuses)."""
        if self._state is not _State.PREAMBLE:
            raise LocalProtocolError(f"next_event while {self._state.value}")
        event = self._reader.next_event()
        if event is NEED_DATA:
            return NEED_DATA
        if not isinstance(event, Preamble):  # pragma: no cover - PreambleReader(Preamble) yields only these
            raise LocalProtocolError(f"unexpected event {event!r}")
        self._preamble = event
        self._state = _State.TOKEN
        return PreambleReceived(preamble=event)

    def admit(
        self,
        access: AccessToken,
        *,
        feed: PolicyDenied | None,
        allow_new_stream: Callable[[str], bool],
        open_streams: int,
        max_streams: int,
    ) -> Admitted:
        """Decide, once the edge verified the preamble's token (``access``): a stale or
        refused revocation feed, a purpose or target no role serves, the peer's new-stream
        rate and its open streams each refuse, in that order. Raises PolicyDenied."""
        if self._state is not _State.TOKEN or self._preamble is None:
            raise LocalProtocolError(f"admit while {self._state.value}")
        self._state = _State.REFUSED  # until every check passed
        if feed is not None:
            raise feed
        preamble = self._preamble
        target = Target()
        if preamble.purpose != REFRESH:
            check = self._purposes.get(preamble.purpose)
            if check is None:
                raise PolicyDenied("bad_purpose", f"purpose {preamble.purpose} is not served here")
            target = check(preamble)
            if target.judge is not None:
                target.judge(access.grants)
        if not allow_new_stream(access.subject):
            raise PolicyDenied("rate_limited", "too many new streams per second")
        if open_streams >= max_streams:
            raise PolicyDenied("connection_limit", f"{max_streams} streams open")
        self._state = _State.ADMITTED
        return Admitted(access=access, purpose=preamble.purpose, target=preamble.target, resolved=target.resolved,
                        judge=target.judge)

    def accept(self, own_token: str) -> bytes:
        """The reply to an admitted stream: our token (narrowed for this peer)."""
        if self._state is not _State.ADMITTED:
            raise LocalProtocolError(f"accept while {self._state.value}")
        self._state = _State.REPLIED
        return encode(PreambleReply(ok=True, token=own_token))

    def refuse(self) -> bytes:
        """The opaque refusal: the log says why, the peer learns nothing."""
        self._state = _State.REFUSED
        return encode(PreambleReply(ok=False, error="denied"))

    @property
    def trailing_data(self) -> bytes:
        """What the peer sent behind its preamble (a first request or header): the
        role's, handed on explicitly. Only after :meth:`accept`."""
        if self._state is not _State.REPLIED:
            raise LocalProtocolError(f"trailing_data while {self._state.value}")
        return self._reader.trailing_data()


def feed_problem(*, refused: bool, last_feed_at: float | None, now: float, max_age: float) -> PolicyDenied | None:
    """Fail closed when the revocation feed is stale (a revoked peer could be let in)
    or the authorization server refuses our certificate (revoked by the CA)."""
    if refused:
        return PolicyDenied("authz_refused", "the authorization server refuses this interceptor's certificate "
                                             "(HTTP 401: revoked by the CA?)")
    # the same text however old the feed is: refusals are listed by it (status shows the age)
    if last_feed_at is None:
        return PolicyDenied("feed_stale", "revocation feed never read")
    if now - last_feed_at > max_age:
        return PolicyDenied("feed_stale", f"revocation feed older than max_feed_age ({max_age:.0f} s)")
    return None


#: The reasons :func:`feed_problem` refuses with: this interceptor's own state, no peer's doing
FEED_REASONS = frozenset({"feed_stale", "authz_refused"})
#: What to do about a refusal of :func:`feed_problem`, listed with it (``cryptoros denials``)
FEED_HINTS = {
    "feed_stale": "bring the authorization server back; cryptoros status shows the feed's age",
}


def held_feed_wait(feed_wait: float, *, request_timeout: float, max_feed_age: float,
                   heartbeat: float = 0.0) -> float:
    """How long a long-poll of the feed may be held: ``feed_wait`` when the server's
    heartbeats (each keeps the feed fresh) come often enough to keep it fresh, else short
    enough for its answer (which may take ``request_timeout`` more, and a second of
    slack) to come before the feed counts as stale (``max_feed_age``); 0, plain polling,
    when nothing is left."""
    if heartbeat and 2 * heartbeat + request_timeout + 1.0 <= max_feed_age:
        return feed_wait
    return max(0.0, min(feed_wait, max_feed_age - request_timeout - 1.0))

class PendingStreams:
    """Streams whose token is not verified yet, counted per key (a source address, a
    certificate): a peer that dribbles its preamble holds at most ``cap`` of them."""

    def __init__(self) -> None:
        self._counts: dict[Hashable, int] = {}

    def enter(self, key: Hashable, cap: int, what: str) -> None:
        if self._counts.get(key, 0) >= cap:
            raise PolicyDenied("pending_limit", f"{cap} unauthenticated streams from this {what} already")
        self._counts[key] = self._counts.get(key, 0) + 1

    def count(self, key: Hashable) -> int:
        return self._counts.get(key, 0)

    def leave(self, key: Hashable) -> None:
        left = self._counts.get(key, 0) - 1
        if left > 0:
            self._counts[key] = left
        else:
            self._counts.pop(key, None)

    def __len__(self) -> int:
        return len(self._counts)


__all__ = ["FEED_HINTS", "FEED_REASONS", "REFRESH", "Admitted", "PendingStreams", "PreambleReceived", "StreamGate", "feed_problem"]
