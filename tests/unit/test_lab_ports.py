"""free_port: ports for children to listen on, away from the kernel's ephemeral ports."""

from __future__ import annotations

import socket

import pytest

from cryptoros.lab.processes import _PICK_FROM, PORT_SLICE_ENV, _ephemeral_low, free_port


def test_free_ports_are_below_the_ephemeral_range_distinct_and_bindable():
    low = _ephemeral_low()
    taken: set[int] = set()
    ports = [free_port(taken=taken) for _ in range(50)]
    assert len(set(ports)) == 50 and set(ports) == taken
    if low - _PICK_FROM >= 1000:  # Linux's default range leaves 20000-32767
        assert all(_PICK_FROM <= p < low for p in ports), ports
    for port in ports[:5]:
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))
            s.listen()


def test_a_port_in_use_is_skipped(monkeypatch):
    """The pick is random: made to land on a port something listens on first, it takes
    the next pick (the random choice is steered, the binding is real)."""
    import cryptoros.lab.processes as processes

    with socket.socket() as held:
        held.bind(("127.0.0.1", free_port()))
        held.listen()
        busy = held.getsockname()[1]
        spare = free_port()
        picks = iter([busy, busy, spare])
        monkeypatch.setattr(processes.random, "choice", lambda _span: next(picks))
        assert free_port() == spare


def test_labs_side_by_side_pick_from_disjoint_slices(monkeypatch):
    """Parallel test workers: each one's slice of the range (two workers' labs once picked
    the same port), and a value that does not parse leaves the whole range."""
    low = _ephemeral_low()
    if low - _PICK_FROM < 3000:
        pytest.skip(f"the kernel's ephemeral range starts at {low}: too few ports below it for three slices")
    size = (low - _PICK_FROM) // 3
    for index in range(3):
        monkeypatch.setenv(PORT_SLICE_ENV, f"{index}/3")
        ports = {free_port() for _ in range(40)}
        first = _PICK_FROM + index * size
        assert all(first <= p < first + size for p in ports), (index, sorted(ports))
    for bogus in ("x", "3/3", "1/"):
        monkeypatch.setenv(PORT_SLICE_ENV, bogus)
        assert _PICK_FROM <= free_port() < low
