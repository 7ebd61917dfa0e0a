"""free_port: ports for children to listen on, away from the kernel's ephemeral ports."""

from __future__ import annotations

import socket

from cryptoros.lab.processes import _PICK_FROM, _ephemeral_low, free_port


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
