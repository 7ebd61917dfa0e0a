"""Recorded messages as the monitor sees them: rosbag files (ROS 1, as ``rosbag record``
writes them) read with ``rosbags``, one feature row per message.

A message's stream is (topic, publisher): the bag keeps the publisher's ``callerid``
per connection. Its arrival time is the time the recorder stored with it. Labels for
evaluation name the attacking publishers (``attackers``): each of their messages is
an attack message, every other message a clean one.
"""

from __future__ import annotations

import json
import statistics
import struct
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from cryptoros.errors import ConfigError
from cryptoros.monitor.features import Crosscheck, StreamFeatures
from cryptoros.monitor.model import AlertTracker, MonitorModel


@dataclass(frozen=True)
class Row:
    topic: str
    publisher: str
    kind: str
    at: float  # arrival, seconds (the recorder's clock)
    values: tuple[float, ...]


def of_robot(robot: str, topic: str, publisher: str) -> bool:
    """A message of ``robot`` (``r0``): on its topics (``/r0/...``) or sent by its nodes
    (``/r0``, ``/r0_base``), its team packets included. An empty name: every message."""
    return not robot or topic.startswith(f"/{robot}/") or publisher == f"/{robot}" \
        or publisher.startswith(f"/{robot}_")


def _messages(bags: Iterable[Path], robot: str = "") -> Iterator[tuple[str, str, StreamFeatures, float, bytes]]:
    """(topic, publisher, the stream's features, arrival, body) of every message of the
    bags that is ``robot``'s (:func:`of_robot`), in recording order per bag; one
    StreamFeatures per stream. The other messages are observed here, not yielded: what
    the streams tell about each other (a robot's beacons) needs every one of them."""
    from rosbags.rosbag1 import Reader, ReaderError

    # what a damaged or foreign file raises in rosbags (a header that is not text, a short
    # record, a missing field): one line naming the bag, never a traceback (operator audit)
    damaged = (ReaderError, OSError, ValueError, KeyError, IndexError, struct.error)

    def read(reader: Reader, bag: Path) -> Iterator:
        try:
            yield from reader.messages()
        except damaged as exc:
            raise ConfigError(f"cannot read bag {bag}: not a readable ROS 1 bag ({exc})") from None

    for bag in bags:
        try:
            reader = Reader(Path(bag))
            reader.open()
        except damaged as exc:
            raise ConfigError(f"cannot read bag {bag}: not a readable ROS 1 bag ({exc})") from None
        try:
            streams: dict[tuple[str, str], StreamFeatures] = {}
            crosscheck = Crosscheck()  # one per recording, as one per interceptor
            for conn, stamp_ns, raw in read(reader, bag):
                publisher = getattr(conn.ext, "callerid", None) or "?"
                key = (conn.topic, publisher)
                features = streams.get(key)
                if features is None:
                    features = streams[key] = StreamFeatures(_ros1_type(conn.msgtype), topic=conn.topic,
                                                             crosscheck=crosscheck)
                if not of_robot(robot, conn.topic, publisher):
                    features.observe(raw, stamp_ns * 1e-9, stamp_ns * 1e-9)
                    continue
                yield conn.topic, publisher, features, stamp_ns * 1e-9, raw
        finally:
            reader.close()


def rows_of(bags: Iterable[Path], robot: str = "") -> Iterator[Row]:
    """Every message of the bags (of ``robot``: :func:`of_robot`), in recording order
    per bag, as a feature row."""
    for topic, publisher, features, at, raw in _messages(bags, robot):
        yield Row(topic, publisher, features.kind, at, features.observe(raw, at, at))


def _ros1_type(msgtype: str) -> str:
    return msgtype.replace("/msg/", "/")


def train(bags: Iterable[Path], **options) -> MonitorModel:
    """A model fitted on the messages of clean bags."""
    by_kind: dict[str, list[tuple[float, ...]]] = {}
    for row in rows_of(bags):
        by_kind.setdefault(row.kind, []).append(row.values)
    if not by_kind:
        raise ConfigError("the bags hold no messages to train on")
    return MonitorModel.fit(by_kind, **options)


@dataclass(frozen=True)
class Label:
    """Messages of ``publisher`` (on ``topic``; None: every topic) arriving at or after
    ``onset`` are attack messages."""

    publisher: str
    topic: str | None = None
    onset: float = 0.0

    def covers(self, row: Row) -> bool:
        return row.publisher == self.publisher and (self.topic is None or row.topic == self.topic) \
            and row.at >= self.onset


def labels_for(bag: Path) -> list[Label]:
    """The labels written beside a bag (``<bag>.labels.json``: a list of publisher,
    topic, onset), or none."""
    path = Path(f"{bag}.labels.json")
    if not path.exists():
        return []
    try:
        raw = json.loads(path.read_text())
        return [Label(str(x["publisher"]), x.get("topic"), float(x.get("onset", 0.0))) for x in raw["attacks"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"labels {path}: {exc}") from None


@dataclass
class Evaluation:
    messages: int = 0
    attack_messages: int = 0
    true_positives: int = 0
    false_positives: int = 0
    #: per attacking stream: seconds from its onset to its first alert (None: never)
    delays: dict[str, float | None] = field(default_factory=dict)
    #: per clean stream that alerted: its first alert's time
    false_alarms: dict[str, float] = field(default_factory=dict)
    #: per run (bag): whether it holds an attack and whether anything in it alerted
    runs: list[dict] = field(default_factory=list)

    @property
    def clean_messages(self) -> int:
        return self.messages - self.attack_messages

    def figures(self) -> dict:
        tp, fp = self.true_positives, self.false_positives
        return {**figures(tp, fp, self.attack_messages - tp, self.clean_messages - fp,
                          right_runs=sum(r["attacked"] == r["flagged"] for r in self.runs), runs=len(self.runs),
                          delays=self.delays),
                "clean_streams_alerted": sorted(self.false_alarms)}


def figures(tp: int, fp: int, fn: int, tn: int, *, right_runs: int, runs: int,
            delays: dict[str, float | None]) -> dict:
    """Per-message and per-run figures of a detector (ours, or the LSTM baseline's) from
    its confusion counts, runs judged right and delays after onset per attacking stream."""
    n = tp + fp + fn + tn
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    known = [d for d in delays.values() if d is not None]
    return {
        "messages": n, "attack_messages": tp + fn,
        "accuracy": round((tp + tn) / n, 4) if n else None,
        "precision": round(precision, 4), "recall": round(recall, 4),
        "f1": round(2 * precision * recall / (precision + recall), 4) if precision + recall else 0.0,
        "false_positive_rate": round(fp / (fp + tn), 5) if fp + tn else 0.0,
        "runs": runs, "run_accuracy": round(right_runs / runs, 4) if runs else None,
        "attack_streams_detected": f"{len(known)} of {len(delays)}",
        "median_delay_s": round(statistics.median(known), 3) if known else None,
        "delays_s": {k: (round(v, 3) if v is not None else None) for k, v in delays.items()},
    }


def scoring_cost_us(model: MonitorModel, bags: Iterable[Path], robot: str = "") -> dict[str, float]:
    """Microseconds per message to decode, compute the features and score, measured
    message by message as the interceptor does it (p50 and p99)."""
    samples: list[float] = []
    for _topic, _publisher, features, at, raw in _messages(bags, robot):
        t0 = time.perf_counter()
        model.score(features.kind, features.observe(raw, at, at))
        samples.append(time.perf_counter() - t0)
    samples.sort()
    if not samples:
        return {"p50": 0.0, "p99": 0.0}
    return {"p50": round(samples[len(samples) // 2] * 1e6, 1), "p99": round(samples[int(len(samples) * 0.99)] * 1e6, 1)}


def roc_points(model: MonitorModel, bags: Iterable[Path], thresholds: Iterable[float],
               robot: str = "") -> list[tuple[float, float, float]]:
    """(threshold, false positive rate, true positive rate) per message when a message is
    suspicious above ``threshold`` times its limits (1 is the model as used), with the
    model's run of ``consecutive`` suspicious messages before a message is flagged."""
    scored: list[tuple[list[float], list[bool]]] = []  # per stream: scores and labels
    for bag in bags:
        labels = labels_for(Path(bag))
        streams: dict[tuple[str, str], tuple[list[float], list[bool]]] = {}
        for row in rows_of([Path(bag)], robot):
            scores, attack = streams.setdefault((row.topic, row.publisher), ([], []))
            scores.append(model.score(row.kind, row.values).value)
            attack.append(any(lb.covers(row) for lb in labels))
        scored += streams.values()
    out = []
    for threshold in thresholds:
        tp = fp = positives = negatives = 0
        for scores, attack in scored:
            tracker = AlertTracker(model.consecutive)
            for score, is_attack in zip(scores, attack):
                tracker.update(score > threshold, bool(model.severe) and score >= model.severe * threshold)
                flagged = tracker.flagged
                positives += is_attack
                negatives += not is_attack
                tp += flagged and is_attack
                fp += flagged and not is_attack
        out.append((threshold, fp / negatives if negatives else 0.0, tp / positives if positives else 0.0))
    return out


def evaluate(model: MonitorModel, bags: Iterable[Path], attackers: Iterable[str] = (),
             robot: str = "") -> Evaluation:
    """Score every message as the interceptor would (a message is flagged once its
    stream's run of suspicious messages reached ``consecutive``, until it ends) and
    compare with the labels: every message of ``attackers``, and what the labels file
    beside each bag names (from its onset on). ``robot``: only that robot's messages
    (:func:`of_robot`; seed 001's detector watches one robot's)."""
    result = Evaluation()
    everywhere = [Label(a) for a in attackers]
    for bag in bags:
        labels = everywhere + labels_for(Path(bag))
        trackers: dict[tuple[str, str], AlertTracker] = {}
        first_message: dict[str, float] = {}
        flagged_run = False
        for row in rows_of([Path(bag)], robot):
            key = (row.topic, row.publisher)
            name = f"{Path(bag).parent.name}/{Path(bag).name}: {row.publisher} on {row.topic}"
            tracker = trackers.setdefault(key, AlertTracker(model.consecutive))
            score = model.score(row.kind, row.values)
            alerted = tracker.update(score.value > 1.0, model.is_severe(score))  # inf (NaN content) included
            flagged = tracker.flagged
            flagged_run = flagged_run or alerted
            label = next((lb for lb in labels if lb.covers(row)), None)
            result.messages += 1
            if label is not None:
                result.attack_messages += 1
                result.true_positives += flagged
                result.delays.setdefault(name, None)
                # from the onset; a label without one (--attacker): from the stream's first message
                began = label.onset or first_message.setdefault(name, row.at)
                if alerted and result.delays[name] is None:
                    result.delays[name] = row.at - began
            else:
                result.false_positives += flagged
                if alerted:
                    result.false_alarms.setdefault(name, row.at)
        result.runs.append({"bag": str(bag), "attacked": bool(labels), "flagged": flagged_run})
    return result


__all__ = ["Evaluation", "Label", "Row", "evaluate", "figures", "labels_for", "of_robot", "roc_points", "rows_of",
           "scoring_cost_us", "train"]
