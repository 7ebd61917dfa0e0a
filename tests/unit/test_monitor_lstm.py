"""Seed 001's LSTM as the baseline: its size as the paper counts it, and its training loop
(class weights, early stopping on held-out sequences, one output per message) on a
small dataset whose attack messages differ from the clean ones."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from cryptoros.monitor.lstm import (  # noqa: E402
    PAPER_PARAMETERS,
    RANGES,
    ROW,
    LstmBaseline,
    Sequence,
    evaluate_lstm,
    param_count,
)


def test_the_papers_parameter_count_is_150_cells_on_its_367_float_rows_and_160_cells_make_more():
    assert param_count(150, ROW) == PAPER_PARAMETERS == 310_951
    assert param_count(160, ROW) == 338_081
    # the network as built counts what Keras counts: one bias per gate, the output neuron
    assert LstmBaseline(hidden=150).parameters() == PAPER_PARAMETERS
    assert LstmBaseline(hidden=160).parameters() == 338_081
    assert LstmBaseline(hidden=160, inputs="paper+dt").parameters() == param_count(160, ROW + 2)


def _run(rng: np.random.Generator, n: int, attacked: bool, name: str) -> Sequence:
    """Rows of poses and scans; from the middle on an attacked run's poses jump (spoofed)."""
    kinds = np.where(np.arange(n) % 3 == 2, 2, 0)  # pose, pose, scan
    rows = np.zeros((n, ROW), np.float32)
    rows[:, 0] = np.cumsum(rng.normal(0.01, 0.002, n))
    rows[:, 4:4 + 72] = rng.uniform(1.0, 2.0, (n, 72))
    rows[np.arange(n), 4 + RANGES + kinds] = 1.0
    attack = np.zeros(n, bool)
    if attacked:
        attack = (np.arange(n) >= n // 2) & (kinds == 0)
        rows[attack, 0] = rng.choice([-1.0, 1.0], attack.sum()) * rng.uniform(10, 20, attack.sum())
        rows[attack, 1] = rng.uniform(-20, 20, attack.sum())
    return Sequence(rows, attack, np.arange(n) * 0.05, (n // 2) * 0.05 if attacked else None, name, kinds)


def test_the_per_message_lstm_learns_attack_messages_and_stops_when_the_validation_loss_does():
    rng = np.random.default_rng(3)
    train = [_run(rng, 120, i % 2 == 1, f"t{i}") for i in range(16)]
    val = [_run(rng, 120, i % 2 == 1, f"v{i}") for i in range(2)]
    test = [_run(rng, 120, i % 2 == 1, f"e{i}") for i in range(2)]
    model = LstmBaseline(window=30, epochs=300, hidden=24, batch=8, patience=10, seed=1).fit(train, val)
    # early stopping: it stopped before the 300 epochs, `patience` epochs after its best one,
    # and the weights kept are the best epoch's (the lowest validation loss, to the 1e-4
    # an epoch must improve by to count)
    assert model.epochs_run < 300 and model.epochs_run == model.best_epoch + model.patience
    losses = [v for _, _, v in model.history]
    assert losses[model.best_epoch - 1] <= min(losses) + 1e-4 and losses[model.best_epoch - 1] < losses[0]
    figures = evaluate_lstm(model, test)
    assert figures["mode"] == "message" and figures["messages"] == 240 and figures["attack_messages"] > 0
    assert figures["accuracy"] >= 0.9 and figures["precision"] >= 0.9 and figures["recall"] >= 0.5, figures
    out, cpu = model.outputs(test[1])
    assert out.shape == (120,) and cpu > 0
    assert out[test[1].attack].mean() > out[~test[1].attack].mean() + 0.3


def test_without_validation_runs_it_trains_the_given_epochs_and_the_window_mode_labels_windows():
    rng = np.random.default_rng(4)
    runs = [_run(rng, 120, i % 2 == 1, f"r{i}") for i in range(4)]
    model = LstmBaseline(window=30, epochs=3, hidden=8, mode="window").fit(runs)
    assert model.epochs_run == 3 and model.best_epoch == 3 and [v for _, _, v in model.history] == [None] * 3
    out, _ = model.outputs(runs[1])
    assert (out[:29] == 0).all() and out.shape == (120,)  # no full window before the 30th message


class _Fixed:
    """A stand-in network output (the scoring of outputs is what is tested here)."""

    train_seconds, mode, inputs, hidden, epochs_run, best_epoch = 0.0, "message", "paper", 0, 0, 0

    def parameters(self) -> int:
        return 0


def test_a_run_counts_as_detected_only_once_an_attack_message_is_flagged():
    """Flags on clean messages after the onset are false positives, not a detection: the
    delay runs to the first attack message flagged (as the monitor's own are counted)."""
    rng = np.random.default_rng(5)
    run = _run(rng, 120, True, "spoof")
    clean_after = (~run.attack) & (run.at >= run.onset)
    only_clean = np.where(clean_after, 0.9, 0.1).astype(np.float32)
    figures = evaluate_lstm(_Fixed(), [run], outputs=[(only_clean, 1e-6)])
    assert figures["attack_streams_detected"] == "0 of 1" and figures["median_delay_s"] is None, figures
    later = only_clean.copy()
    third = np.nonzero(run.attack)[0][2]
    later[third] = 0.9
    figures = evaluate_lstm(_Fixed(), [run], outputs=[(later, 1e-6)])
    assert figures["attack_streams_detected"] == "1 of 1"
    assert figures["median_delay_s"] == round(float(run.at[third] - run.onset), 3), figures


def test_the_bag_mode_gives_one_verdict_per_run_beside_calling_every_run_attacked():
    """Seed 001's experiment: a whole run in, one output at its end."""
    from cryptoros.monitor.lstm import evaluate_runs

    rng = np.random.default_rng(6)

    def run(n: int, attacked: bool, name: str) -> Sequence:  # an attacked run's second half is far off
        seq = _run(rng, n, attacked, name)
        seq.rows[seq.attack, 0] = rng.uniform(10, 20, seq.attack.sum())
        return seq

    train = [run(40 + 4 * i, i % 2 == 1, f"t{i}") for i in range(8)]
    test = [run(45 + 15 * i, i % 2 == 1, f"e{i}") for i in range(4)]  # the last two longer than any trained
    model = LstmBaseline(mode="bag", epochs=150, hidden=16, batch=2, seed=2).fit(train)  # all 150 epochs
    # the runs it learnt, each judged by its one output (labels, padding and the readout
    # line up: a network that fits them judges every one right)
    fitted = evaluate_runs(model, train)
    assert fitted["run_accuracy"] == 1.0 and fitted["attacked_runs_flagged"] == "4 of 4", fitted
    assert fitted["clean_runs_flagged"] == "0 of 4" and fitted["every_run_attacked_accuracy"] == 0.5
    figures = evaluate_runs(model, test)  # unseen runs, two longer than any it learnt: read at its length
    assert figures["runs"] == 4 and figures["every_run_attacked_accuracy"] == 0.5 and figures["mode"] == "bag"
    assert figures["attacked_runs_flagged"] == "2 of 2", figures
