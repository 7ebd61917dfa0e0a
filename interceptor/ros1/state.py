"""What the ROS 1 role keeps across its own restarts (``state_dir``): exports, relays,
owners, the registrations kept for rosmaster, local subscribers, this host's nodes'
registrations (made and refused), the source addresses verified peers streamed from."""

from __future__ import annotations

import asyncio
import contextlib
import json

from interceptor.ros1.wire import (
    log,
)
from interceptor.statefile import write_private_json

#: seconds from a change of the state to its write (changes in between join it)
STATE_SAVE_DELAY = 0.05


class PersistedState:
    """The state file of :class:`~interceptor.ros1.role.Ros1Role` (a part of it)."""

    # ---------------------------------------------------------------- state across restarts
    def _state_path(self):
        return None if self.cfg.state_dir is None else self.cfg.state_dir / f"{self.cfg.manager}.state.json"

    def _state_data(self) -> dict:
        data = {"version": 1, "translator": self.translator.snapshot(), "topic_types": self.topic_types,
                "local_subscribers": self._local_subscribers,
                "node_apis": self._node_apis,
                "export_children": {api: sorted(ids) for api, ids in self._export_children.items()},
                "waiting": [[method, list(params)] for method, params in self._ledger.refused_items()],
                # this host's nodes' registrations; the master role's ("registrations") are its ledger's
                "local_registrations": [[method, list(params)] for method, params in self._ledger.made_items()],
                "known_sources": self.gw.known_sources()}
        master = self._master_ledger.snapshot()
        if master.keys() & data.keys():  # one file for both roles: a shared key would lose one table
            raise RuntimeError(f"state keys of both roles: {sorted(master.keys() & data.keys())}")
        return {**data, **master}

    def _save_state(self) -> None:
        """Keep the tables a restart would otherwise lose (written atomically), now, on
        this thread: at start and at stop; every change in between calls
        :meth:`_save_state_soon`."""
        path = self._state_path()
        if path is None or not self._state_loaded:
            return
        self._state_dirty = False
        try:
            write_private_json(path, self._state_data())
            self._state_saves += 1
        except OSError as exc:
            log.error("cannot keep state in %s: %s", path, exc)

    def _save_state_soon(self) -> None:
        """Save :data:`STATE_SAVE_DELAY` after a change, off the event loop: a burst of
        changes (a robot's nodes registering at once, a multicall) is one write, and a
        disk slow to rename never holds a call. The tables are read on the loop; the
        file is written and renamed in a thread, one write at a time, the newest last."""
        if self._state_path() is None or not self._state_loaded:
            return
        self._state_dirty = True
        if self._save_task is not None:
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no loop (start-up code, tests of the tables): now
            self._save_state()
            return
        self._save_task = loop.create_task(self._save_state_later(), name="state-save")

    async def _save_state_later(self) -> None:
        path = self._state_path()
        try:
            while self._state_dirty:
                await asyncio.sleep(STATE_SAVE_DELAY)
                self._state_dirty = False
                text = json.dumps(self._state_data())
                try:
                    await asyncio.to_thread(write_private_json, path, text, encoded=True)
                    self._state_saves += 1
                except OSError as exc:
                    log.error("cannot keep state in %s: %s", path, exc)
        finally:
            self._save_task = None

    async def _flush_state(self) -> None:
        """At stop: the write under way finished, then what changed since written now."""
        task = self._save_task
        if task is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(asyncio.shield(task), 5)
            if not task.done():
                task.cancel()
        if self._state_dirty:
            self._save_state()

    def _load_state(self) -> None:
        path = self._state_path()
        self._state_loaded = True
        if path is None or not path.exists():
            return
        try:
            data = json.loads(path.read_text())
            if data.get("version") != 1:
                raise ValueError(f"unknown state version {data.get('version')!r}")
            problems = self.translator.restore(data["translator"])
            self.topic_types.update({str(k): str(v) for k, v in data.get("topic_types", {}).items()})
            self._master_ledger.restore(data)
            for method, params in data.get("local_registrations", [])[:self._ledger.max_entries]:
                self._ledger.made(str(method), tuple(str(p) for p in params))
            for method, params in data.get("waiting", [])[:self._ledger.max_refused]:
                self._ledger.refused(str(method), tuple(str(p) for p in params))
            for topic, subscribers in data.get("local_subscribers", {}).items():
                self._local_subscribers[str(topic)] = {str(n): str(api) for n, api in subscribers.items()}
            self._node_apis.update({str(n): str(i) for n, i in data.get("node_apis", {}).items()})
            for api, ids in data.get("export_children", {}).items():
                self._export_children[str(api)] = {str(i) for i in ids}
            self.gw.know_sources([str(a) for a in data.get("known_sources", [])])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.error("state in %s not used (%s): nodes of this host may need a restart", path, exc)
            return
        for problem in problems:
            log.warning("state: %s", problem)
        log.info("state restored from %s: %d exports, %d relays, %d published topics", path,
                 len(data["translator"].get("exports", {})), self.translator.relay_count, len(self.topic_types))
        self._save_state()

