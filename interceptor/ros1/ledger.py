"""The master role's ledger of rosmaster's registrations made through this interceptor:
who owns each node name, the registrations kept to replay to a restarted rosmaster,
each node's API and parameter subscriptions, and how many registrations stand behind
each relay (a relay with none left is released).

Pure: no I/O and no clock of its own (name holds take theirs, passed in); a relay is
known by the predicate it is given; what a change calls for (a relay to release, the
state file to write) is returned, the caller does it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from interceptor.name_holds import NameHolds
from interceptor.ros1.wire import (
    MAX_PARAM_SUBSCRIPTIONS_PER_NODE,
    MAX_REGISTRATIONS,
    RELAY_URI_INDEX,
    caller_api,
    local_endpoint,
    param_subscription_key,
    registration_key,
)

Endpoint = tuple[str, int]
Key = tuple[str, str, str]  # (kind, node, name)
Call = tuple[str, tuple]  # (method, params) as forwarded


@dataclass
class Owner:
    manager: str
    registrations: int = 0


@dataclass
class Noted:
    """What a call rosmaster answered changed: the state file is due (``changed``), these
    relays have no registration left (``released``), this node was registered from
    another API and what it had is gone (``replaced``: the owner it had, or "")."""

    changed: bool = False
    released: list[Endpoint] = field(default_factory=list)
    replaced: str | None = None


class MasterLedger:
    def __init__(self, holds: NameHolds, is_relay: Callable[[Endpoint], bool], *,
                 max_registrations: int = MAX_REGISTRATIONS) -> None:
        self.holds = holds
        self._is_relay = is_relay
        self.max_registrations = max_registrations
        self.owners: dict[str, Owner] = {}
        #: nodes whose owner holds the name only through ``*`` or a pattern (a manager
        #: whose grants name the node itself takes it from such an owner)
        self.owned_by_pattern: set[str] = set()
        #: the registrations rosmaster holds through us, as forwarded: (kind, node, name) -> call
        self.registrations: dict[Key, Call] = {}
        #: registrations not kept because the table was full (a restarted rosmaster misses them)
        self.not_kept = 0
        #: each registered node's API as rosmaster has it (its relay here), and its kept keys:
        #: a node that registers from another API was restarted or replaced
        self.api_of_node: dict[str, str] = {}
        self.keys_of_node: dict[str, set[Key]] = {}
        #: each node's parameter subscriptions (key -> the call's params), counted behind relays
        self.param_subs_of_node: dict[str, dict[str, tuple]] = {}
        #: registrations behind each relay
        self.relay_refs: dict[Endpoint, int] = {}

    # ---------------------------------------------------------------- reading
    def owner_of(self, node: str, names_exactly: bool = False) -> str | None:
        """The manager that has ``node`` registered, or released it within its hold. A
        hold, or a registration made through ``*`` or a pattern, does not stand against a
        caller whose grants name that very node (``names_exactly``)."""
        entry = self.owners.get(node)
        if entry:
            if node in self.owned_by_pattern and names_exactly:
                return None
            return entry.manager
        holder = self.holds.holder(node)
        return None if holder is not None and names_exactly else holder

    def nodes_of(self, manager: str) -> int:
        return sum(1 for o in self.owners.values() if o.manager == manager)

    def param_subscriptions_of(self, manager: str) -> int:
        return sum(len(s) for n, s in self.param_subs_of_node.items()
                   if (o := self.owners.get(n)) is not None and o.manager == manager)

    def kept(self, method: str, params: tuple) -> Call | None:
        """The registration (or parameter subscription) a master call makes or releases,
        as it was forwarded when made, if it is kept."""
        key = registration_key(method, params)
        if key is not None:
            return self.registrations.get(key)
        key = param_subscription_key(method, params)
        if key is not None:
            kept = self.param_subs_of_node.get(key[1], {}).get(key[2])
            return None if kept is None else ("subscribeParam", kept)
        return None

    # ---------------------------------------------------------------- changing
    def note(self, method: str, params: tuple, *, ok: bool, released: int, manager: str, exact: bool,
             hold_seconds: float) -> Noted:
        """A call rosmaster answered (``ok``; ``released``: what an unregister said it
        removed) by ``manager``'s node (``exact``: its grants name the node itself).

        rosmaster keeps one registration per node and topic (service, parameter key):
        the same registration made again changes nothing, here either."""
        out = Noted()
        if not ok or not params:
            return out
        node = params[0]
        registering = method.startswith("register") or method == "subscribeParam"
        if registering:
            api = caller_api(method, params)
            if api is not None and self.api_of_node.setdefault(node, api) != api:
                out.replaced = self._forget_replaced_node(node, out.released)
                self.api_of_node[node] = api
        kept = self.kept(method, params)
        if registering and node in self.owners and kept == (method, tuple(params)):
            return out  # an identical repeat
        self.record(method, params)
        if registering:
            out.released += self.count_relay_refs(method, params, +1)
            if kept is not None and node in self.owners:
                # made again with other values (a topic's type, a service's URI): it
                # replaces the one kept, and the relays behind that one lose its count
                out.released += self.count_relay_refs(kept[0], kept[1], -1)
            else:
                entry = self.owners.setdefault(node, Owner(manager))
                if entry.registrations == 0 and exact:
                    self.owned_by_pattern.discard(node)
                elif entry.registrations == 0:
                    self.owned_by_pattern.add(node)
                entry.registrations += 1
                self.holds.claim(node)
            self._note_param_subscription(method, params)
            out.changed = True
        elif (method.startswith("unregister") or method == "unsubscribeParam") and released > 0:
            entry = self.owners.get(node)
            if entry is not None:
                entry.registrations -= 1
                if entry.registrations <= 0:
                    del self.owners[node]
                    self.owned_by_pattern.discard(node)
                    self.api_of_node.pop(node, None)
                    self.param_subs_of_node.pop(node, None)
                    self.holds.release(node, entry.manager, hold_seconds)
            out.changed = entry is not None or kept is not None
            # the relays behind the registration as it was made: unregisterService names
            # the service's URI, not the node API its registration counted too
            out.released += self.count_relay_refs(*(kept or (method, params)), -1)
            self._note_param_subscription(method, params)
        return out

    def record(self, method: str, params: tuple) -> None:
        """Keep (or drop) one registration as it was forwarded to rosmaster."""
        key = registration_key(method, params)
        if key is None:
            return
        node = key[1]
        if method.startswith("register"):
            if key not in self.registrations and len(self.registrations) >= self.max_registrations:
                self.not_kept += 1
                return
            self.registrations[key] = (method, tuple(params))
            self.keys_of_node.setdefault(node, set()).add(key)
            api = caller_api(method, params)
            if api is not None:
                self.api_of_node.setdefault(node, api)
        elif self.registrations.pop(key, None) is not None:
            keys = self.keys_of_node.get(node)
            if keys is not None:
                keys.discard(key)
                if not keys:
                    del self.keys_of_node[node]

    def count_relay_refs(self, method: str, params: tuple, delta: int) -> list[Endpoint]:
        """One count per registration behind each relay the call names; returns the
        relays whose last registration was released."""
        released = []
        for index in RELAY_URI_INDEX.get(method, ()):
            endpoint = local_endpoint(params[index] if len(params) > index else None)
            if endpoint is None or not self._is_relay(endpoint):
                continue
            count = self.relay_refs.get(endpoint, 0) + delta
            if count > 0:
                self.relay_refs[endpoint] = count
                continue
            self.relay_refs.pop(endpoint, None)
            if delta < 0:
                released.append(endpoint)
        return released

    def adopt(self, counts: Iterable[tuple[Endpoint, int]]) -> int:
        """Relays rosmaster names after a restart with no state, each with its count."""
        adopted = 0
        for endpoint, count in counts:
            if self._is_relay(endpoint):
                self.relay_refs[endpoint] = self.relay_refs.get(endpoint, 0) + count
                adopted += 1
        return adopted

    def _note_param_subscription(self, method: str, params: tuple) -> None:
        key = param_subscription_key(method, params)
        if key is None:
            return
        _kind, node, name = key
        if method == "subscribeParam":
            subs = self.param_subs_of_node.setdefault(node, {})
            if name in subs or len(subs) < MAX_PARAM_SUBSCRIPTIONS_PER_NODE:
                subs[name] = tuple(params)
        else:
            subs = self.param_subs_of_node.get(node)
            if subs is not None:
                subs.pop(name, None)
                if not subs:
                    del self.param_subs_of_node[node]

    def _forget_replaced_node(self, node: str, released: list[Endpoint]) -> str:
        """``node`` registered from another API: rosmaster dropped every registration of
        the old one, so the kept registrations, its parameter subscriptions, the relay
        counts behind them and the owner go too. Returns the owner it had ("": none)."""
        for key in self.keys_of_node.pop(node, ()):
            kept = self.registrations.pop(key, None)
            if kept is not None:
                released += self.count_relay_refs(kept[0], kept[1], -1)
        for params in self.param_subs_of_node.pop(node, {}).values():
            released += self.count_relay_refs("subscribeParam", params, -1)
        entry = self.owners.pop(node, None)
        self.owned_by_pattern.discard(node)
        return entry.manager if entry else ""

    # ---------------------------------------------------------------- the state file
    def snapshot(self) -> dict:
        return {"owners": {n: [o.manager, o.registrations] for n, o in self.owners.items()},
                "owned_by_pattern": sorted(self.owned_by_pattern),
                "registrations": [[method, list(params)] for method, params in self.registrations.values()]}

    def restore(self, data: dict) -> None:
        """Tables from :meth:`snapshot` (raises ValueError, KeyError or TypeError on a bad one)."""
        self.owners.update({str(k): Owner(str(v[0]), int(v[1])) for k, v in data.get("owners", {}).items()})
        self.owned_by_pattern.update(str(n) for n in data.get("owned_by_pattern", ()) if str(n) in self.owners)
        for method, params in data.get("registrations", [])[:self.max_registrations]:
            self.record(str(method), tuple(str(p) for p in params))
        for method, params in self.registrations.values():  # the counts behind each restored relay
            self.count_relay_refs(method, params, +1)


__all__ = ["MasterLedger", "Noted", "Owner"]
