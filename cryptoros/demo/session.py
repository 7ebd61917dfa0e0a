"""One ``cryptoros demo`` run: each mode's mission (ROS 1: :mod:`cryptoros.demo.run`,
ROS 2: :mod:`cryptoros.demo.ros2`), judged, with what it left behind checked.

Kept apart from both missions so neither imports the other's module back.
"""

from __future__ import annotations

import dataclasses
import shutil
import socket
import tempfile
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

from cryptoros.demo import ros2
from cryptoros.demo.attackers import ATTACKS, target_of
from cryptoros.demo.run import ALL_ATTACKS, Children, DemoError, DemoOptions, Mission, attacker_role, judge
from cryptoros.errors import CryptorosError


def run_demo(opts: DemoOptions, progress: Callable[[dict[str, Any]], None] = lambda _e: None,
             note: Callable[[str], None] = lambda _m: None) -> dict[str, Any]:
    if opts.robots < 2:
        raise DemoError("the demo needs at least 2 robots")
    mission_class, role, what = Mission, attacker_role, {}
    if opts.ros == 2:
        mission_class, role, what = ros2.Ros2Mission, ros2.attacker_role, ros2.WHAT
        known = ros2.ROS2_ATTACKS
    elif opts.ros == 1:
        known = ALL_ATTACKS
    else:
        raise DemoError(f"ros must be 1 or 2, not {opts.ros}")
    for a in opts.attacks:
        if a not in known:
            raise DemoError(f"unknown attack {a!r} for ROS {opts.ros}; one of {', '.join(known)}")
    if "monitored" in opts.modes and opts.ros != 1:
        raise DemoError("the monitored mode runs the ROS 1 demo (the ROS 2 role's monitor: docs/monitor.md)")
    workdir = Path(opts.workdir) if opts.workdir else Path(tempfile.mkdtemp(prefix="cryptoros-demo-"))
    workdir.mkdir(parents=True, exist_ok=True)
    ended = False  # the missions ran to their end (the caller removes a throwaway workdir then)
    children = Children()
    result: dict[str, Any] = {"config": {**asdict(opts), "attacks": list(opts.attacks), "modes": list(opts.modes)},
                              "workdir": str(workdir), "modes": {}, "attacks": {}}
    missions: list[dict[str, Any]] = []  # every mission's result, for the clean-up checks
    try:
        if "monitored" in opts.modes and not opts.monitor_model:
            opts = dataclasses.replace(opts, monitor_model=calibrate(opts, workdir / "calibration", children, note))
            result["calibration"] = {"model": opts.monitor_model, "seconds": CALIBRATION_S}
        plans = [(k, dataclasses.replace(opts, attacks=(k,))) for k in opts.attacks] if opts.isolate else [(None, opts)]
        for name, plan in plans:
            here = workdir / name if name else workdir
            modes: dict[str, Any] = {}
            for mode in opts.modes:
                note(f"{mode}{f' ({name} alone)' if name else ''}: starting "
                     f"{'the master' if mode == 'plain' else 'PKI, authorization server, master and interceptors'}"
                     f" and {opts.robots} robots")
                res = mission_class(plan, mode, here, children, progress).run()
                res["judged"] = judge(res, plan.attacks, opts.robots)
                modes[mode] = res
                missions.append(res)
            if name:
                result.setdefault("isolated", {})[name] = modes
            else:
                result["modes"] = modes
            for k in plan.attacks:
                entry = {"seed": ATTACKS[k]["seed"],
                         "what": what.get(k, ATTACKS[k]["what"]).format(t=target_of(k, opts.robots) or ""),
                         "protected_attacker": role(k, opts.robots)}
                for mode, res in modes.items():
                    entry[mode] = res["judged"][k]
                    if name:
                        entry[mode] = {**entry[mode], "coverage": res["coverage"], "end_reason": res["end_reason"]}
                result["attacks"][k] = entry
        ended = True
    finally:
        children.kill_all()
        if not ended and opts.workdir is None and not opts.keep:
            # Ctrl-C or a failure: the throwaway directory goes too (it holds the demo's CA
            # and robot keys; a newcomer audit found it left in /tmp after each Ctrl-C)
            shutil.rmtree(workdir, ignore_errors=True)
    for res in missions:
        res.pop("_final", None)
    result["children_started"] = len(children.procs)
    result["leftover_children"] = [p.pid for p in children.procs if p.poll() is None]
    result["ports_still_open"] = [list(p) for res in missions for p in free_after(res.get("ports", []))]
    return result


#: wall seconds of the clean mission the monitor's model is trained on
CALIBRATION_S = 12.0


def calibrate(opts: DemoOptions, workdir: Path, children: Children, note: Callable[[str], None]) -> str:
    """A clean plain mission of the same team, recorded through ``cryptoros monitor record``,
    and the monitor's model trained on it: what an operator does before enabling the
    monitor (``docs/monitor.md``). Returns the model's path."""
    from cryptoros.demo.dataset import ATTEMPTS, RecordingMission
    from cryptoros.monitor.dataset import train

    note(f"calibration: a clean {CALIBRATION_S:g} s plain mission recorded to train the monitor's model")
    clean = dataclasses.replace(opts, attacks=(), modes=("plain",), seconds=CALIBRATION_S, coverage_target=1.01,
                                compromise=None, isolate=False)
    bag = workdir / "clean.bag"
    for attempt in range(1, ATTEMPTS + 1):
        workdir.mkdir(parents=True, exist_ok=True)
        mission = RecordingMission(clean, "plain", workdir, children, lambda _e: None, bag=bag)
        result = mission.run()
        try:
            model = train([bag])
            break
        except CryptorosError as exc:  # no bag, or nothing in it: never a model from nothing
            recorder = mission.dir / "recorder.log"
            why = (f"{exc} (the mission ran {result.get('wall_s', 0):.1f} s, "
                   f"{result.get('end_reason') or 'no end reason'}; recorder: "
                   f"{' | '.join(recorder.read_text().splitlines()[-3:]) if recorder.exists() else 'no log'}"
                   f"{'; ' + repr(result['exit_log']) if result.get('exit_log') else ''})")
            if attempt == ATTEMPTS:
                raise DemoError(f"calibration failed {ATTEMPTS} times: {why}") from None
            note(f"calibration: {why}; recording it again")
            shutil.rmtree(workdir, ignore_errors=True)
    path = workdir / "monitor-model.json"
    model.save(path)
    note(f"calibration: model trained on {sum(model.trained_on.values())} clean messages ({path})")
    return str(path)


def free_after(ports: list[tuple[str, int]]) -> list[tuple[str, int]]:
    busy = []
    for host, port in ports:
        with socket.socket() as s:
            s.settimeout(0.3)
            if s.connect_ex((host, port)) == 0:
                busy.append((host, port))
    return busy


__all__ = ["free_after", "run_demo"]
