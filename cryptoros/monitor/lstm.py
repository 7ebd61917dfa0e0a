"""Seed 001's detector, reimplemented as the baseline (PyTorch on the CPU, the optional
``lstm`` extra: ``pip install 'cryptoros[lstm]'``).

What the paper did (its text and public code): one 367-float row per message of the
robot (x, y of the pose; linear.x, angular.z of ``cmd_vel``; 360 laser ranges; a one-hot
flag of the topic), the first 2,000 rows of a 20 s bag as one sequence with one label
per bag, Keras LSTM(150) -> Dense(1, sigmoid), Adam, binary cross-entropy, 250 epochs,
batch 64. Here the same network, loss, optimizer, epochs and batch, on the same rows,
with two changes the data forces and one fix:

* the demo's runs hold a few hundred messages of the robot, not 2,000, and there are a
  dozen runs, not 206 bags: a sequence is a window of ``window`` rows (default 200,
  half-overlapping), labelled 1 when it holds a message of the compromised stream at or
  after the onset;
* the demo's scans have 72 beams: they fill the first 72 of the 360 range slots;
* the paper's feature code fills only ``ranges[0]``; here every beam is filled.

Per message, a message is flagged when the window that ends with it (the sequence of the
``window`` rows up to it) is classified as attacked: the per-message figures and the
detection delay come from the same network run as a sliding window.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cryptoros.errors import ConfigError
from cryptoros.monitor.dataset import figures, labels_for

ROW = 367
RANGES = 360
TOPIC_KINDS = ("pose", "cmd_vel", "scan")


def _torch():
    try:
        import torch
    except ImportError:
        raise ConfigError("the LSTM baseline needs PyTorch: pip install 'cryptoros[lstm]'") from None
    return torch


@dataclass
class Sequence:
    rows: np.ndarray  # (n, 367)
    attack: np.ndarray  # (n,) bool: the message is an attack message
    at: np.ndarray  # (n,) arrival time
    onset: float | None  # of the attack in this run, if any
    name: str = ""


def paper_rows(bag: Path, robot: str = "r0") -> Sequence:
    """The robot's messages of one bag as the paper's rows, in arrival order."""
    from rosbags.rosbag1 import Reader

    from cryptoros.ros1 import msgs

    labels = labels_for(bag)
    rows, attack, at = [], [], []
    decoders = {}
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic.startswith(f"/{robot}/")]
        for conn, stamp_ns, raw in reader.messages(connections=conns):
            kind = conn.topic.rsplit("/", 1)[1]
            if kind not in TOPIC_KINDS:
                continue
            typename = conn.msgtype.replace("/msg/", "/")
            decode = decoders.get(typename) or decoders.setdefault(typename, msgs.deserializer(typename))
            row = np.zeros(ROW, dtype=np.float32)
            try:
                m = decode(raw)
            except Exception:  # noqa: BLE001 - a message that does not decode is a row of zeros
                m = None
            if m is not None and kind == "pose":
                row[0], row[1] = m.pose.position.x, m.pose.position.y
            elif m is not None and kind == "cmd_vel":
                row[2], row[3] = m.linear.x, m.angular.z
            elif m is not None and kind == "scan":
                r = np.nan_to_num(np.asarray(m.ranges, dtype=np.float32)[:RANGES], posinf=0.0, neginf=0.0)
                row[4:4 + len(r)] = r
            row[4 + RANGES + TOPIC_KINDS.index(kind)] = 1.0
            t = stamp_ns * 1e-9
            publisher = getattr(conn.ext, "callerid", None) or "?"
            rows.append(row)
            at.append(t)
            attack.append(any(lb.publisher == publisher and lb.topic in (None, conn.topic) and t >= lb.onset
                              for lb in labels))
    onset = min((lb.onset for lb in labels), default=None)
    return Sequence(np.asarray(rows, dtype=np.float32).reshape(-1, ROW), np.asarray(attack, dtype=bool),
                    np.asarray(at), onset, f"{Path(bag).parent.name}")


def windows(seq: Sequence, window: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Half-overlapping windows of a sequence and their labels."""
    xs, ys = [], []
    for end in range(window, len(seq.rows) + 1, stride):
        xs.append(seq.rows[end - window:end])
        ys.append(float(seq.attack[end - window:end].any()))
    return np.asarray(xs, dtype=np.float32).reshape(-1, window, ROW), np.asarray(ys, dtype=np.float32)


@dataclass
class LstmBaseline:
    window: int = 200
    epochs: int = 250
    batch: int = 64
    hidden: int = 150
    seed: int = 1
    train_seconds: float = 0.0
    _net: object = field(default=None, repr=False)
    _scale: np.ndarray | None = field(default=None, repr=False)

    def _build(self):
        torch = _torch()

        class Net(torch.nn.Module):
            def __init__(self, hidden: int) -> None:
                super().__init__()
                self.lstm = torch.nn.LSTM(ROW, hidden, batch_first=True)
                self.out = torch.nn.Linear(hidden, 1)

            def forward(self, x):
                seq, _ = self.lstm(x)
                return torch.sigmoid(self.out(seq[:, -1, :])).squeeze(-1)

        torch.manual_seed(self.seed)
        return Net(self.hidden)

    def fit(self, sequences: Iterable[Sequence]) -> LstmBaseline:
        torch = _torch()
        torch.set_num_threads(1)
        xs, ys = [], []
        for seq in sequences:
            x, y = windows(seq, self.window, max(1, self.window // 2))
            xs.append(x)
            ys.append(y)
        x = np.concatenate(xs) if xs else np.zeros((0, self.window, ROW), np.float32)
        y = np.concatenate(ys) if ys else np.zeros(0, np.float32)
        if len(x) == 0 or len(set(y.tolist())) < 2:
            raise ConfigError("the LSTM needs windows of both labels: clean and attacked runs with enough messages")
        self._scale = np.maximum(np.abs(x).reshape(-1, ROW).max(axis=0), 1e-6)  # the paper feeds raw values; scaled
        net = self._build()
        opt = torch.optim.Adam(net.parameters())
        loss = torch.nn.BCELoss()
        tx, ty = torch.from_numpy(x / self._scale), torch.from_numpy(y)
        start = time.process_time()
        gen = torch.Generator().manual_seed(self.seed)
        for _ in range(self.epochs):
            order = torch.randperm(len(tx), generator=gen)
            for i in range(0, len(tx), self.batch):
                idx = order[i:i + self.batch]
                opt.zero_grad()
                loss(net(tx[idx]), ty[idx]).backward()
                opt.step()
        self.train_seconds = time.process_time() - start
        self._net = net
        return self

    def flag_messages(self, seq: Sequence, threshold: float = 0.5) -> tuple[np.ndarray, float]:
        """Per message: attacked by the window ending with it (the first ``window - 1``
        messages have no full window: not flagged). And the CPU seconds per message."""
        out, cpu = self.outputs(seq)
        return out > threshold, cpu

    def outputs(self, seq: Sequence) -> tuple[np.ndarray, float]:
        """Per message, the network's output for the window ending with it (0 where no
        full window), and the CPU seconds per message."""
        torch = _torch()
        flags = np.zeros(len(seq.rows), dtype=np.float32)
        if len(seq.rows) < self.window or self._net is None:
            return flags, 0.0
        x = np.lib.stride_tricks.sliding_window_view(seq.rows / self._scale, (self.window, ROW))[:, 0]
        start = time.process_time()
        with torch.no_grad():
            out = []
            for i in range(0, len(x), 256):
                out.append(self._net(torch.from_numpy(np.ascontiguousarray(x[i:i + 256], dtype=np.float32))).numpy())
        cpu = (time.process_time() - start) / max(1, len(x))
        flags[self.window - 1:] = np.concatenate(out)
        return flags, cpu


def evaluate_lstm(model: LstmBaseline, sequences: Iterable[Sequence], threshold: float = 0.5,
                  outputs: list[tuple[np.ndarray, float]] | None = None) -> dict:
    """The baseline's figures at an output ``threshold`` (the paper's 0.5), in the shape
    of ``Evaluation.figures()``. ``outputs``: the network's, per sequence, if computed."""
    tp = fp = fn = tn = 0
    runs_right = runs = 0
    delays: dict[str, float | None] = {}
    cpu = []
    sequences = list(sequences)
    for seq, (out, per_message) in zip(sequences, outputs or [model.outputs(seq) for seq in sequences]):
        flags = out > threshold
        cpu.append(per_message)
        tp += int((flags & seq.attack).sum())
        fp += int((flags & ~seq.attack).sum())
        fn += int((~flags & seq.attack).sum())
        tn += int((~flags & ~seq.attack).sum())
        attacked = bool(seq.attack.any())
        runs += 1
        runs_right += attacked == bool(flags.any())
        if attacked:
            hits = np.nonzero(flags & (seq.at >= (seq.onset or 0.0)))[0]
            delays[seq.name] = float(seq.at[hits[0]] - seq.onset) if len(hits) and seq.onset is not None else None
    return {**figures(tp, fp, fn, tn, right_runs=runs_right, runs=runs, delays=delays),
            "cpu_us_per_message": round(1e6 * (sum(cpu) / len(cpu)), 1) if cpu else None,
            "train_cpu_s": round(model.train_seconds, 1), "threshold": round(threshold, 6)}


def threshold_for(sequences: list[Sequence], outputs: list[tuple[np.ndarray, float]], max_fpr: float) -> float:
    """The lowest output threshold at which the network flags at most ``max_fpr`` of the
    clean messages (to compare detectors at the same false-positive rate)."""
    clean = np.concatenate([out[~seq.attack] for seq, (out, _) in zip(sequences, outputs)] or [np.zeros(0)])
    if not clean.size:
        return 0.5
    allowed = int(np.floor(max_fpr * clean.size))
    ranked = np.sort(clean)[::-1]  # a threshold at the (allowed+1)-th highest clean output flags `allowed` of them
    return float(np.nextafter(ranked[allowed], np.inf)) if allowed < ranked.size else 0.0


def lstm_roc_points(model: LstmBaseline, sequences: list[Sequence],
                    thresholds: Iterable[float]) -> list[tuple[float, float, float]]:
    """(threshold, false positive rate, true positive rate) per message over the
    network's output threshold."""
    outputs = [(model.outputs(seq)[0], seq.attack) for seq in sequences]
    points = []
    for t in thresholds:
        tp = sum(int(((o > t) & a).sum()) for o, a in outputs)
        fp = sum(int(((o > t) & ~a).sum()) for o, a in outputs)
        pos = sum(int(a.sum()) for _, a in outputs)
        neg = sum(int((~a).sum()) for _, a in outputs)
        points.append((t, fp / neg if neg else 0.0, tp / pos if pos else 0.0))
    return points


__all__ = ["LstmBaseline", "Sequence", "evaluate_lstm", "lstm_roc_points", "paper_rows", "threshold_for", "windows"]
