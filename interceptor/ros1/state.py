"""What the ROS 1 role keeps across its own restarts (``state_dir``): exports, relays,
owners, the registrations kept for rosmaster, local subscribers, refused registrations."""

from __future__ import annotations

import asyncio
import json

from interceptor.ros1.wire import (
    log,
)
from interceptor.statefile import write_private_json


class PersistedState:
    """The state file of :class:`~interceptor.ros1.role.Ros1Role` (a part of it)."""

    # ---------------------------------------------------------------- state across restarts
    def _state_path(self):
        return None if self.cfg.state_dir is None else self.cfg.state_dir / f"{self.cfg.manager}.state.json"

    def _save_state(self) -> None:
        """Keep the tables a restart would otherwise lose (written atomically)."""
        path = self._state_path()
        if path is None or not self._state_loaded:
            return
        data = {"version": 1, "translator": self.translator.snapshot(), "topic_types": self.topic_types,
                **self._master_ledger.snapshot(),
                "local_subscribers": self._local_subscribers,
                "node_apis": self._node_apis,
                "export_children": {api: sorted(ids) for api, ids in self._export_children.items()},
                "waiting": [[method, list(params)] for method, params in self._ledger.refused_items()]}
        try:
            write_private_json(path, data)
            self._state_saves += 1
        except OSError as exc:
            log.error("cannot keep state in %s: %s", path, exc)

    def _save_state_soon(self) -> None:
        """Save once after this turn of the loop (a multicall changes many owners)."""
        if self._state_path() is not None and not self._save_pending:
            self._save_pending = True

            def save() -> None:
                self._save_pending = False
                self._save_state()

            asyncio.get_running_loop().call_soon(save)

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
            for method, params in data.get("waiting", [])[:self._ledger.max_refused]:
                self._ledger.refused(str(method), tuple(str(p) for p in params))
            for topic, subscribers in data.get("local_subscribers", {}).items():
                self._local_subscribers[str(topic)] = {str(n): str(api) for n, api in subscribers.items()}
            self._node_apis.update({str(n): str(i) for n, i in data.get("node_apis", {}).items()})
            for api, ids in data.get("export_children", {}).items():
                self._export_children[str(api)] = {str(i) for i in ids}
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.error("state in %s not used (%s): nodes of this host may need a restart", path, exc)
            return
        for problem in problems:
            log.warning("state: %s", problem)
        log.info("state restored from %s: %d exports, %d relays, %d published topics", path,
                 len(data["translator"].get("exports", {})), self.translator.relay_count, len(self.topic_types))
        self._save_state()

