"""The interceptor's runtime monitor (``[monitor]``): scores the messages a peer's
publisher sends into this host and acts on alerts.

The pump hands each chunk it forwards on a watched topic stream to
:meth:`WatchedStream.feed`, which only queues it (the chunk is already a copy: the
pump copies out of its read buffer) and schedules the scoring for later on the loop:
forwarding never waits for decoding. What every stream queued within ``batch_seconds``
is scored in one pass: at a robot's rates (tens of messages a second per stream) a
wake-up per message ran the scoring code cold each time, at several times the cost of
the same code run over a batch; an alert comes at most that much later. A stream that
queues :data:`BATCH_EARLY_CHUNKS` chunks before the timer (a flood, a burst of spoofed
poses) has the batch scored at once: at such rates a batch fills by itself, and the
stream is cut within a few messages; a gated message's scoring (below) is followed by
the queued batch on the loop's next turn. The scoring splits the chunks into TCPROS frames,
computes the message's features (:mod:`cryptoros.monitor.features`) and scores them
with the model (:mod:`cryptoros.monitor.model`); ``consecutive`` suspicious messages in
a row make an alert: a log line (``MONITOR alert``) and
``cryptoros_monitor_alerts_total``; with ``action = "quarantine"`` the publisher's
streams into this host are cut and new ones refused for ``quarantine_seconds``
(counted as denials, reason ``quarantined``).

A monitor that cannot keep up (a stream's queued bytes over ``max_backlog_bytes``) or
cannot read a stream stops watching that stream and counts it; it blocks nothing
unless ``fail_closed = true``, which cuts the stream instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import fnmatch
import heapq
import json
import logging
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from prometheus_client import Counter, Histogram

from cryptoros.errors import ConfigError, PolicyDenied
from cryptoros.lru import remember
from cryptoros.monitor.features import Crosscheck, StreamFeatures, kind_of, warm_up
from cryptoros.monitor.model import AlertTracker, MonitorModel
from cryptoros.ros1.tcpros import FrameWalker
from interceptor.statefile import write_private_json

log = logging.getLogger("cryptoros.interceptor.monitor")

ACTIONS = ("log", "quarantine")
#: publishers remembered in quarantine at once (the oldest leaves first)
MAX_QUARANTINED = 4096
#: the publisher name of a manager-wide quarantine
WHOLE_MANAGER = "*"
#: seconds between two alert log lines of one stream (every alert is counted)
ALERT_LOG_INTERVAL = 1.0
#: one scored message in this many is timed (the histogram costs as much as a pose's features)
TIMING_SAMPLE = 16
#: messages one stream scores before it hands the event loop back (a backlog of small
#: messages must not stall forwarding)
MESSAGES_PER_TURN = 256
#: chunks one stream may queue before the batch is scored at once (not at its timer)
BATCH_EARLY_CHUNKS = 8


@dataclass(frozen=True, kw_only=True)
class MonitorSettings:
    model: Path
    #: fnmatch patterns of the topics watched
    topics: tuple[str, ...] = ("*",)
    action: str = "log"
    quarantine_seconds: float = 30.0
    #: bytes queued for scoring per stream before the monitor gives that stream up
    max_backlog_bytes: int = 4 << 20
    #: watched streams at once; more are let through unwatched (and counted)
    max_streams: int = 1024
    #: a stream the monitor gives up (backlog, malformed framing) is cut instead of let through
    fail_closed: bool = False
    #: this many publishers of one manager quarantined within quarantine_seconds put the
    #: whole manager (every publisher it has or starts) in quarantine here: a compromised
    #: robot whose grant names a pattern (/pose_*) cannot evade by renaming its node
    manager_after: int = 3
    #: fnmatch patterns of topics whose messages are scored before they are forwarded
    #: (ROS 2: samples before they are republished): a suspicious one is dropped. For
    #: topics where one message does the harm (a false "map explored" is believed at
    #: once); the scoring is then on the hot path
    gate: tuple[str, ...] = ()
    #: what the streams queue within this many seconds is scored in one pass (0: each
    #: chunk on the loop's next turn); alerts come up to this much later
    batch_seconds: float = 0.25

    def __post_init__(self) -> None:
        if self.action not in ACTIONS:
            raise ConfigError(f"[monitor] action must be one of {', '.join(ACTIONS)}, got {self.action!r}")
        if not self.topics or any(not p.startswith(("/", "*")) or len(p) > 256 for p in self.topics):
            raise ConfigError("[monitor] topics must be a non-empty list of topic patterns (/name, /team/*, *)")
        if any(not p.startswith(("/", "*")) or len(p) > 256 for p in self.gate):
            raise ConfigError("[monitor] gate must be a list of topic patterns (/team/map, /team/*)")
        if not 0.0 <= self.batch_seconds <= 1.0:
            raise ConfigError(f"[monitor] batch_seconds must be within 0..1 s, got {self.batch_seconds!r}")

    def watches(self, topic: str) -> bool:
        return self.gates(topic) or any(fnmatch.fnmatchcase(topic, p) for p in self.topics)

    def gates(self, topic: str) -> bool:
        return any(fnmatch.fnmatchcase(topic, p) for p in self.gate)


class MonitorMetrics:
    def __init__(self, registry) -> None:
        self.messages = Counter("cryptoros_monitor_messages_total", "Messages scored, by topic", ["topic"],
                                registry=registry)
        self.alerts = Counter("cryptoros_monitor_alerts_total", "Alerts, by topic and the feature that exceeded",
                              ["topic", "feature"], registry=registry)
        self.given_up = Counter("cryptoros_monitor_streams_given_up_total",
                                "Streams the monitor stopped watching, by reason", ["reason"], registry=registry)
        self.quarantined = Counter("cryptoros_monitor_quarantines_total", "Publishers put in quarantine",
                                   registry=registry)
        self.dropped = Counter("cryptoros_monitor_dropped_total", "Messages of gated topics dropped as "
                               "suspicious before they were forwarded, by topic", ["topic"], registry=registry)
        self.busy = Counter("cryptoros_monitor_busy_seconds_total", "CPU seconds the monitor spent on the event "
                            "loop's thread (queueing, splitting, decoding, scoring, alerting): its share of the "
                            "interceptor's CPU",
                            registry=registry)
        self.seconds = Histogram("cryptoros_monitor_score_seconds", "Time to score one message (decode + features "
                                 "+ model)", buckets=(5e-6, 1e-5, 2e-5, 5e-5, 1e-4, 2e-4, 5e-4, 1e-3, 1e-2),
                                 registry=registry)


def release_path_for(state_path: Path) -> Path:
    """The release requests beside a quarantine file (``<manager>.quarantine.json``)."""
    return state_path.with_suffix(".release.json")


def quarantine_path(state_dir: Path, manager: str) -> Path:
    """Where an interceptor with ``state_dir`` keeps its monitor's quarantines."""
    return state_dir / f"{manager}.quarantine.json"


class Monitor:
    """One interceptor's monitor: the model, the quarantine list, the watched streams."""

    def __init__(self, settings: MonitorSettings, registry, *,
                 deny: Callable[[str, PolicyDenied, str], None] = lambda _k, _e, _w: None,
                 clock: Callable[[], float] = time.monotonic, wall: Callable[[], float] = time.time,
                 state_path: Path | None = None) -> None:
        """``state_path``: where the quarantines are kept across restarts (None: not kept):
        a restarted interceptor (a crash, an operator's restart) still refuses what it had
        quarantined, for the time left."""
        self.settings = settings
        self.wall = wall  # arrival times: clock (rates, quarantine) and wall (the age of a stamp)
        self.deny = deny
        self.model = MonitorModel.load(settings.model)
        self.model.prepare()  # its per-kind tables: at start-up, not on the first message
        # numpy (scans, team maps) and the decoders of the known types are made at start-up
        # (0.1-0.2 s of CPU here), not on the first message a peer sends, where they would
        # stall the event loop
        warm_up()
        self.metrics = MonitorMetrics(registry)
        self.clock = clock
        self._quarantine: OrderedDict[tuple[str, str], float] = OrderedDict()
        self._state_path = state_path
        self._load_quarantines()
        self.apply_releases()  # asked for while the interceptor was down
        self._streams: set[WatchedStream] = set()
        #: every open topic stream into this host (watched or not), by (manager, publisher):
        #: how to cut it when its publisher is quarantined
        self._cuts: dict[tuple[str, str], set[Callable[[], None]]] = {}
        #: what the streams tell about each other (a robot's beacons against its poses)
        self.crosscheck = Crosscheck()
        #: this host's own beacon streams read (one per publisher and topic)
        self._references: dict[tuple[str, str], WatchedStream] = {}
        #: streams with chunks queued for the next batch, and its timer
        self._due: list[WatchedStream] = []
        self._batch: asyncio.TimerHandle | asyncio.Handle | None = None
        self._batch_soon = False  # the batch is due on the loop's next turn, not on its timer

    def _schedule(self, stream: WatchedStream, *, soon: bool = False) -> None:
        """Score ``stream``'s queue in the next batch (one timer for every stream); with
        ``soon``, on the loop's next turn (a backlog scored in turns)."""
        self._due.append(stream)
        if soon or self.settings.batch_seconds <= 0:
            self._score_soon()
        elif self._batch is None:
            self._batch = asyncio.get_running_loop().call_later(self.settings.batch_seconds, self._score_batch)

    def _score_soon(self) -> None:
        """Score the batch on the loop's next turn instead of waiting out ``batch_seconds``
        (a stream queued :data:`BATCH_EARLY_CHUNKS` chunks: a flood is a batch of its own,
        cut within a few messages, not after a quarter of a second of them; a gated
        message was just scored: the batch runs right after it, while the monitor's code
        and data are still in the CPU's caches, instead of on a wake-up of its own)."""
        if self._batch_soon:
            return
        if self._batch is not None:
            self._batch.cancel()
        self._batch_soon = True
        self._batch = asyncio.get_running_loop().call_soon(self._score_batch)

    def _score_batch(self) -> None:
        """Score what the due streams queued, chunk by chunk in arrival order across the
        streams (what streams tell about each other, a robot's beacons against its poses,
        needs the order they arrived in, not one stream after the other); a stream that
        scored :data:`MESSAGES_PER_TURN` goes on in the loop's next turn."""
        t0 = time.thread_time()
        try:
            self._batch, self._batch_soon = None, False
            due, self._due = self._due, []
            for stream in due:
                stream._scheduled = False
            heap = [(stream._chunks[0][1], i, stream) for i, stream in enumerate(due)
                    if stream._chunks and not stream.closed]
            heapq.heapify(heap)
            scored = [0] * len(due)
            while heap:
                _at, i, stream = heapq.heappop(heap)
                scored[i] += stream._score_next_chunk()
                if stream.closed or not stream._chunks:
                    continue
                if scored[i] >= MESSAGES_PER_TURN:  # let the loop forward others' bytes; go on after
                    stream._scheduled = True
                    self._schedule(stream, soon=True)
                    continue
                heapq.heappush(heap, (stream._chunks[0][1], i, stream))
        finally:
            for stream in due:  # the messages scored, counted once per stream and batch
                if stream._uncounted:
                    stream._messages_counted.inc(stream._uncounted)
                    stream._uncounted = 0
            self.metrics.busy.inc(time.thread_time() - t0)

    def reconfigure(self, settings: MonitorSettings, model: MonitorModel) -> None:
        """SIGHUP: new settings and model (loaded and checked by the caller). Open streams
        are scored with the new model from their next message; quarantines stay."""
        model.prepare()
        self.settings, self.model = settings, model
        for stream in self._streams:
            stream.alerts.needed = model.consecutive

    def quarantined_for(self, manager: str, publisher: str) -> float:
        """Seconds left of this publisher's quarantine, or of its manager's (0: neither)."""
        return max(self._left((manager, publisher)), self._left((manager, WHOLE_MANAGER)))

    def _left(self, key: tuple[str, str]) -> float:
        until = self._quarantine.get(key)
        if until is None:
            return 0.0
        left = until - self.clock()
        if left <= 0:
            del self._quarantine[key]
            return 0.0
        return left

    def status(self) -> dict:
        """What ``cryptoros status`` shows of the monitor: streams watched, quarantines."""
        now = self.clock()
        return {"action": self.settings.action, "watched_streams": len(self._streams),
                "quarantined": [{"manager": m, "publisher": p, "seconds_left": round(u - now, 1)}
                                for (m, p), u in self._quarantine.items() if u > now]}

    def check_admission(self, manager: str, publisher: str) -> None:
        """Refuse a new stream from a quarantined publisher (:class:`PolicyDenied`)."""
        left = self.quarantined_for(manager, publisher)
        if left > 0:
            raise PolicyDenied("quarantined", f"{publisher} ({manager}) is quarantined by the monitor for "
                                              f"{left:.0f} s more")

    def register(self, manager: str, publisher: str, cut: Callable[[], None]) -> Callable[[], None]:
        """Know how to cut one open stream from ``publisher``; returns the undo."""
        key = (manager, publisher)
        self._cuts.setdefault(key, set()).add(cut)

        def unregister() -> None:
            cuts = self._cuts.get(key)
            if cuts is not None:
                cuts.discard(cut)
                if not cuts:
                    del self._cuts[key]
        return unregister

    def watch(self, *, manager: str, publisher: str, topic: str, typename: str,
              cut: Callable[[], None], codec: str = "ros1") -> WatchedStream | None:
        """A watched stream for the pump's tap, or None (topic not watched, or too many
        streams watched: counted). ``codec``: ``ros1`` (TCPROS frames, fed as byte
        chunks with :meth:`WatchedStream.feed`) or ``cdr`` (ROS 2 samples, fed whole
        with :meth:`WatchedStream.feed_messages`)."""
        if not self.settings.watches(topic):
            return None
        if len(self._streams) >= self.settings.max_streams:
            self.metrics.given_up.labels("max_streams").inc()
            return None
        stream = WatchedStream(self, manager, publisher, topic, typename, cut, codec)
        self._streams.add(stream)
        return stream

    def watch_reference(self, *, manager: str, publisher: str, topic: str, typename: str) -> WatchedStream | None:
        """A stream this host's own node sends out (``manager`` is this interceptor's),
        tapped only for what other streams are checked against: its robot's beacons.
        Never scored, never cut; None for every other kind, past the stream cap, or when
        the same publisher's topic is already read on its way to another peer (one copy
        of each beacon is enough)."""
        key = (publisher, topic)
        if kind_of(typename) != "beacon" or len(self._streams) >= self.settings.max_streams \
                or key in self._references:
            return None
        stream = WatchedStream(self, manager, publisher, topic, typename, lambda: None, reference=True)
        self._streams.add(stream)
        self._references[key] = stream
        return stream

    def _alert(self, stream: WatchedStream, feature: str, score: float) -> None:
        self.metrics.alerts.labels(stream.topic, feature).inc()
        action = self.settings.action
        now = self.clock()
        if action == "log" and now - stream.logged_at < ALERT_LOG_INTERVAL:
            return  # counted; a stream that alerts again and again is logged once a second
        stream.logged_at = now
        log.warning("MONITOR alert: %s from %s (%s) on %s [%s]: %s at %.1fx its limit%s", action, stream.publisher,
                    stream.manager, stream.topic, stream.typename, feature, score,
                    f"; quarantined for {self.settings.quarantine_seconds:g} s" if action == "quarantine" else "")
        if action == "quarantine":
            manager, until = stream.manager, self.clock() + self.settings.quarantine_seconds
            self._put(manager, stream.publisher, until)
            self.deny("monitor", PolicyDenied("quarantined", f"{feature} at {score:.1f}x its limit on {stream.topic}; "
                                              f"refused for {self.settings.quarantine_seconds:g} s"),
                      f"{stream.publisher} ({manager})")
            victims = [key for key in self._cuts if key == (manager, stream.publisher)]
            now = self.clock()
            others = {p for (m, p), u in self._quarantine.items() if m == manager and p != WHOLE_MANAGER and u > now}
            if len(others) >= self.settings.manager_after and self._left((manager, WHOLE_MANAGER)) == 0:
                self._put(manager, WHOLE_MANAGER, until)
                log.warning("MONITOR quarantine of manager %s: %d of its publishers quarantined within %g s",
                            manager, len(others), self.settings.quarantine_seconds)
                self.deny("monitor", PolicyDenied("quarantined", f"{len(others)} publishers quarantined; the "
                                                  f"manager is refused for {self.settings.quarantine_seconds:g} s"),
                          f"every publisher of {manager}")
                victims = [key for key in self._cuts if key[0] == manager]
            for key in victims:
                for cut in list(self._cuts.get(key, ())):
                    cut()

    def _put(self, manager: str, publisher: str, until: float) -> None:
        remember(self._quarantine, (manager, publisher), until, MAX_QUARANTINED)
        self.metrics.quarantined.inc()
        self._save_quarantines()

    # -- kept across restarts (wall-clock ends: the monotonic clock starts again)
    def _save_quarantines(self) -> None:
        path = self._state_path
        if path is None:
            return
        now, wall = self.clock(), self.wall()
        entries = [{"manager": m, "publisher": p, "until": round(wall + (u - now), 3)}
                   for (m, p), u in self._quarantine.items() if u > now]
        try:
            write_private_json(path, {"version": 1, "quarantined": entries})
        except OSError as exc:
            log.error("cannot keep the monitor's quarantines in %s: %s", path, exc)

    def release_path(self) -> Path | None:
        """Where ``cryptoros unquarantine`` asks for quarantines to be lifted."""
        return release_path_for(self._state_path) if self._state_path is not None else None

    def apply_releases(self) -> list[str]:
        """Lift the quarantines an operator asked to (``cryptoros unquarantine``: a false
        alert on a publisher a robot needs), then forget the request. Called on SIGHUP and
        at start. Returns what was lifted."""
        path = self.release_path()
        if path is None or not path.exists():
            return []
        try:
            data = json.loads(path.read_text())
            asked = [(str(e["manager"]), None if e.get("publisher") is None else str(e["publisher"]))
                     for e in data["release"][:MAX_QUARANTINED]]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.error("quarantine release request %s not read (%s): nothing lifted", path, exc)
            return []
        finally:
            with contextlib.suppress(OSError):
                path.unlink()
        lifted = []
        for manager, publisher in asked:
            for key in [k for k in self._quarantine if k[0] == manager and publisher in (None, k[1])]:
                del self._quarantine[key]
                lifted.append(f"{key[1]} ({manager})" if key[1] != WHOLE_MANAGER else f"every publisher of {manager}")
        log.warning("MONITOR quarantines lifted by the operator: %s", ", ".join(lifted) or "none matched")
        self._save_quarantines()
        return lifted

    def _load_quarantines(self) -> None:
        path = self._state_path
        if path is None or not path.exists():
            return
        try:
            data = json.loads(path.read_text())
            if not isinstance(data, dict) or data.get("version") != 1 or not isinstance(data.get("quarantined"), list):
                raise ValueError("not a version 1 quarantine list")
            now, wall = self.clock(), self.wall()
            loaded: dict[tuple[str, str], float] = {}
            kept = []
            for entry in data["quarantined"][-MAX_QUARANTINED:]:
                manager, publisher, until = entry["manager"], entry["publisher"], float(entry["until"])
                if not (isinstance(manager, str) and isinstance(publisher, str)):
                    raise ValueError(f"bad entry {entry!r:.80}")
                left = min(until - wall, self.settings.quarantine_seconds)  # a clock set back lengthens nothing
                if left > 0:
                    loaded[(manager, publisher)] = now + left
                    kept.append(f"{publisher} ({manager}) {left:.0f} s")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.error("the monitor's quarantines in %s were not read (%s): none is in force", path, exc)
            return
        self._quarantine.update(loaded)  # all of the file or none of it
        if kept:
            log.warning("MONITOR quarantines kept across the restart: %s", ", ".join(kept))


class WatchedStream:
    """One publisher's topic stream into this host, as the monitor sees it."""

    def __init__(self, monitor: Monitor, manager: str, publisher: str, topic: str, typename: str,
                 cut: Callable[[], None], codec: str = "ros1", *, reference: bool = False) -> None:
        self.monitor, self.manager, self.publisher = monitor, manager, publisher
        self.topic, self.typename, self.cut = topic, typename, cut
        self.reference = reference  # this host's own beacons: read, never scored
        self.features = StreamFeatures(typename, codec=codec, topic=topic, crosscheck=monitor.crosscheck,
                                       beacon_from=manager)
        self.alerts = AlertTracker(monitor.model.consecutive)
        self._walker = FrameWalker(what=f"monitor {topic}")
        self._chunks: deque[tuple[bytes, float, float]] = deque()
        self._backlog = 0
        self._buffer = bytearray()
        self._scheduled = False
        self.closed = False
        self.logged_at = -ALERT_LOG_INTERVAL
        self._scored = 0
        self._messages_counted = monitor.metrics.messages.labels(topic)
        self._uncounted = 0  # scored in this batch, added to the counter at its end

    def feed(self, data: bytes) -> None:
        """The pump's tap: queue a forwarded chunk of TCPROS frames (no copy, no parsing)."""
        self._queue(data, False)

    def feed_messages(self, bodies: list[bytes]) -> None:
        """Queue whole messages (the ROS 2 role's samples, already split)."""
        for body in bodies:
            self._queue(body, True)

    def _queue(self, data: bytes, whole: bool) -> None:
        if self.closed:
            return
        self._queue_now(data, whole)

    def _queue_now(self, data: bytes, whole: bool) -> None:
        """(Queueing a chunk, a deque append and at most one call_soon, is the one part of
        the monitor's work its busy counter leaves out: timing it would cost as much.)"""
        self._chunks.append((data, self.monitor.clock(), self.monitor.wall(), whole))
        self._backlog += len(data)
        if self._backlog > self.monitor.settings.max_backlog_bytes:
            self._give_up("backlog")
            return
        if not self._scheduled:
            self._scheduled = True
            self.monitor._schedule(self)
        elif len(self._chunks) >= BATCH_EARLY_CHUNKS:
            self.monitor._score_soon()

    def close(self) -> None:
        self.closed = True
        self._chunks.clear()
        self._buffer.clear()
        self.monitor._streams.discard(self)
        if self.reference and self.monitor._references.get((self.publisher, self.topic)) is self:
            del self.monitor._references[(self.publisher, self.topic)]

    def _give_up(self, reason: str) -> None:
        self.monitor.metrics.given_up.labels(reason).inc()
        log.warning("MONITOR gave up %s from %s (%s): %s%s", self.topic, self.publisher, self.manager, reason,
                    "; stream cut (fail_closed)" if self.monitor.settings.fail_closed else "")
        fail_closed = self.monitor.settings.fail_closed
        self.close()
        if fail_closed:
            self.cut()

    def gate(self, body: bytes) -> bool:
        """A gated topic's message, scored before it is forwarded: False drops it (it
        is suspicious, or the stream is already cut). Scoring errors drop it too."""
        if self.closed:
            return False
        t0 = time.thread_time()
        try:
            return self._gate_timed(body)
        finally:
            monitor = self.monitor
            if monitor._due:  # the queued batch on the loop's next turn, while the monitor's code is warm
                monitor._score_soon()
            monitor.metrics.busy.inc(time.thread_time() - t0)

    def _gate_timed(self, body: bytes) -> bool:
        monitor = self.monitor
        try:
            self._messages_counted.inc()
            suspicious = self._score(body, monitor.clock(), monitor.wall())
        except Exception:  # noqa: BLE001 - a gate that cannot decide denies
            log.exception("MONITOR gate on %s from %s failed: message dropped", self.topic, self.publisher)
            suspicious = True
        if suspicious:
            monitor.metrics.dropped.labels(self.topic).inc()
        return not suspicious

    def _score(self, body: bytes, now: float, wall: float) -> bool:
        """Score one message (features, model, alert): whether it is suspicious. One
        message in :data:`TIMING_SAMPLE` is timed for ``cryptoros_monitor_score_seconds``."""
        monitor = self.monitor
        model, features = monitor.model, self.features
        self._scored += 1
        if self._scored % TIMING_SAMPLE:
            score = model.score(features.kind, features.observe(body, now, wall))
        else:
            t0 = time.perf_counter()
            score = model.score(features.kind, features.observe(body, now, wall))
            monitor.metrics.seconds.observe(time.perf_counter() - t0)
        if not score.value > 1.0:  # the common case: not suspicious, so not severe either
            self.alerts.update(False)
            return False
        if self.alerts.update(True, model.is_severe(score)):
            monitor._alert(self, score.feature, score.value)
        return True

    def _score_next_chunk(self) -> int:
        """Score the oldest queued chunk (its whole messages; a frame still arriving stays
        in the buffer): how many messages it held."""
        monitor = self.monitor
        data, now, wall, whole = self._chunks.popleft()
        self._backlog -= len(data)
        buffer = self._buffer
        if whole:
            bodies, stop, error = [data], 0, None
        elif not buffer and len(data) >= 4 and int.from_bytes(data[:4], "little") + 4 == len(data):
            bodies, stop, error = [data[4:]], 0, None  # one whole frame (the commonest chunk)
        elif not buffer:  # the chunk starts with a frame (the common case): its bodies sliced from it
            spans, stop, _pending, error = self._walker.split(data)
            bodies = [data[start:end] for start, end in spans]
            if stop < len(data):
                buffer += memoryview(data)[stop:]
            stop = 0
        else:
            buffer += data
            spans, stop, _pending, error = self._walker.split(buffer)
            bodies = [bytes(buffer[start:end]) for start, end in spans]
        if self.reference:  # read only while a pose stream of its robot is followed
            if monitor.crosscheck.follows(self.manager):
                for body in bodies:
                    self.features.reference(body, now, wall)
        else:
            self._uncounted += len(bodies)
            for body in bodies:
                self._score(body, now, wall)
                if self.closed:
                    return len(bodies)
        if whole:
            return len(bodies)
        if stop:
            del buffer[:stop]
        if error is not None:
            self._give_up("malformed")
        elif len(buffer) > monitor.settings.max_backlog_bytes:  # one frame bigger than the backlog
            self._give_up("backlog")
        return len(bodies)


__all__ = ["ACTIONS", "Monitor", "MonitorSettings", "WatchedStream", "quarantine_path", "release_path_for"]
