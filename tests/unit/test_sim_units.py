"""Unit tests of the simulator's modules, each alone."""

from __future__ import annotations

import random

import networkx as nx
import numpy as np
import pytest

from cryptoros.sim import packets as P
from cryptoros.sim.battery import Battery, BatterySpec
from cryptoros.sim.buffer import FrameBuffer
from cryptoros.sim.channel import Channel, Radio
from cryptoros.sim.explorer import Belief, Explorer, frontier_mask
from cryptoros.sim.home import HomeHandler
from cryptoros.sim.protocol import Protocol, dijkstra
from cryptoros.sim.robot import IDLE
from cryptoros.sim.scenario import Mission, SimConfig
from cryptoros.sim.security import Roster, SecurityConfig, SecurityManager, CostTable
from cryptoros.sim.world import FREE, OCC, UNKNOWN, Lidar, World, generate, load_map_server, save_map_server


# ---------------------------------------------------------------- battery, buffer, home


def test_battery_reaches_zero_exactly_when_it_should():
    b = Battery(BatterySpec(capacity_j=100.0, idle_w=2.0))
    assert b.time_to_empty() == pytest.approx(50.0)
    b.elapse(49.0)
    assert not b.empty and b.energy == pytest.approx(2.0)
    b.elapse(1.0)
    assert b.empty and b.energy == 0.0
    b.elapse(10.0)
    assert b.energy == 0.0  # never negative


def test_battery_charges_every_cost_kind():
    b = Battery(BatterySpec(capacity_j=1000.0, idle_w=1.0, move_j_per_m=10.0, tx_j_per_byte=0.01, rx_j_per_byte=0.005, cpu_w=2.0))
    b.move(2.0)
    b.tx(100)
    b.rx(200)
    b.crypto(3.0)
    assert b.used == {"idle": 0.0, "move": 20.0, "tx": 1.0, "rx": 1.0, "crypto": 6.0}
    assert b.energy == pytest.approx(1000 - 28)


def test_frame_buffer_is_proportional_to_distance_and_unloads():
    fb = FrameBuffer(frames_per_m=2.0, capacity=10)
    for _ in range(10):
        fb.travelled(0.25)
    assert fb.frames == 5
    fb.travelled(10.0)
    assert fb.frames == 10 and fb.dropped == 15
    assert fb.unload() == 10 and fb.frames == 0


def test_home_handler_turns_back_before_the_battery_cannot_make_it():
    spec = BatterySpec(capacity_j=2000.0, idle_w=6.0, move_j_per_m=14.0)
    home = HomeHandler([(0, 0)], resolution=0.2, speed=0.22, reserve_j=50.0)
    b = Battery(spec)
    # far away: the energy needed to get home grows with distance
    assert home.energy_home(b, (0, 100)) > home.energy_home(b, (0, 10))
    b.energy = home.energy_home(b, (0, 100)) + 1.0
    assert home.must_return(b, (0, 100), 0.2)
    b.energy = 2000.0
    assert not home.must_return(b, (0, 100), 0.2)


# ---------------------------------------------------------------- world


def test_generated_world_is_deterministic_and_bounded():
    a, b = generate(7, 50, 40), generate(7, 50, 40)
    assert np.array_equal(a.occupied, b.occupied) and a.bases == b.bases
    assert not np.array_equal(a.occupied, generate(8, 50, 40).occupied)
    assert a.occupied[0].all() and a.occupied[:, -1].all()
    assert a.explorable().sum() > 0.6 * (~a.occupied).sum()  # rooms connect through doors


def test_map_server_round_trip(tmp_path):
    w = generate(3, 40, 30)
    y = save_map_server(w, tmp_path / "m.yaml")
    back = load_map_server(y)
    assert np.array_equal(back.occupied, w.occupied)
    assert back.resolution == w.resolution


def test_lidar_does_not_see_through_walls():
    occ = np.zeros((30, 30), dtype=bool)
    occ[:, 15] = True
    lidar = Lidar(10)
    flat, hit = lidar.scan(occ, 15, 10)
    cols = flat % 30
    assert cols.max() == 15  # the wall is seen, nothing behind it
    assert hit[cols == 15].all()


# ---------------------------------------------------------------- explorer


def test_explorer_goes_to_a_frontier_through_free_cells():
    known = np.full((40, 40), UNKNOWN, dtype=np.int8)
    known[5:20, 5:20] = FREE
    known[5:20, 12] = OCC
    known[10, 12] = FREE  # a door
    ex = Explorer()
    path = ex.plan_frontier(known, (15, 6))
    assert path
    for a, b in zip([(15, 6)] + path, path):
        assert abs(a[0] - b[0]) + abs(a[1] - b[1]) == 1
        assert known[b] == FREE
    assert frontier_mask(known)[path[-1]]
    known[:] = FREE
    assert ex.plan_frontier(known, (15, 6)) is None


def test_belief_replaces_a_peers_map_and_can_lose_knowledge():
    b = Belief((10, 10))
    b.merge_peer("p", 0, 0, np.zeros((5, 5), dtype=np.int8))
    assert (b.known[:5, :5] == FREE).all()
    b.merge_peer("p", 0, 0, np.full((5, 5), -1, dtype=np.int8))
    assert (b.known == UNKNOWN).all()


# ---------------------------------------------------------------- routing


@pytest.mark.parametrize("seed", range(8))
def test_dijkstra_matches_networkx(seed):
    rnd = random.Random(seed)
    g = nx.gnp_random_graph(25, 0.12, seed=seed)
    adj = {str(n): {str(m) for m in g.neighbors(n)} for n in g.nodes}
    dist, first = dijkstra(adj, "0")
    ref = nx.single_source_shortest_path_length(g, 0)
    assert dist == {str(k): v for k, v in ref.items()}
    for dest, hop in first.items():
        # the first hop is on some shortest path
        assert nx.shortest_path_length(g, int(hop), int(dest)) == ref[int(dest)] - 1
    low = {str(n) for n in g.nodes if rnd.random() < 0.3} - {"0"}
    dist2, first2 = dijkstra(adj, "0", allowed_relay=lambda n: n not in low)
    # reference: shortest paths whose interior avoids 'low' nodes
    for dest in dist2:
        sub = g.subgraph([n for n in g.nodes if str(n) not in low or str(n) == dest])
        assert nx.shortest_path_length(sub, 0, int(dest)) == dist2[dest]


def test_protocol_builds_topology_from_lsus():
    a, b = Protocol("a"), Protocol("b")
    hb = b.hello(0.0, (1.0, 0.0), 100.0, 1)
    assert a.on_hello(P.decode(P.encode(hb, P.HELLO), P.HELLO), 0.1)
    lsu = P.make(P.LSU, origin="c", sender="b", seq=1, timestamp=0.0, ttl=3, position=P.Point(), residual_energy=5.0, buffer_free=1.0, state=1, neighbours=["b"])
    fwd = a.on_lsu(lsu, 0.2)
    assert fwd is not None and fwd.ttl == 2 and fwd.sender == "a"
    assert a.on_lsu(lsu, 0.3) is None  # each (origin, seq) once
    assert a.next_hop("c") == "b" and a.hops("c") == 2
    a.min_relay_energy = 200.0  # b advertises 100 J: not a feasible relay
    a._routes = None
    assert a.next_hop("c") is None


# ---------------------------------------------------------------- channel


def _radios(ch, pos):
    for name, p in pos.items():
        ch.add(Radio(name, (lambda p=p: p), 10.0))


def test_collisions_drop_both_packets():
    ch = Channel(np.random.default_rng(0))
    # a and c cannot hear each other (hidden terminals), b hears both
    _radios(ch, {"a": (0.0, 0.0), "b": (6.0, 0.0), "c": (12.0, 0.0)})
    got = []
    ch.transmit(0.0, P.Frame("a", P.HELLO, b"x" * 100), lambda t, rec: got.append(rec))
    ch.transmit(0.0001, P.Frame("c", P.HELLO, b"y" * 100), lambda t, rec: got.append(rec))
    at_b = [r for r in got if r.receiver == "b"]
    assert len(at_b) == 2
    assert not any(ch.finish(r) for r in at_b)
    assert all(r.lost == "collision" for r in at_b)
    # far apart in time: both delivered
    got.clear()
    ch.transmit(1.0, P.Frame("a", P.HELLO, b"x" * 100), lambda t, rec: got.append(rec))
    ch.transmit(2.0, P.Frame("c", P.HELLO, b"y" * 100), lambda t, rec: got.append(rec))
    assert all(ch.finish(r) for r in got if r.receiver == "b")


def test_channel_range_delay_and_loss():
    ch = Channel(np.random.default_rng(0), bitrate=1e6, loss=1.0)
    _radios(ch, {"a": (0.0, 0.0), "b": (9.0, 0.0), "far": (50.0, 0.0)})
    got = []
    ch.transmit(0.0, P.Frame("a", P.HELLO, b"x" * 125), lambda t, rec: got.append((t, rec)))
    assert [r.receiver for _, r in got] == ["b"]
    t, rec = got[0]
    assert t == pytest.approx(9.0 / 3e8 + 125 * 8 / 1e6)
    assert not ch.finish(rec) and rec.lost == "random"


# ---------------------------------------------------------------- packets


def test_packets_round_trip_with_real_ros1_sizes():
    for typename in P.ALL_TYPES:
        assert len(P.md5sum(typename)) == 32
    m = P.make(P.HELLO, source="r1", seq=3, timestamp=1.5, position=P.Point(1, 2), residual_energy=10.0, buffer_free=0.5, state=1)
    data = P.encode(m, P.HELLO)
    # string: 4-byte length + 2, uint32, float64, Point (3 float64), float32 x 2, uint8
    assert len(data) == 4 + 2 + 4 + 8 + 24 + 4 + 4 + 1
    assert P.decode(data, P.HELLO) == m


# ---------------------------------------------------------------- security


def _pair(spec):
    cfg = SecurityConfig.parse(spec)
    roster = Roster(1, cfg.curve)
    for n in ("a", "b"):
        roster.enrol(n)
    costs = CostTable(cfg.curve)
    return cfg, {n: SecurityManager(n, cfg, roster, costs, np.random.default_rng(i)) for i, n in enumerate("ab")}


def _exchange_keys(m):
    pending = [("a", x) for x in m["a"].start(0.0)] + [("b", x) for x in m["b"].start(0.0)]
    for _ in range(6):
        nxt = []
        for src, (msg, t) in pending:
            dst = "b" if src == "a" else "a"
            _, _, why, replies = m[dst].open(P.frame(src, msg, t), 0.1)
            assert why == ""
            nxt += [(dst, r) for r in replies]
        pending = nxt


@pytest.mark.parametrize("spec", ["ecdsa", "sha256", "hmac", "aes", "full", "rsa,hmac,aes"])
def test_security_round_trip(spec):
    cfg, m = _pair(spec)
    _exchange_keys(m)
    hello = m["a"].seal(P.make(P.HELLO, source="a", seq=1, timestamp=0.2, position=P.Point(), residual_energy=1.0, buffer_free=1.0, state=1), P.HELLO, 0.2)
    msg, typename, why, _ = m["b"].open(P.Frame("a", *hello), 0.3)
    assert why == "" and typename == P.HELLO and msg.source == "a"
    assert m["b"].take_cpu() > 0
    if cfg.auth != "none" or cfg.integrity == "hmac":  # replay of the same frame
        assert m["b"].open(P.Frame("a", *hello), 0.4)[2] == "replay"


@pytest.mark.parametrize("spec,reason", [("ecdsa", "bad_signature"), ("hmac", "bad_mac"), ("sha256", "bad_digest")])
def test_tampering_is_detected(spec, reason):
    cfg, m = _pair(spec)
    _exchange_keys(m)
    typename, data = m["a"].seal(P.make(P.HELLO, source="a", seq=1, timestamp=0.2, position=P.Point(), residual_energy=1.0, buffer_free=1.0, state=1), P.HELLO, 0.2)
    f = P.decode(data, P.SECURE)
    payload = bytearray(bytes(f.payload))
    payload[-1] ^= 1
    bad = P.encode(P.replace(f, payload=np.frombuffer(bytes(payload), dtype=np.uint8)), P.SECURE)
    assert m["b"].open(P.Frame("a", typename, bad), 0.3)[2] == reason


def test_reflected_frame_fails_with_per_direction_keys():
    cfg, m = _pair("hmac,aes")
    _exchange_keys(m)
    typename, data = m["a"].seal(P.make(P.HELLO, source="a", seq=1, timestamp=0.2, position=P.Point(), residual_energy=1.0, buffer_free=1.0, state=1), P.HELLO, 0.2)
    f = P.decode(data, P.SECURE)
    reflected = P.encode(P.replace(f, sender="b"), P.SECURE)  # sent back as if from b
    assert m["a"].open(P.Frame("x", typename, reflected), 0.3)[2] == "bad_mac"


# ---------------------------------------------------------------- expanding ring


def _chain(k: int):
    """k+1 robots on a corridor, 5 m apart with a 6 m radio: robot i is i hops from r0."""
    occ = np.ones((5, 30 * (k + 1) + 10), dtype=bool)
    occ[2, 1:-1] = False
    world = World(occ, 0.2, [(2, 2)])
    starts = [(2, 2 + 25 * i) for i in range(k + 1)]
    cfg = SimConfig(robots=k + 1, idle=k + 1, range_m=6.0, max_time=120.0)
    return Mission(cfg, world=world, starts=starts)


@pytest.mark.parametrize("k", [1, 3])
def test_expanding_ring_reaches_k_hops_with_ttl_k_and_not_before(k):
    mission = _chain(k)
    for r in mission.robots.values():
        r.start()
    mission.engine.run_until(25.0)  # HELLOs and LSUs settle
    r0, rk = mission.robots["r0"], mission.robots[f"r{k}"]
    assert r0.protocol.hops(f"r{k}") == k
    assert all(r.state == IDLE for r in mission.robots.values())
    r0._start_recruit((2, 2 + 25 * k), dest=f"r{k}")
    mission.engine.run_until(80.0)
    events = [(e, ttl) for _, e, _, ttl in r0.recruit.log]
    assert [ttl for e, ttl in events if e == "request"] == list(range(1, k + 1))
    offers = [ttl for e, ttl in events if e == "offer"]
    assert offers and set(offers) == {k}
    assert ("confirm", k) in events
    assert rk.counters["recruited"] == 1
    # a robot k hops away saw the request only in the ring with TTL k
    assert min(rk.recruit.seen_request_ttls("r0", 1)) == 1 and len(rk.recruit.seen_request_ttls("r0", 1)) == 1


def _room_with_two_idle_robots_at_the_base(seed: int) -> Mission:
    """r1 and r2 idle side by side at the base, r0 in range of both: one general recruit
    request reaches both at the same instant."""
    occ = np.ones((20, 40), dtype=bool)
    occ[1:-1, 1:-1] = False
    world = World(occ, 0.2, [(2, 2)])
    cfg = SimConfig(robots=3, idle=3, seed=seed, range_m=6.0, max_time=120.0)
    return Mission(cfg, world=world, starts=[(10, 20), (2, 3), (3, 2)])


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_two_idle_robots_in_range_both_offer_and_the_recruit_succeeds(seed):
    mission = _room_with_two_idle_robots_at_the_base(seed)
    for r in mission.robots.values():
        r.start()
    mission.engine.run_until(12.0)  # neighbours known
    r0, r1, r2 = (mission.robots[n] for n in ("r0", "r1", "r2"))
    r0._start_recruit((10, 30), dest="")  # general request: any robot idle at a base
    mission.engine.run_until(20.0)
    events = [e for _, e, _, _ in r0.recruit.log]
    assert events.count("offer") == 2  # both idle robots got their offer through
    assert "confirm" in events
    assert r1.counters["offers_sent"] == 1 and r2.counters["offers_sent"] == 1
    assert r1.counters["recruited"] + r2.counters["recruited"] == 1
    assert not r0.recruit.pending


def test_a_recharged_robot_resumes_exploring():
    # one robot, a battery for about five minutes: out, home, charge, out again
    m = Mission(SimConfig(robots=1, seed=3, battery_j=3000.0, max_time=600.0))
    r = m.run()
    c = r["robots"]["r0"]["counters"]
    assert c["returns_home"] >= 1 and c["charges"] >= 1
    assert c["resumed"] >= 1
    assert r["outcome"]["end_reason"] != "no_robot_active"
    # one full battery drives at most capacity / (traction + idle draw per metre) metres:
    # anything beyond that was driven after a recharge
    spec = m.robots["r0"].battery.spec
    one_charge_m = spec.capacity_j / (spec.move_j_per_m + spec.idle_w / m.robots["r0"].cfg.speed)
    assert r["robots"]["r0"]["travelled_m"] > one_charge_m


def test_buffer_space_travels_in_the_link_state_and_a_full_buffer_is_not_recruited():
    a, b, c = Protocol("a"), Protocol("b"), Protocol("c")
    b.on_hello(a.hello(0.0, (0.0, 0.0), 100.0, IDLE, buffer_free=0.0), 0.0)
    c.on_lsu(b.lsu(0.1, (1.0, 0.0), 100.0, IDLE, buffer_free=0.25), 0.1)
    assert b.known_robots()["a"].buffer_free == 0.0
    assert c.known_robots()["b"].buffer_free == pytest.approx(0.25)
    # a recruiter with two idle candidates in range: the nearer one's buffer is full
    mission = _room_with_two_idle_robots_at_the_base(1)
    r0, r1, r2 = (mission.robots[n] for n in ("r0", "r1", "r2"))
    r1.buffer.frames = r1.buffer.capacity  # r1 (nearer to the target) has no room left
    for r in mission.robots.values():
        r.start()
    mission.engine.run_until(12.0)
    assert r0.protocol.known_robots()["r1"].buffer_free == 0.0
    assert r0._pick_candidate((2, 4)) == "r2"
    r1.buffer.unload()
    mission.engine.run_until(14.0)
    assert r0._pick_candidate((2, 4)) == "r1"


def test_t_interval_uses_students_t_not_1_96():
    from cryptoros.sim.plots import aggregate, t_interval

    mean, half = t_interval([1.0, 2.0, 3.0])
    assert mean == 2.0
    assert half == pytest.approx(4.302652729749464 * 1.0 / 3 ** 0.5)  # t(0.975, 2 d.f.)
    assert half > 2 * 1.96 / 3 ** 0.5
    rows = [{"s": "x", "v": v} for v in (10.0, 12.0, 11.0, 13.0, 9.0, 10.0, 12.0, 11.0, 13.0, 9.0)]
    m, h, n = aggregate(rows, "v", ("s",))[("x",)]
    sd = float(np.std([r["v"] for r in rows], ddof=1))
    assert n == 10 and h == pytest.approx(2.2621571627409915 * sd / 10 ** 0.5)  # t(0.975, 9 d.f.)


def test_fig8_keeps_each_scenario_its_own_series():
    from cryptoros.sim.plots import aggregate
    from cryptoros.sim.sweep import curve_rows

    rows = [{"scenario": s, "curve": c, "robots": 2, "seed": k, "task_time_s": t + k}
            for s, t in (("secure", 100.0), ("defended1", 300.0)) for c in ("secp192r1", "secp384r1") for k in (1, 2, 3)]
    rows.append({"scenario": "legacy", "curve": "secp192r1", "robots": 2, "seed": 1, "task_time_s": 5.0})
    agg = aggregate(curve_rows(rows), "task_time_s", ("series", "robots"))
    assert set(agg) == {("secure secp192r1", 2), ("secure secp384r1", 2), ("defended1 secp192r1", 2), ("defended1 secp384r1", 2)}
    assert agg[("secure secp192r1", 2)][0] == 102.0 and agg[("defended1 secp384r1", 2)][0] == 302.0
