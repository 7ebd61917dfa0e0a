"""An embedded ROS 1 master (asyncio): the master and parameter-server APIs.

Implements what rospy, roscpp, rostopic and rosnode use: ``register*`` and
``unregister*`` for publishers, subscribers and services, ``lookupNode``,
``lookupService``, ``getSystemState``, ``getTopicTypes``, ``getPublishedTopics``,
``getUri``, ``getPid`` and the parameter calls, with ``publisherUpdate`` callbacks to
subscribers (one new connection per call, in order per node, as rosmaster does) and
``paramUpdate`` to parameter subscribers. Rules follow rosmaster: an ``unregister*``
only succeeds when ``(caller_id, caller_api)`` matches; a node name registered again
with another ``caller_api`` makes the master call ``shutdown`` on the old node.

Run it with ``cryptoros master --port N`` or in-process::

    async with Master(port=0) as m:
        print(m.uri)
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
from collections import defaultdict
from typing import Any

from cryptoros.ros1.node import XmlRpcServer, call
from cryptoros.ros1.xmlrpc import Fault, Request, Response

log = logging.getLogger(__name__)

__all__ = ["Master"]


def _ok(value: Any, msg: str = "") -> Response:
    return Response(value=[1, msg, value])


def _err(msg: str, value: Any = 0) -> Response:
    return Response(value=[-1, msg, value])


def _canon(key: str, caller_id: str = "/") -> str:
    """Resolve a parameter key (global, relative to the caller's namespace, or ~private)."""
    if key.startswith("/"):
        name = key
    elif key.startswith("~"):
        name = caller_id.rstrip("/") + "/" + key[1:]
    else:
        ns = caller_id.rsplit("/", 1)[0] if "/" in caller_id else ""
        name = ns + "/" + key
    parts = [p for p in name.split("/") if p]
    return "/" + "/".join(parts)


class Master:
    """The embedded master. ``await start()`` binds ``host:port`` (0 = any free port)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 11311, *, callback_timeout: float = 5.0) -> None:
        self.server = XmlRpcServer(self._handle, host, port)
        self.callback_timeout = callback_timeout
        self.publishers: dict[str, dict[str, str]] = defaultdict(dict)  # topic -> caller_id -> api
        self.subscribers: dict[str, dict[str, str]] = defaultdict(dict)
        self.services: dict[str, tuple[str, str, str]] = {}  # service -> (caller_id, service_api, caller_api)
        self.topic_types: dict[str, str] = {}
        self.nodes: dict[str, str] = {}  # caller_id -> caller_api
        self.params: dict[str, Any] = {}
        self.param_subscribers: dict[str, dict[str, str]] = defaultdict(dict)  # key -> caller_id -> api
        self._node_locks: dict[str, asyncio.Lock] = defaultdict(asyncio.Lock)
        self._tasks: set[asyncio.Task] = set()
        self.shutdown_requested = asyncio.Event()

    async def start(self) -> Master:
        await self.server.start()
        log.info("master listening on %s", self.uri)
        return self

    async def __aenter__(self) -> Master:
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def uri(self) -> str:
        return self.server.uri

    @property
    def port(self) -> int:
        return self.server.port

    async def close(self) -> None:
        for t in list(self._tasks):
            t.cancel()
        await self.server.close()

    # ---------------------------------------------------------------- callbacks

    def _notify(self, api: str, method: str, *params: Any) -> None:
        async def run() -> None:
            async with self._node_locks[api]:
                try:
                    await call(api, method, *params, timeout=self.callback_timeout)
                except Exception as err:  # a dead node must not stop the master
                    log.info("%s to %s failed: %s", method, api, err)

        task = asyncio.get_running_loop().create_task(run())
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _publisher_update(self, topic: str) -> None:
        apis = list(self.publishers.get(topic, {}).values())
        for api in self.subscribers.get(topic, {}).values():
            self._notify(api, "publisherUpdate", "/master", topic, apis)

    def _register_node(self, caller_id: str, caller_api: str) -> None:
        old = self.nodes.get(caller_id)
        if old is not None and old != caller_api:
            log.warning("new node registered with the name %s; shutting down the old one at %s", caller_id, old)
            self._drop_node(caller_id, old)
            self._notify(old, "shutdown", "/master", f"[{caller_id}] Reason: new node registered with same name")
        self.nodes[caller_id] = caller_api

    def _drop_node(self, caller_id: str, api: str) -> None:
        for table in (self.publishers, self.subscribers):
            for topic, regs in list(table.items()):
                if regs.get(caller_id) == api:
                    del regs[caller_id]
                    if table is self.publishers:
                        self._publisher_update(topic)
        for svc, (cid, _, capi) in list(self.services.items()):
            if cid == caller_id and capi == api:
                del self.services[svc]
        for regs in self.param_subscribers.values():
            if regs.get(caller_id) == api:
                del regs[caller_id]

    def _node_still_used(self, caller_id: str) -> bool:
        return (
            any(caller_id in r for r in self.publishers.values())
            or any(caller_id in r for r in self.subscribers.values())
            or any(v[0] == caller_id for v in self.services.values())
            or any(caller_id in r for r in self.param_subscribers.values())
        )

    # ---------------------------------------------------------------- dispatch

    async def _handle(self, req: Request) -> Response | Fault:
        fn = getattr(self, "api_" + req.method, None)
        if fn is None:
            return Fault(code=-1, string=f"method {req.method!r} is not supported")
        p = req.params
        if not p or not isinstance(p[0], str):
            return _err("caller_id must be a string")
        try:
            return fn(*p)
        except TypeError as err:
            return _err(f"bad parameters for {req.method}: {err}")

    @staticmethod
    def _strs(*values: Any) -> bool:
        return all(isinstance(v, str) for v in values)

    # ---------------------------------------------------------------- registration

    def api_registerPublisher(self, caller_id: str, topic: str, topic_type: str, caller_api: str) -> Response:
        if not self._strs(topic, topic_type, caller_api):
            return _err("registerPublisher(caller_id, topic, type, caller_api) takes strings")
        self._register_node(caller_id, caller_api)
        self.publishers[topic][caller_id] = caller_api
        if topic_type != "*" or topic not in self.topic_types:
            self.topic_types[topic] = topic_type
        self._publisher_update(topic)
        return _ok(list(self.subscribers.get(topic, {}).values()), f"Registered [{caller_id}] as publisher of [{topic}]")

    def api_registerSubscriber(self, caller_id: str, topic: str, topic_type: str, caller_api: str) -> Response:
        if not self._strs(topic, topic_type, caller_api):
            return _err("registerSubscriber(caller_id, topic, type, caller_api) takes strings")
        self._register_node(caller_id, caller_api)
        self.subscribers[topic][caller_id] = caller_api
        if topic_type != "*" and topic not in self.topic_types:
            self.topic_types[topic] = topic_type
        return _ok(list(self.publishers.get(topic, {}).values()), f"Subscribed to [{topic}]")

    def _unregister(self, table: dict, caller_id: str, topic: str, caller_api: str) -> Response:
        regs = table.get(topic, {})
        if regs.get(caller_id) != caller_api:
            return _ok(0, f"[{caller_id}] is not registered on [{topic}] with that caller_api")
        del regs[caller_id]
        if not regs:
            table.pop(topic, None)
        if not self._node_still_used(caller_id):
            self.nodes.pop(caller_id, None)
        return _ok(1, f"Unregistered [{caller_id}] from [{topic}]")

    def api_unregisterPublisher(self, caller_id: str, topic: str, caller_api: str) -> Response:
        resp = self._unregister(self.publishers, caller_id, topic, caller_api)
        if resp.value[2] == 1:
            self._publisher_update(topic)
        return resp

    def api_unregisterSubscriber(self, caller_id: str, topic: str, caller_api: str) -> Response:
        return self._unregister(self.subscribers, caller_id, topic, caller_api)

    def api_registerService(self, caller_id: str, service: str, service_api: str, caller_api: str) -> Response:
        if not self._strs(service, service_api, caller_api):
            return _err("registerService(caller_id, service, service_api, caller_api) takes strings")
        self._register_node(caller_id, caller_api)
        self.services[service] = (caller_id, service_api, caller_api)
        return _ok(1, f"Registered [{caller_id}] as provider of [{service}]")

    def api_unregisterService(self, caller_id: str, service: str, service_api: str) -> Response:
        cur = self.services.get(service)
        if cur is None or cur[0] != caller_id or cur[1] != service_api:
            return _ok(0, f"[{caller_id}] is not the provider of [{service}] at that service_api")
        del self.services[service]
        if not self._node_still_used(caller_id):
            self.nodes.pop(caller_id, None)
        return _ok(1, f"Unregistered [{caller_id}] as provider of [{service}]")

    # ---------------------------------------------------------------- lookups

    def api_lookupNode(self, caller_id: str, node_name: str) -> Response:
        api = self.nodes.get(node_name)
        return _ok(api, "node api") if api else _err(f"unknown node [{node_name}]", "")

    def api_lookupService(self, caller_id: str, service: str) -> Response:
        cur = self.services.get(service)
        return _ok(cur[1], "rosrpc URI") if cur else _err(f"no provider for [{service}]", "")

    def api_getPublishedTopics(self, caller_id: str, subgraph: str = "") -> Response:
        prefix = subgraph.rstrip("/") + "/" if subgraph else ""
        out = [[t, self.topic_types.get(t, "*")] for t, regs in self.publishers.items() if regs and t.startswith(prefix)]
        return _ok(sorted(out), "current topics")

    def api_getTopicTypes(self, caller_id: str) -> Response:
        return _ok(sorted([t, ty] for t, ty in self.topic_types.items()), "current topic types")

    def api_getSystemState(self, caller_id: str) -> Response:
        pubs = [[t, sorted(r)] for t, r in sorted(self.publishers.items()) if r]
        subs = [[t, sorted(r)] for t, r in sorted(self.subscribers.items()) if r]
        srvs = [[s, [v[0]]] for s, v in sorted(self.services.items())]
        return _ok([pubs, subs, srvs], "current system state")

    def api_getUri(self, caller_id: str) -> Response:
        return _ok(self.uri, "")

    def api_getPid(self, caller_id: str) -> Response:
        return _ok(os.getpid(), "")

    def api_shutdown(self, caller_id: str, msg: str = "") -> Response:
        log.warning("master shutdown requested by %s: %s", caller_id, msg)
        self.shutdown_requested.set()
        return _ok(0, "shutdown")

    # ---------------------------------------------------------------- parameters

    def _get(self, key: str) -> tuple[bool, Any]:
        node: Any = self.params
        for part in [p for p in key.split("/") if p]:
            if not isinstance(node, dict) or part not in node:
                return False, None
            node = node[part]
        return True, node

    def api_getParam(self, caller_id: str, key: str) -> Response:
        found, value = self._get(_canon(key, caller_id))
        return _ok(value, f"Parameter [{key}]") if found else _err(f"Parameter [{key}] is not set")

    def api_hasParam(self, caller_id: str, key: str) -> Response:
        return _ok(self._get(_canon(key, caller_id))[0], key)

    def api_setParam(self, caller_id: str, key: str, value: Any) -> Response:
        name = _canon(key, caller_id)
        parts = [p for p in name.split("/") if p]
        if not parts:
            if not isinstance(value, dict):
                return _err("the root parameter must be a dictionary")
            self.params = value
        else:
            node = self.params
            for part in parts[:-1]:
                if not isinstance(node.get(part), dict):
                    node[part] = {}
                node = node[part]
            node[parts[-1]] = value
        self._param_update(name)
        return _ok(0, f"parameter {name} set")

    def api_deleteParam(self, caller_id: str, key: str) -> Response:
        name = _canon(key, caller_id)
        parts = [p for p in name.split("/") if p]
        node: Any = self.params
        for part in parts[:-1]:
            node = node.get(part) if isinstance(node, dict) else None
        if not parts or not isinstance(node, dict) or parts[-1] not in node:
            return _err(f"parameter [{name}] is not set")
        del node[parts[-1]]
        self._param_update(name)
        return _ok(0, f"parameter {name} deleted")

    def api_searchParam(self, caller_id: str, key: str) -> Response:
        first = key.lstrip("/").split("/")[0]
        ns = caller_id.rsplit("/", 1)[0]
        while True:
            candidate = _canon(first, ns + "/x")
            if self._get(candidate)[0]:
                rest = key.lstrip("/")[len(first):]
                return _ok(candidate + rest, "found")
            if not ns:
                return _err(f"cannot find [{key}]", "")
            ns = ns.rsplit("/", 1)[0]

    def api_subscribeParam(self, caller_id: str, caller_api: str, key: str) -> Response:
        name = _canon(key, caller_id)
        self.param_subscribers[name][caller_id] = caller_api
        found, value = self._get(name)
        return _ok(value if found else {}, f"subscribed to [{name}]")

    def api_unsubscribeParam(self, caller_id: str, caller_api: str, key: str) -> Response:
        regs = self.param_subscribers.get(_canon(key, caller_id), {})
        if regs.get(caller_id) == caller_api:
            del regs[caller_id]
            return _ok(1, "unsubscribed")
        return _ok(0, "not subscribed")

    def api_getParamNames(self, caller_id: str) -> Response:
        names: list[str] = []

        def walk(prefix: str, node: Any) -> None:
            for k, v in node.items():
                full = prefix + "/" + k
                if isinstance(v, dict) and v:
                    walk(full, v)
                else:
                    names.append(full)

        walk("", self.params)
        return _ok(sorted(names), "parameter names")

    def _param_update(self, name: str) -> None:
        for key, regs in self.param_subscribers.items():
            if key == name or key.startswith(name.rstrip("/") + "/") or name.startswith(key.rstrip("/") + "/"):
                found, value = self._get(key)
                for cid, api in regs.items():
                    self._notify(api, "paramUpdate", "/master", key + "/", value if found else {})


async def serve(host: str, port: int) -> None:
    """Run a master until cancelled or asked to shut down."""
    master = Master(host, port)
    await master.start()
    try:
        await master.shutdown_requested.wait()
    finally:
        with contextlib.suppress(Exception):
            await master.close()
