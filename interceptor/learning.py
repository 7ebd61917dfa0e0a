"""Learning mode in a running interceptor: the state the verifier decides with, the
reports to the authorization server, and how the interceptor says it is learning.

:mod:`cryptoros.learning` decides (grants widened while a manager learns, requests
recorded); this module does the I/O around it:

- every ``REPORT_INTERVAL`` seconds, what was recorded is posted to the authorization
  server (``POST /observations``, over the interceptor's own mutual TLS: the server
  files it under the manager the certificate belongs to, and takes learned requests
  only while that manager learns); a report the server cannot take now is kept for the
  next one; one it refuses as sent (a malformed row) is halved until the row it refuses
  stands alone, which is dropped and logged, so one bad row never holds back the rest;
- while this interceptor's own manager learns, every log line starts with
  ``LEARNING``, ``status`` and ``/healthz`` say until when, and the metric
  ``cryptoros_interceptor_learning`` is 1; the start and the end of a window are logged.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

from prometheus_client import Gauge

from cryptoros.errors import TokenError
from cryptoros.learning import LearningState
from interceptor.authz_client import ReportRefused

log = logging.getLogger(__name__)

#: seconds between two reports to the authorization server
REPORT_INTERVAL = 5.0
#: rows in one report (the server takes at most MAX_OBSERVATION_ROWS per request, in its 16 KiB body)
REPORT_ROWS = 50


class LearningLogFilter(logging.Filter):
    """Starts every log record's message with ``LEARNING`` while the window lasts (a
    filter on the handler: the lines of every module, asyncio's and aiohttp's too)."""

    def __init__(self, state: LearningState) -> None:
        super().__init__()
        self.state = state

    def filter(self, record: logging.LogRecord) -> bool:
        if self.state.learning(self.state.own) and not getattr(record, "_learning_marked", False):
            record.msg = f"LEARNING {record.msg}"
            record._learning_marked = True
        return True


class Learner:
    """The interceptor's side of learning mode (one per gateway)."""

    def __init__(self, own: str, *, serves_everyone: bool, authz: Any, registry: Any) -> None:
        self.state = LearningState(own, serves_everyone=serves_everyone)
        self._authz = authz
        self._gauge = Gauge("cryptoros_interceptor_learning",
                            "1 while this interceptor's manager is in learning mode", registry=registry)
        self._filter = LearningLogFilter(self.state)
        self._was_learning = False
        self._unreported = False  # a report failed (the authorization server out of reach): said once
        self.reported = 0
        self.refused = 0

    def install_log_marker(self) -> None:
        for handler in logging.getLogger().handlers:
            if self._filter not in handler.filters:
                handler.addFilter(self._filter)

    def remove_log_marker(self) -> None:
        for handler in logging.getLogger().handlers:
            handler.removeFilter(self._filter)

    def status(self) -> dict | None:
        """``status``'s ``learning``: None unless this manager learns now."""
        until = self.state.until(self.state.own)
        if until is None:
            return None
        learned = self.state.table.learned()
        return {"until": until, "left": round(until - time.time()), "learned": len(learned),
                "top": learned[:10], "reported": self.reported}

    def health_note(self) -> str | None:
        until = self.state.until(self.state.own)
        if until is None:
            return None
        return (f"LEARNING until {time.strftime('%H:%M:%S', time.localtime(until))} ({until - time.time():.0f} s "
                "left): requests no grant covers are let through and recorded (cryptoros-authz learn propose)")

    def _tick(self) -> None:
        learning = self.state.learning(self.state.own)
        self._gauge.set(1 if learning else 0)
        if learning != self._was_learning:
            self._was_learning = learning
            if learning:
                log.warning("%s", self.health_note())
            else:
                log.warning("learning mode ended: requests no grant covers are refused again")

    async def report(self) -> None:
        """Post what is due; kept for the next report when the server cannot take it.
        A report the server refuses as sent is posted again in halves, down to the one
        row it refuses, which is dropped: sent again it would be refused again, forever,
        and with it every row of its report."""
        rows = self.state.table.due(time.time())
        batches = [rows[start:start + REPORT_ROWS] for start in range(0, len(rows), REPORT_ROWS)]
        while batches:
            batch = batches.pop(0)
            try:
                answer = await self._authz.post_observations(batch)
            except ReportRefused as exc:
                if len(batch) > 1:
                    half = len(batch) // 2
                    batches[:0] = [batch[:half], batch[half:]]
                else:
                    self.refused += 1
                    row = batch[0]
                    log.warning("observation dropped, the authorization server refuses it (%s): %s %s %s %s",
                                exc.detail, row["node"], row["action"], row["name"], row["type"] or "")
                continue
            except TokenError as exc:
                self.state.table.unreport([row for rest in (batch, *batches) for row in rest])
                if not self._unreported:  # once per outage, not every REPORT_INTERVAL
                    log.info("observations not reported yet (%s): kept for the next report", exc.detail)
                self._unreported = True
                return
            if self._unreported:
                log.info("observations reported again")
                self._unreported = False
            self.reported += int(answer.get("accepted", 0))
            self.refused += int(answer.get("refused", 0))

    async def run(self) -> None:
        while True:
            self._tick()
            await self.report()
            await asyncio.sleep(REPORT_INTERVAL)


__all__ = ["Learner", "LearningLogFilter", "REPORT_INTERVAL"]
