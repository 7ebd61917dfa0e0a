"""Seed 001's detector, reimplemented as the baseline (PyTorch on the CPU, the optional
``lstm`` extra: ``pip install 'cryptoros[lstm]'``).

The paper: one layer of 160 LSTM cells and one output neuron, "310,951 trainable
parameters", trained on recorded bags (one label per 20 s bag), 92 % on unseen data,
53.4 us per message. Its public code: one 367-float row per message of the robot (x, y of
the pose; linear.x, angular.z of ``cmd_vel``; 360 laser ranges; a one-hot flag of the
topic), Keras LSTM -> Dense(1, sigmoid), Adam, binary cross-entropy, 250 epochs, batch
64. Keras counts 4 x (h x (367 + h) + h) + h + 1 parameters: 310,951 is exactly h = 150
cells on 367 inputs (the code's LSTM(150)); 160 cells make 338,081. :func:`param_count`
gives both; the network here counts as Keras does (PyTorch's second LSTM bias is held
at zero and not trained, so the trainable count is Keras's).

Three ways to train and score, ``mode``:

* ``"bag"``: the paper's own experiment (its proof of concept): "data was fed one entire
  bag at a time ... a single classification out at the end". A run is one sequence,
  labelled 1 when it holds an attack message; the output after its last row is the
  verdict, scored per run (:func:`evaluate_runs`). Runs are read at the length of the
  longest trained on (zero rows in front, or the first rows cut).
* ``"window"``: its one label per sequence, on shorter sequences: a window of ``window``
  rows (the demo's runs hold a few hundred messages of the robot, not 2,000), labelled 1
  when it holds an attack message; a message is flagged when the window ending with it is.
  Every clean message of an attacked window is then flagged too.
* ``"message"``: what the paper names as the better approach ("a classification for
  each message individually ... a single flag to be set": Keras's
  ``return_sequences``): one output per row, trained on each message's own label over
  windows of ``window`` rows side by side, and run over a recording the same way (each
  message's output sees the rows before it in its window).

All: the positive class weighted by negatives over positives (``pos_weight``), Adam,
mini-batches of 64, and, when validation sequences are given, early stopping on the
validation loss (``patience`` epochs without improvement; the best epoch's weights are
kept). ``inputs="paper+dt"`` adds two columns to the paper's row: the log of the time
since the robot's previous message and since the previous one on the same topic (the
paper's row has no time, so a flood is visible only by its share of the rows).

The demo's scans have 72 beams: they fill the first 72 of the 360 range slots; the
paper's feature code fills only ``ranges[0]``, here every beam is filled.
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
PAPER_PARAMETERS = 310_951
INPUTS = {"paper": ROW, "paper+dt": ROW + 2}


def param_count(hidden: int, inputs: int = ROW) -> int:
    """Keras's count for LSTM(hidden) -> Dense(1) on ``inputs`` floats per row."""
    return 4 * (hidden * (inputs + hidden) + hidden) + hidden + 1


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
    kinds: np.ndarray | None = None  # (n,) index into TOPIC_KINDS

    def inputs(self, which: str) -> np.ndarray:
        """The rows as the network reads them: the paper's, or with the two time columns."""
        if which == "paper":
            return self.rows
        kinds = self.kinds if self.kinds is not None else np.argmax(self.rows[:, 4 + RANGES:], axis=1)
        gap = np.diff(self.at, prepend=self.at[:1] if len(self.at) else self.at)
        same = np.zeros(len(self.at), dtype=np.float64)
        last: dict[int, float] = {}
        for i, (k, t) in enumerate(zip(kinds.tolist(), self.at.tolist())):
            same[i] = t - last[k] if k in last else 0.0
            last[k] = t
        extra = np.log1p(np.stack([np.maximum(gap, 0), np.maximum(same, 0)], axis=1) * 1000.0).astype(np.float32)
        return np.concatenate([self.rows, extra], axis=1)


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
    arr = np.asarray(rows, dtype=np.float32).reshape(-1, ROW)
    return Sequence(arr, np.asarray(attack, dtype=bool), np.asarray(at), onset, f"{Path(bag).parent.name}",
                    np.argmax(arr[:, 4 + RANGES:], axis=1) if len(arr) else np.zeros(0, dtype=int))


def windows(seq: Sequence, window: int, stride: int, inputs: str = "paper",
            per_message: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Windows of a sequence (``stride`` apart) and their labels: one per window (any
    attack message in it), or with ``per_message`` one per row."""
    rows = seq.inputs(inputs)
    xs, ys = [], []
    for end in range(window, len(rows) + 1, stride):
        xs.append(rows[end - window:end])
        ys.append(seq.attack[end - window:end].astype(np.float32) if per_message
                  else float(seq.attack[end - window:end].any()))
    shape = (-1, window) if per_message else (-1,)
    return (np.asarray(xs, dtype=np.float32).reshape(-1, window, rows.shape[1]),
            np.asarray(ys, dtype=np.float32).reshape(shape))


@dataclass
class LstmBaseline:
    window: int = 200
    epochs: int = 250
    batch: int = 64
    hidden: int = 160
    seed: int = 1
    mode: str = "message"  # or "window" (a label per window), or "bag" (the paper's: a label per run)
    inputs: str = "paper"  # or "paper+dt"
    patience: int = 15  # epochs without a better validation loss before stopping
    balance: bool = True  # weight the positive class by negatives / positives
    train_seconds: float = 0.0
    epochs_run: int = 0
    best_epoch: int = 0
    history: list = field(default_factory=list, repr=False)  # (epoch, train loss, validation loss)
    _net: object = field(default=None, repr=False)
    _scale: np.ndarray | None = field(default=None, repr=False)
    _length: int | None = field(default=None, repr=False)  # ``bag`` mode: the rows of a run as trained

    @property
    def row(self) -> int:
        return INPUTS[self.inputs]

    def _build(self):
        torch = _torch()
        per_message = self.mode == "message"

        class Net(torch.nn.Module):
            def __init__(self, inputs: int, hidden: int) -> None:
                super().__init__()
                self.lstm = torch.nn.LSTM(inputs, hidden, batch_first=True)
                with torch.no_grad():  # Keras has one bias per gate: the second one held at zero
                    self.lstm.bias_hh_l0.zero_()
                self.lstm.bias_hh_l0.requires_grad_(False)
                self.out = torch.nn.Linear(hidden, 1)

            def forward(self, x):  # logits
                seq, _ = self.lstm(x)
                return self.out(seq if per_message else seq[:, -1, :]).squeeze(-1)

        torch.manual_seed(self.seed)
        return Net(self.row, self.hidden)

    def parameters(self) -> int:
        """Trainable parameters of the network as built (Keras's count)."""
        net = self._net if self._net is not None else self._build()
        return sum(p.numel() for p in net.parameters() if p.requires_grad)

    def _bag_rows(self, sequences: Iterable[Sequence], length: int | None = None) -> np.ndarray:
        """Whole runs, each padded with zero rows in front to ``length`` (default: the
        longest): the network's output after a run's last message is its verdict."""
        runs = [seq.inputs(self.inputs) for seq in sequences]
        length = length or max((len(r) for r in runs), default=0)
        x = np.zeros((len(runs), length, self.row), np.float32)
        for i, rows in enumerate(runs):
            rows = rows[-length:]
            x[i, length - len(rows):] = rows
        return x

    def _data(self, sequences: Iterable[Sequence]) -> tuple[np.ndarray, np.ndarray]:
        if self.mode == "bag":
            sequences = [seq for seq in sequences if len(seq.rows)]
            return (self._bag_rows(sequences, self._length),
                    np.asarray([float(seq.attack.any()) for seq in sequences], np.float32))
        per_message = self.mode == "message"
        # windows: half-overlapping (the paper's one label each); per message: side by side
        # (every message has its own label either way)
        stride = self.window if per_message else max(1, self.window // 2)
        xs, ys = [], []
        for seq in sequences:
            if len(seq.rows) < self.window:
                continue
            x, y = windows(seq, self.window, stride, self.inputs, per_message)
            xs.append(x)
            ys.append(y)
        shape = (0, self.window) if per_message else (0,)
        return (np.concatenate(xs) if xs else np.zeros((0, self.window, self.row), np.float32),
                np.concatenate(ys) if ys else np.zeros(shape, np.float32))

    def fit(self, sequences: Iterable[Sequence], validation: Iterable[Sequence] = (),
            progress=None) -> LstmBaseline:
        torch = _torch()
        torch.set_num_threads(1)
        self._length = None
        x, y = self._data(sequences)
        if self.mode == "bag":
            self._length = x.shape[1]  # every run is read at this length, padded or cut in front
        if len(x) == 0 or len(set(np.unique(y).tolist())) < 2:
            raise ConfigError("the LSTM needs windows of both labels: clean and attacked runs with enough messages")
        self._scale = np.maximum(np.abs(x).reshape(-1, self.row).max(axis=0), 1e-6)  # the paper feeds raw values; scaled
        vx, vy = self._data(validation)
        net = self._build()
        opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad])
        pos = float(y.sum())
        weight = torch.tensor((y.size - pos) / pos if self.balance and pos else 1.0)
        loss_fn = torch.nn.BCEWithLogitsLoss(pos_weight=weight)
        tx, ty = torch.from_numpy(x / self._scale), torch.from_numpy(y)
        tvx, tvy = torch.from_numpy(vx / self._scale), torch.from_numpy(vy)
        start = time.process_time()
        gen = torch.Generator().manual_seed(self.seed)
        best, best_state, waited = float("inf"), None, 0
        self.history = []
        for epoch in range(1, self.epochs + 1):
            net.train()
            order = torch.randperm(len(tx), generator=gen)
            total = 0.0
            for i in range(0, len(tx), self.batch):
                idx = order[i:i + self.batch]
                opt.zero_grad()
                loss = loss_fn(net(tx[idx]), ty[idx])
                loss.backward()
                opt.step()
                total += loss.item() * len(idx)
            val = None
            if len(tvx):
                net.eval()
                with torch.no_grad():
                    val = float(loss_fn(net(tvx), tvy))
            self.history.append((epoch, total / len(tx), val))
            self.epochs_run = epoch
            if progress is not None and (epoch == 1 or epoch % 10 == 0):
                progress(f"  epoch {epoch}: train loss {total / len(tx):.4f}"
                         + (f", validation loss {val:.4f}" if val is not None else ""))
            if val is None:
                continue
            if val < best - 1e-4:
                best, waited, self.best_epoch = val, 0, epoch
                best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
            else:
                waited += 1
                if waited >= self.patience:
                    break
        if best_state is not None:
            net.load_state_dict(best_state)
        else:
            self.best_epoch = self.epochs_run
        net.eval()
        self.train_seconds = time.process_time() - start
        self._net = net
        return self

    def run_output(self, seq: Sequence) -> float:
        """``bag`` mode: the network's output (a probability) after the run's last message."""
        torch = _torch()
        if self._net is None or len(seq.rows) == 0:
            return 0.0
        with torch.no_grad():
            logits = self._net(torch.from_numpy(self._bag_rows([seq], self._length) / self._scale))
        return float(torch.sigmoid(logits)[0])

    def flag_messages(self, seq: Sequence, threshold: float = 0.5) -> tuple[np.ndarray, float]:
        """Per message: attacked or not (``window`` mode: the first ``window - 1``
        messages have no full window and are not flagged). And the CPU seconds per message."""
        out, cpu = self.outputs(seq)
        return out > threshold, cpu

    def outputs(self, seq: Sequence) -> tuple[np.ndarray, float]:
        """Per message, the network's output (a probability), and the CPU seconds per
        message. ``message`` mode: the recording in windows side by side."""
        torch = _torch()
        flags = np.zeros(len(seq.rows), dtype=np.float32)
        if self._net is None or len(seq.rows) == 0:
            return flags, 0.0
        rows = seq.inputs(self.inputs) / self._scale
        if self.mode == "message":
            # in chunks of ``window`` rows, each from a zero state: what the network was
            # trained on (a whole recording in one pass drifts past the lengths it saw)
            n, w = len(rows), self.window
            padded = np.zeros((-(-n // w) * w, rows.shape[1]), dtype=np.float32)
            padded[:n] = rows
            start = time.process_time()
            with torch.no_grad():
                out = torch.sigmoid(self._net(torch.from_numpy(padded.reshape(-1, w, rows.shape[1])))).reshape(-1)[:n]
            return out.numpy().astype(np.float32), (time.process_time() - start) / n
        if len(rows) < self.window:
            return flags, 0.0
        x = np.lib.stride_tricks.sliding_window_view(rows, (self.window, rows.shape[1]))[:, 0]
        start = time.process_time()
        with torch.no_grad():
            out = []
            for i in range(0, len(x), 256):
                logits = self._net(torch.from_numpy(np.ascontiguousarray(x[i:i + 256], dtype=np.float32)))
                out.append(torch.sigmoid(logits).numpy())
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
            # detected once an attack message is flagged, as ours is counted (a clean pose or
            # scan flagged after the onset is a false positive, not a detection)
            hits = np.nonzero(flags & seq.attack)[0]
            delays[seq.name] = float(seq.at[hits[0]] - seq.onset) if len(hits) and seq.onset is not None else None
    return {**figures(tp, fp, fn, tn, right_runs=runs_right, runs=runs, delays=delays),
            "cpu_us_per_message": round(1e6 * (sum(cpu) / len(cpu)), 1) if cpu else None,
            "train_cpu_s": round(model.train_seconds, 1), "threshold": round(threshold, 6),
            "mode": model.mode, "inputs": model.inputs, "hidden": model.hidden, "parameters": model.parameters(),
            "epochs_run": model.epochs_run, "best_epoch": model.best_epoch}


def evaluate_runs(model: LstmBaseline, sequences: Iterable[Sequence], threshold: float = 0.5) -> dict:
    """A ``bag``-mode network's verdicts, one per run (seed 001's experiment: one output at
    the end of each bag): how many runs it judged right, beside a judge that calls every
    run attacked (the share of attacked runs: what the accuracy must beat)."""
    sequences = [seq for seq in sequences if len(seq.rows)]
    verdicts = [(bool(seq.attack.any()), model.run_output(seq) > threshold) for seq in sequences]
    attacked = sum(truth for truth, _ in verdicts)
    n = len(verdicts)
    return {"runs": n, "run_accuracy": round(sum(t == v for t, v in verdicts) / n, 4) if n else None,
            "attacked_runs_flagged": f"{sum(t and v for t, v in verdicts)} of {attacked}",
            "clean_runs_flagged": f"{sum(v and not t for t, v in verdicts)} of {n - attacked}",
            "every_run_attacked_accuracy": round(attacked / n, 4) if n else None,
            "train_cpu_s": round(model.train_seconds, 1), "mode": model.mode, "inputs": model.inputs,
            "hidden": model.hidden, "parameters": model.parameters(), "epochs_run": model.epochs_run,
            "best_epoch": model.best_epoch}


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


__all__ = ["INPUTS", "PAPER_PARAMETERS", "LstmBaseline", "Sequence", "evaluate_lstm", "evaluate_runs", "lstm_roc_points", "paper_rows",
           "param_count", "threshold_for", "windows"]
