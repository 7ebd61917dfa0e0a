"""The monitor's detector: per kind of topic, one upper limit per feature.

Fitted on clean recordings only (``fit``): a feature's limit is its ``quantile`` over
the clean messages times ``margin``, plus a small absolute floor so a feature that is
always zero when clean (a stamp that never goes back) still needs a real excursion.
A message's score is its worst feature's value over that feature's limit; above 1 the
message is suspicious, and ``consecutive`` suspicious messages in a row from one
publisher on one topic raise an alert; so does one message ``severe`` times over
(a claim far out of what clean traffic ever shows needs no second one: a false map is
believed at the first). Why limits and not a classifier trained on
attacks: the attacks a compromised robot will try are not the ones recorded, and a
limit learned from normal traffic flags any excursion of a feature, whatever caused
it; the recorded attacks measure it (``cryptoros monitor eval``).

The model is a small JSON file (``save``/``load``), checked on load: the interceptor
refuses to start with a model that does not parse.
"""

from __future__ import annotations

import functools
import json
import math
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

from cryptoros.errors import ConfigError
from cryptoros.monitor.features import FEATURES

FORMAT = "cryptoros-monitor-model/1"
#: absolute floors added to every limit (a feature that is 0 on clean data needs this much)
FLOORS = {"rate_hz": 2.0, "burst_hz": 2.0, "size_change": 0.05, "malformed": 0.5, "speed_mps": 0.2, "stamp_back_s": 0.05,
          "stamp_lag_s": 0.5, "roughness": 0.05, "scan_change": 0.05, "linear": 0.1, "angular": 0.1,
          "geometry_change": 0.5, "beacon_gap_m": 0.3, "unseen_claim": 0.05,
          "walls_erased": 0.05}


class Score(NamedTuple):
    """One message's score (a named tuple: made for every message scored, at a
    tuple's cost rather than a frozen dataclass's)."""

    value: float  # worst feature value / its limit
    feature: str  # the worst feature


@dataclass(frozen=True)
class MonitorModel:
    #: kind -> feature -> upper limit
    limits: Mapping[str, Mapping[str, float]]
    consecutive: int = 3
    #: a message this many times over its limit alerts on its own (0: never alone)
    severe: float = 5.0
    quantile: float = 0.999
    margin: float = 1.5
    #: what the model was fitted on (messages per kind), for ``cryptoros monitor eval``
    trained_on: Mapping[str, int] = field(default_factory=dict)

    def prepare(self) -> MonitorModel:
        """Build the per-kind tables :meth:`score` reads now (an interceptor's start-up),
        not on the first message scored."""
        self._limits_by_kind  # noqa: B018  (a cached property: computed once)
        return self

    def score(self, kind: str, values: tuple[float, ...]) -> Score:
        worst, name = 0.0, ""
        for (feature, limit), value in zip(self._limits_by_kind[kind], values):
            if limit is None:
                continue
            if not math.isfinite(value):  # NaN or inf in a message is never clean (NaN compares false)
                return Score(math.inf, feature)
            ratio = value / limit
            if ratio > worst:
                worst, name = ratio, feature
        return Score(worst, name)

    @functools.cached_property
    def _limits_by_kind(self) -> dict[str, tuple[tuple[str, float | None], ...]]:
        """Per kind, (feature, its limit or None) in the order the features come."""
        out = {}
        for kind, names in FEATURES.items():
            limits = self.limits.get(kind) or self.limits.get("any") or {}
            out[kind] = tuple((feature, limits.get(feature)) for feature in names)
        return out

    def is_severe(self, score: Score, threshold: float = 1.0) -> bool:
        """``score`` alone is enough for an alert (limits multiplied by ``threshold``)."""
        return bool(self.severe) and score.value >= self.severe * threshold

    # -- fitting
    @classmethod
    def fit(cls, rows: Mapping[str, Iterable[tuple[float, ...]]], *, quantile: float = 0.999, margin: float = 1.5,
            consecutive: int = 3, severe: float = 5.0) -> MonitorModel:
        """Limits from clean messages' features, per kind (``rows[kind]``)."""
        if not 0.5 <= quantile <= 1.0 or margin < 1.0 or consecutive < 1 or not (severe == 0 or 1 < severe <= 1000):
            raise ConfigError("quantile must be in 0.5..1, margin >= 1, consecutive >= 1, severe 0 (off) or in 1..1000")
        tables = {kind: list(kind_rows) for kind, kind_rows in rows.items()}
        if "any" not in tables:  # every type is watched at least for rate and size
            tables["any"] = [row[:len(FEATURES["any"])] for table in tables.values() for row in table]
        limits: dict[str, dict[str, float]] = {}
        counts: dict[str, int] = {}
        for kind, table in tables.items():
            if not table:
                continue
            counts[kind] = len(table)
            limits[kind] = {}
            for i, name in enumerate(FEATURES[kind]):
                column = sorted(row[i] for row in table)
                q = column[min(len(column) - 1, math.ceil(quantile * len(column)) - 1)]
                limits[kind][name] = round(q * margin + FLOORS.get(name, 0.05), 6)
        return cls(limits=limits, consecutive=consecutive, severe=severe, quantile=quantile, margin=margin,
                   trained_on=counts)

    # -- the file
    def to_json(self) -> dict:
        return {"format": FORMAT, "consecutive": self.consecutive, "severe": self.severe, "quantile": self.quantile, "margin": self.margin,
                "trained_on": dict(self.trained_on), "limits": {k: dict(v) for k, v in self.limits.items()}}

    def save(self, path: str | os.PathLike[str]) -> None:
        path = Path(path)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=1) + "\n")
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> MonitorModel:
        """A model file, checked: every problem is one :class:`ConfigError` line."""
        try:
            raw = json.loads(Path(path).read_text())
        except FileNotFoundError:
            raise ConfigError(f"monitor model not found: {path}") from None
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise ConfigError(f"monitor model {path}: {exc}") from None
        return cls.from_json(raw, str(path))

    @classmethod
    def from_json(cls, raw: object, where: str = "monitor model") -> MonitorModel:
        if not isinstance(raw, dict) or raw.get("format") != FORMAT:
            raise ConfigError(f"{where}: not a {FORMAT} file")
        limits_raw = raw.get("limits")
        if not isinstance(limits_raw, dict) or not limits_raw:
            raise ConfigError(f"{where}: no limits")
        limits: dict[str, dict[str, float]] = {}
        for kind, table in limits_raw.items():
            if kind not in FEATURES or not isinstance(table, dict):
                raise ConfigError(f"{where}: unknown kind {kind!r} (known: {', '.join(FEATURES)})")
            for name, value in table.items():
                if name not in FEATURES[kind]:
                    raise ConfigError(f"{where}: {kind} has no feature {name!r}")
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0 \
                        or not math.isfinite(value):
                    raise ConfigError(f"{where}: {kind}.{name} must be a positive number, got {value!r}")
            limits[kind] = {name: float(value) for name, value in table.items()}
        consecutive = raw.get("consecutive", 3)
        if isinstance(consecutive, bool) or not isinstance(consecutive, int) or not 1 <= consecutive <= 1000:
            raise ConfigError(f"{where}: consecutive must be an integer in 1..1000")
        severe = raw.get("severe", 5.0)
        if isinstance(severe, bool) or not isinstance(severe, (int, float)) or not (severe == 0 or 1 < severe <= 1000):
            raise ConfigError(f"{where}: severe must be 0 (off) or a number in 1..1000")
        trained = raw.get("trained_on", {})
        return cls(limits=limits, consecutive=consecutive, severe=float(severe), quantile=float(raw.get("quantile", 0.999)),
                   margin=float(raw.get("margin", 1.5)),
                   trained_on=trained if isinstance(trained, dict) else {})


class AlertTracker:
    """Consecutive suspicious messages per stream -> an alert (once per run of them); a
    severe message completes the run at once."""

    __slots__ = ("needed", "_run")

    def __init__(self, needed: int) -> None:
        self.needed = needed
        self._run = 0

    def update(self, suspicious: bool, severe: bool = False) -> bool:
        """True exactly when the run of suspicious messages reaches ``needed`` (a severe
        message reaches it at once)."""
        if severe and self._run < self.needed:
            self._run = self.needed
            return True
        self._run = self._run + 1 if suspicious or severe else 0
        return self._run == self.needed

    @property
    def flagged(self) -> bool:
        """The last message is in a run of ``needed`` or more suspicious ones."""
        return self._run >= self.needed


__all__ = ["FORMAT", "AlertTracker", "MonitorModel", "Score"]
