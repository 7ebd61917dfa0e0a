"""Stand-ins for seed 002's two computers, calibrated from published single-thread figures.

A stand-in is a cgroup tree: a parent limited to ``cores x ratio`` of this machine's
CPU (the computer's cores at its single-thread speed relative to one vCPU here), and one
child per process limited to ``ratio`` of one core (one thread cannot run faster than one
of the computer's cores). ``ratio`` is the computer's published single-thread rating over
this CPU's (:data:`SINGLE_THREAD`); :func:`check` times a reference workload (pure Python
and a 3DES pass over an 80 KB buffer) unthrottled and in a child at ``ratio`` and
reports the effective ratio the cgroup delivered.

cgroup v1 (``cpu.cfs_quota_us``, nested quotas) or v2 (``cpu.max``); no cgroup: a
:class:`~cryptoros.errors.ConfigError` (the stand-in needs root and a cpu controller).
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from cryptoros.errors import ConfigError

#: Published single-thread ratings (PassMark's CPU benchmark pages, cpubenchmark.net,
#: "Single Thread Rating"; approximate figures recalled from those pages, not re-checked
#: from this machine, not measured here): the paper's two computers and the CPU family of
#: this machine (AMD EPYC 9004, Zen 4).
#: Cross-check from a retrieved source: Tom's Hardware ("Intel Fires Up New Atom
#: Processors") quotes SPECint2000 653 for a 1.6 GHz Atom core against about 1,900 for
#: a 1.86 GHz Core 2 Duo E6300 core: an Atom core at 1.8 GHz is about 0.39 of a Core 2
#: core, and an Ivy Bridge i7 core about 1.7 Core 2 cores, so 0.23 of an i7-3612QM core,
#: where PassMark's figures give 0.21.
SINGLE_THREAD = {
    "Atom D525": {"rating": 330, "cores": 2, "source": "PassMark single-thread rating, Intel Atom D525 @ 1.80GHz"},
    "i7-3612QM": {"rating": 1600, "cores": 4, "source": "PassMark single-thread rating, Intel Core i7-3612QM @ 2.10GHz"},
    "this CPU": {"rating": 2800, "cores": None, "source": "PassMark single-thread rating of AMD EPYC 9004 (Zen 4) "
                                                          "parts, about 2,700 to 3,000; one vCPU of this VM"},
}
PERIOD_US = 100_000


def ratio(cpu: str) -> float:
    """A core of ``cpu`` over one vCPU here, by published single-thread rating."""
    return SINGLE_THREAD[cpu]["rating"] / SINGLE_THREAD["this CPU"]["rating"]


def _cpu_root() -> tuple[str, Path]:
    for line in Path("/proc/mounts").read_text().splitlines():
        parts = line.split()
        if len(parts) >= 4 and parts[2] == "cgroup" and "cpu" in parts[3].split(","):
            return "v1", Path(parts[1])
    for line in Path("/proc/mounts").read_text().splitlines():
        parts = line.split()
        if len(parts) >= 3 and parts[2] == "cgroup2":
            root = Path(parts[1])
            with contextlib.suppress(OSError):
                if "cpu" in (root / "cgroup.controllers").read_text().split():
                    return "v2", root
    raise ConfigError("the stand-in needs a cgroup cpu controller (v1 cpu or v2 cpu.max)")


def _set_quota(version: str, path: Path, cores: float) -> None:
    quota = max(1000, int(cores * PERIOD_US))
    if version == "v2":
        (path / "cpu.max").write_text(f"{quota} {PERIOD_US}")
    else:
        (path / "cpu.cfs_period_us").write_text(str(PERIOD_US))
        (path / "cpu.cfs_quota_us").write_text(str(quota))


@dataclass
class StandIn:
    """A computer of ``cores`` cores at ``per_core`` of one vCPU here each."""

    name: str
    cores: int
    per_core: float
    version: str = ""
    root: Path | None = None
    _children: list[Path] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.version, base = _cpu_root()
        self.root = base / f"cryptoros-standin-{os.getpid()}-{self.name.replace(' ', '_')}"
        try:
            self.root.mkdir(exist_ok=True)
            if self.version == "v2":
                with contextlib.suppress(OSError):
                    (self.root / "cgroup.subtree_control").write_text("+cpu")
            _set_quota(self.version, self.root, self.cores * self.per_core)
        except OSError as exc:
            raise ConfigError(f"cannot make the stand-in's cgroup {self.root}: {exc}") from None

    @property
    def total(self) -> float:
        return self.cores * self.per_core

    def describe(self) -> str:
        return (f"{self.name} stand-in: cgroup {self.version}, {self.cores} cores x {self.per_core:.3f} of a vCPU "
                f"(each process at most {self.per_core:.3f}, all together {self.total:.3f}), period "
                f"{PERIOD_US // 1000} ms")

    def attach(self, pid: int) -> None:
        assert self.root is not None
        child = self.root / f"p{pid}"
        child.mkdir(exist_ok=True)
        _set_quota(self.version, child, self.per_core)
        (child / "cgroup.procs").write_text(str(pid))
        self._children.append(child)

    def close(self) -> None:
        for child in self._children:
            with contextlib.suppress(OSError):
                child.rmdir()
        if self.root is not None:
            with contextlib.suppress(OSError):
                self.root.rmdir()

    def __enter__(self) -> StandIn:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def standin(cpu: str) -> StandIn:
    spec = SINGLE_THREAD[cpu]
    return StandIn(cpu, int(spec["cores"]), ratio(cpu))


REFERENCE = r"""
import sys, time
from Cryptodome.Cipher import DES3
print("READY", flush=True)
sys.stdin.readline()
buf = bytes(81920); key = bytes(range(1, 25)); iv = bytes(8)
def work():
    s = 0
    for i in range(200000):
        s += i * i % 7
    DES3.new(key, DES3.MODE_CBC, iv).encrypt(buf)
t0, c0, n = time.perf_counter(), time.process_time(), 0
while n < 3 or time.perf_counter() - t0 < float(sys.argv[1]):
    work(); n += 1
print((time.perf_counter() - t0) / n, (time.process_time() - c0) / n, flush=True)
"""


def _time_reference(seconds: float, stand: StandIn | None) -> tuple[float, float]:
    """(wall seconds, CPU seconds) per pass of the reference workload."""
    proc = subprocess.Popen(["/usr/bin/python3", "-c", REFERENCE, str(seconds)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdin is not None
        if proc.stdout.readline().strip() != "READY":
            raise ConfigError("the reference workload did not start (Debian's python3-pycryptodome?)")
        if stand is not None:
            stand.attach(proc.pid)
        proc.stdin.write("go\n")
        proc.stdin.flush()
        out = proc.stdout.readline()
        proc.wait(timeout=seconds * 20 + 30)
        wall, cpu = out.split()
        return float(wall), float(cpu)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def check(stand: StandIn, seconds: float = 2.0) -> dict:
    """The reference workload per pass: its CPU time unthrottled (the work, whatever the
    load; its wall time is printed too) against its wall time in ``stand``'s child quota:
    the effective share of a vCPU the cgroup delivered against the intended ``per_core``.
    On a loaded machine the stand-in can get less than its quota (effective < intended)."""
    load = os.getloadavg()[0]
    free_wall, free_cpu = _time_reference(seconds, None)
    throttled_wall, _ = _time_reference(seconds * 2, stand)
    return {"unthrottled_s": free_cpu, "unthrottled_wall_s": free_wall, "standin_s": throttled_wall,
            "effective_ratio": free_cpu / throttled_wall, "intended_ratio": stand.per_core, "loadavg_1min": load}


def describe_sources() -> str:
    return "; ".join(f"{k}: {v['rating']} ({v['source']})" for k, v in SINGLE_THREAD.items())


__all__ = ["SINGLE_THREAD", "StandIn", "check", "describe_sources", "ratio", "standin"]

if __name__ == "__main__":  # pragma: no cover - a manual check
    with standin(sys.argv[1] if len(sys.argv) > 1 else "Atom D525") as s:
        print(s.describe(), check(s, 1.0))
