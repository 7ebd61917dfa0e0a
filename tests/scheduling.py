"""How the test files are shared among xdist workers (``scripts/test``): a whole file to
one worker, as ``--dist loadfile`` does, with two changes.

- The files that keep both cores busy on their own (the demo's missions, the benchmarks'
  quick runs, the monitor's training) are one work unit: they run one after another on
  one worker, never two at once, so the tests beside them keep a core between them.
- The long units are handed out first (longest first), so that no long file starts
  last and runs alone at the end.

The seconds below are what each file took in a two-worker run on the two-core CI
machine (``--durations=0``, summed per file); they only order the work. A file not
listed runs after them, in xdist's order.
"""

from __future__ import annotations

from xdist.scheduler import LoadFileScheduling

#: files that saturate the machine by themselves (seconds measured per file)
HEAVY = {
    "tests/system/test_demo.py": 207,
    "tests/system/test_bench_interceptor.py": 48,
    "tests/system/test_bench_scale.py": 44,
    "tests/system/test_ros2_demo.py": 42,
    "tests/system/test_bench_cipher_replay.py": 40,
    "tests/system/test_bench_fleet.py": 40,
    "tests/system/test_monitor_dataset.py": 31,
    "tests/system/test_bench_soak.py": 18,
    "tests/system/test_bench_ciphers.py": 12,
    "tests/system/test_bench_ros2.py": 11,
}
HEAVY_UNIT = "heavy files, one at a time"
#: other files of a minute or more (seconds measured per file)
LONG = {
    "tests/system/test_ros2.py": 113,
    "tests/system/test_ros2_hardening.py": 88,
    "tests/system/test_learning.py": 80,
    "tests/system/test_authz_audit_changes.py": 78,
    "tests/system/test_learning_ros2.py": 76,
    "tests/system/test_ros2_operations.py": 70,
    "tests/system/test_stock_tools.py": 70,
    "tests/system/test_ros2_attack_aftermath.py": 61,
    "tests/system/test_runbook.py": 61,
    "tests/system/test_day2_live.py": 60,
    "tests/system/test_monitor_live.py": 60,
}
SECONDS = {HEAVY_UNIT: sum(HEAVY.values()), **LONG}


class HeavyApartScheduling(LoadFileScheduling):
    """``--dist loadfile`` with the heavy files in one unit and the long units first."""

    def __init__(self, config, log=None) -> None:
        super().__init__(config, log)
        self._ordered = False  # the queue is put longest first when the first unit is handed out

    def _split_scope(self, nodeid: str) -> str:
        path = nodeid.split("::", 1)[0]
        return HEAVY_UNIT if path in HEAVY else path

    def _assign_work_unit(self, node) -> None:
        if not self._ordered:  # the first unit handed out: order the queue once
            self._ordered = True
            for unit in sorted((u for u in self.workqueue if u in SECONDS), key=SECONDS.get):
                self.workqueue.move_to_end(unit, last=False)  # shortest moved first: the longest ends in front
        super()._assign_work_unit(node)


def pytest_xdist_make_scheduler(config, log):
    if config.getvalue("dist") == "loadfile":
        return HeavyApartScheduling(config, log)
    return None
