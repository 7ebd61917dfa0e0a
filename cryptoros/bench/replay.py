"""``cryptoros bench cipher-replay``: seed 002's pipeline as the paper ran it.

A rosbag of the paper's two sensors (:mod:`cryptoros.bench.replay_bag`: LaserScan at
10 Hz, a 640x480 camera at 30 fps of the paper's mean size) is replayed with
``rosbag play`` through an encrypting and a decrypting rospy node per sensor
(:mod:`cryptoros.bench.replay_nodes.crypto_node`, Debian's python3 and pycryptodome),
per cipher (plain: the same nodes copying; 3DES, AES, Blowfish in CBC as the paper; AES-GCM
and ChaCha20-Poly1305), per computer (this machine whole, and the calibrated Atom D525
stand-in of :mod:`cryptoros.bench.standin`, which holds the nodes and ``rosbag play`` as
the paper's CU held them), repeated. Measured per run, over the steady part of the
replay (the first seconds and the last half second left out):

* messages delivered (decrypted) per second per sensor, and dropped (published by the
  bag and never decrypted), as the paper's ROS statistics counted them;
* the CPU % of the encrypting and the decrypting node apart (their own CPU time);
* bytes on the wire per topic (rospy's transport counters of the subscriber: the plain
  topic as the encrypting node reads it, the ciphertext topic as the decrypting node
  reads it);
* the time each node spends in its stages (serialize, cipher, publish; cipher,
  deserialize) per message, which says where a node's time goes.

The 1-minute load average is recorded beside every run (the machine is shared).
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import click

from cryptoros.bench.replay_spec import CIPHERS, MACHINES, SENSORS
from cryptoros.outputs import write_output

SYS_PY = "/usr/bin/python3"
NODE = Path(__file__).parent / "replay_nodes" / "crypto_node.py"


def _progress(started: float):
    def say(message: str) -> None:
        click.echo(f"[{time.monotonic() - started:7.1f} s] {message}", err=True)
    return say


def _interp(samples: list[list[float]], t: float, col: int) -> float:
    """The sampled counter ``col`` at wall time ``t`` (linear between samples)."""
    if not samples:
        return 0.0
    if t <= samples[0][0]:
        return samples[0][col]
    for a, b in zip(samples, samples[1:]):
        if a[0] <= t <= b[0]:
            if b[0] == a[0]:
                return b[col]
            return a[col] + (b[col] - a[col]) * (t - a[0]) / (b[0] - a[0])
    return samples[-1][col]


def run_once(bag: Path, bag_info: dict, cipher: str, machine: str, workdir: Path, env: dict[str, str],
             ratios: dict[str, float], say) -> dict:
    """One replay of the bag through the four nodes; figures over the steady window."""
    from cryptoros.bench.standin import StandIn
    from cryptoros.lab.processes import stop

    stand = None
    if machine == "atom":
        stand = StandIn("Atom D525", 2, ratios["atom"])
    elif machine == "i7":
        stand = StandIn("i7-3612QM", 4, ratios["i7"])
    no_aesni = "1" if machine == "atom" else "0"
    procs: dict[tuple[str, str], subprocess.Popen] = {}
    stats_files: dict[tuple[str, str], Path] = {}
    play = None
    load_before = os.getloadavg()[0]
    try:
        for role in ("dec", "enc"):  # the decrypting node first: the encrypting one waits for it
            for sensor in SENSORS:
                stats_files[(role, sensor)] = workdir / f"{role}-{sensor}-{cipher}-{machine}.json"
                stats_files[(role, sensor)].unlink(missing_ok=True)
                procs[(role, sensor)] = subprocess.Popen(
                    [SYS_PY, str(NODE), role, sensor, cipher, str(stats_files[(role, sensor)]), no_aesni,
                     "raw" if bag_info["image"]["type"] == "sensor_msgs/Image" else "compressed"],
                    env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        for key, proc in procs.items():
            assert proc.stdout is not None
            line = proc.stdout.readline()  # bounded by the node's own 60 s wait for its peer
            if line.strip() != "READY":
                raise click.ClickException(f"the {key[0]} node of {key[1]} ({cipher}) did not get ready: {line!r}")
            if stand is not None:
                stand.attach(proc.pid)
        play = subprocess.Popen(["rosbag", "play", "-q", "--wait-for-subscribers", str(bag)], env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if stand is not None:
            stand.attach(play.pid)
        try:
            _, err = play.communicate(timeout=bag_info["seconds"] * 4 + 60)
        except subprocess.TimeoutExpired:
            raise click.ClickException(f"rosbag play did not finish ({cipher}, {machine})") from None
        play_end = time.time()
        if play.returncode != 0:
            raise click.ClickException(f"rosbag play failed ({cipher}, {machine}): {err.strip()[-300:]}")
        time.sleep(0.5)  # what is in flight arrives (after the window: not counted)
    finally:
        for proc in procs.values():
            stop(proc, timeout=10)
        if play is not None:
            stop(play)
        if stand is not None:
            stand.close()
    stats = {}
    for key, path in stats_files.items():
        if not path.exists():
            raise click.ClickException(f"the {key[0]} node of {key[1]} ({cipher}, {machine}) wrote no statistics")
        stats[key] = json.loads(path.read_text())
    firsts = [stats[("enc", s)]["done_at"][0] for s in SENSORS if stats[("enc", s)]["done_at"]]
    if not firsts:
        raise click.ClickException(f"no message reached the encrypting nodes ({cipher}, {machine})")
    start = min(firsts)
    warm = min(3.0, 0.2 * bag_info["seconds"])
    t0, t1 = start + warm, play_end - 0.5
    span = t1 - t0
    if span <= 0.5:
        raise click.ClickException(f"the replay's steady window is {span:.2f} s: a longer bag is needed")
    out: dict = {"cipher": cipher, "machine": machine, "window_s": span, "loadavg_1min_before": load_before,
                 "loadavg_1min_after": os.getloadavg()[0], "play_s": play_end - start}
    for sensor in SENSORS:
        rate = bag_info[sensor]["rate_hz"]
        enc, dec = stats[("enc", sensor)], stats[("dec", sensor)]
        published = rate * span
        delivered = sum(1 for t in dec["done_at"] if t0 <= t <= t1)
        encrypted = sum(1 for t in enc["done_at"] if t0 <= t <= t1)
        row = {"published_per_s": rate, "delivered_per_s": delivered / span, "encrypted_per_s": encrypted / span,
               "dropped_per_s": max(0.0, published - delivered) / span,
               "delivered_total": len(dec["done_at"]), "published_total": bag_info[sensor]["messages"],
               "decrypt_errors": dec["errors"]}
        for role, st in (("enc", enc), ("dec", dec)):
            cpu = _interp(st["samples"], t1, 1) - _interp(st["samples"], t0, 1)
            row[f"{role}_cpu_pct"] = 100 * cpu / span
            n = max(1, len(st["done_at"]))
            row[f"{role}_stage_us"] = {k: v / n * 1e6 for k, v in st["stages"].items() if v}
            row[f"{role}_cpu_us_per_msg"] = 1e6 * cpu / max(1, encrypted if role == "enc" else delivered)
        row["plain_wire_bytes_per_s"] = (_interp(enc["samples"], t1, 2) - _interp(enc["samples"], t0, 2)) / span
        row["cipher_wire_bytes_per_s"] = (_interp(dec["samples"], t1, 2) - _interp(dec["samples"], t0, 2)) / span
        out[sensor] = row
    say(f"  {machine:5s} {cipher:9s} laser {out['laser']['delivered_per_s']:5.1f}/10  image "
        f"{out['image']['delivered_per_s']:5.1f}/30  CPU enc/dec image {out['image']['enc_cpu_pct']:5.1f}/"
        f"{out['image']['dec_cpu_pct']:5.1f} %  load {load_before:.1f}")
    return out


def _env(master: str, home: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("ROS_")}
    env.pop("PYTHONPATH", None)
    env.update(ROS_MASTER_URI=master, ROS_IP="127.0.0.1", ROS_HOME=home, PYTHONUNBUFFERED="1")
    return env


def summarize(runs: list[dict]) -> dict:
    """machine -> cipher -> figure -> {mean, sd, min, max, values} over the repetitions."""
    out: dict = {}
    for r in runs:
        flat = {"window_s": r["window_s"], "loadavg": r["loadavg_1min_before"]}
        for sensor in SENSORS:
            for k, v in r[sensor].items():
                if isinstance(v, (int, float)):
                    flat[f"{sensor}.{k}"] = v
                elif isinstance(v, dict):
                    for sk, sv in v.items():
                        flat[f"{sensor}.{k}.{sk}"] = sv
        slot = out.setdefault(r["machine"], {}).setdefault(r["cipher"], {})
        for k, v in flat.items():
            slot.setdefault(k, []).append(v)
    for machine in out.values():
        for cipher, figs in machine.items():
            machine[cipher] = {k: {"mean": statistics.fmean(v), "sd": statistics.stdev(v) if len(v) > 1 else 0.0,
                                   "min": min(v), "max": max(v), "values": v} for k, v in figs.items()}
    return out


@click.command("cipher-replay")
@click.option("--quick", is_flag=True, help="A 6 s bag, one repetition, plain and AES only on both computers (the test).")
@click.option("--seconds", type=click.FloatRange(4, 3600), default=20.0, show_default=True, help="Length of the bag.")
@click.option("--reps", type=click.IntRange(1, 20), default=3, show_default=True, help="Repetitions (the paper: 3).")
@click.option("--ciphers", "cipher_list", default=",".join(CIPHERS), show_default=True, help="Comma-separated.")
@click.option("--machines", "machine_list", default="full,atom", show_default=True,
              help="full (this machine), atom (Atom D525 stand-in), i7 (i7-3612QM stand-in).")
@click.option("--laser-ranges", type=click.Choice(["683", "1024"]), default="683", show_default=True,
              help="683: the URG-04LX's points (2,789 B); 1024: a layout of the paper's 4,152 B.")
@click.option("--image", "image_kind", type=click.Choice(["compressed", "raw"]), default="compressed", show_default=True,
              help="compressed: the paper's mean size (79,737 B); raw: 640x480 rgb8 (921,654 B), a hypothesis test.")
@click.option("--atom-ratio", type=click.FloatRange(0.01, 1.0), default=None,
              help="An Atom core over one vCPU here (default: from published single-thread ratings).")
@click.option("--libs", "libs_python", default=None, metavar="PYTHON",
              help="Also time the paper's ciphers per image under PYTHON with PyCrypto (Crypto) and pycryptodome "
                   "(Cryptodome) importable, unthrottled and in the Atom stand-in (why drop rates differ).")
@click.option("--check/--no-check", "do_check", default=True, help="Time a reference workload in the stand-in first.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write every run and figure as JSON.")
@click.option("--plots", "plots_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Also draw replay-delivered, -cpu, -bytes and -fig9 .png into this directory.")
@click.option("--markdown", is_flag=True, help="Print the tables as Markdown.")
@click.option("--report", "report_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="Measure nothing: print (and --plots) an earlier run's --json.")
def cipher_replay(quick: bool, seconds: float, reps: int, cipher_list: str, machine_list: str, laser_ranges: str, image_kind: str,
                  atom_ratio: float | None, libs_python: str | None, do_check: bool, json_path: Path | None, plots_dir: Path | None,
                  markdown: bool, report_path: Path | None) -> None:
    """Seed 002's rosbag replay through encrypting and decrypting rospy nodes, per cipher and computer."""
    from cryptoros.bench import replay_report as rr
    from cryptoros.bench.replay_bag import write_bag
    from cryptoros.bench.standin import SINGLE_THREAD, StandIn, check, ratio
    from cryptoros.errors import ConfigError
    from cryptoros.lab.processes import free_port, stop, wait_port

    if report_path is not None:
        report = json.loads(report_path.read_text())
        report["derived"] = rr.derive(report)
    else:
        started = time.monotonic()
        say = _progress(started)
        if quick:
            seconds, reps, cipher_list = 6.0, 1, "plain,aes"
        ciphers = [c.strip() for c in cipher_list.split(",") if c.strip()]
        machines = [m.strip() for m in machine_list.split(",") if m.strip()]
        bad = [c for c in ciphers if c not in CIPHERS] + [m for m in machines if m not in MACHINES]
        if bad:
            raise click.BadParameter(f"unknown: {', '.join(bad)}")
        if not Path(SYS_PY).exists() or not shutil.which("rosbag") or not shutil.which("rosmaster"):
            raise click.ClickException("needs Debian's ROS 1 (rosbag, rosmaster, python3-rospy) and python3-pycryptodome: "
                                       "scripts/install-system-parts")
        ratios = {"atom": atom_ratio or ratio("Atom D525"), "i7": ratio("i7-3612QM")}
        workdir = Path(tempfile.mkdtemp(prefix="cryptoros-cipher-replay-"))
        report = {"config": {"seconds": seconds, "reps": reps, "ciphers": ciphers, "machines": machines,
                             "laser_ranges": int(laser_ranges), "image": image_kind, "ratios": ratios, "single_thread": SINGLE_THREAD,
                             "cpus": os.cpu_count(), "quick": quick}}
        port = free_port()
        env = _env(f"http://127.0.0.1:{port}/", str(workdir / "ros_home"))
        master = None
        try:
            say(f"writing a {seconds:g} s bag (LaserScan {laser_ranges} ranges at 10 Hz, camera at 30 fps)")
            bag = workdir / "sensors.bag"
            info = write_bag(bag, seconds, laser_ranges=int(laser_ranges), image=image_kind)
            info["seconds"] = seconds
            report["bag"] = info
            say(f"  laser {info['laser']['bytes_mean']:,.0f} B x {info['laser']['messages']}, image "
                f"{info['image']['bytes_mean']:,.1f} B (SD {info['image']['bytes_sd']:,.1f}) x {info['image']['messages']}")
            if do_check and any(m in ("atom", "i7") for m in machines):
                for m in machines:
                    if m in ("atom", "i7"):
                        with StandIn("Atom D525" if m == "atom" else "i7-3612QM", 2 if m == "atom" else 4, ratios[m]) as s:
                            say(f"checking the {m} stand-in with a reference workload: {s.describe()}")
                            report.setdefault("check", {})[m] = c = check(s, 1.0 if quick else 3.0)
                            say(f"  effective {c['effective_ratio']:.3f} of a vCPU (intended {c['intended_ratio']:.3f}), "
                                f"load {c['loadavg_1min']:.1f}")
            if libs_python:
                from cryptoros.bench.replay_libs import compare

                with StandIn("Atom D525", 2, ratios["atom"]) as s:
                    say(f"timing the ciphers' libraries under {libs_python}, unthrottled and in the Atom stand-in")
                    report["libs"] = {"rows": compare(libs_python, s, 0.2 if quick else 0.5),
                                      "loadavg_1min": os.getloadavg()[0]}
            master = subprocess.Popen(["rosmaster", "--core", "-p", str(port)], env=env, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL)
            wait_port("127.0.0.1", port, 30, master, "rosmaster")
            runs = []
            for rep in range(reps):
                for machine in machines:
                    say(f"repetition {rep + 1}/{reps}, {MACHINES[machine]}")
                    for cipher in ciphers:
                        r = run_once(bag, info, cipher, machine, workdir, env, ratios, say)
                        r["rep"] = rep
                        runs.append(r)
            report["runs"] = runs
            report["summary"] = summarize(runs)
            report["elapsed_s"] = time.monotonic() - started
        except ConfigError as exc:
            raise click.ClickException(str(exc)) from None
        finally:
            stop(master)
            shutil.rmtree(workdir, ignore_errors=True)
        report["derived"] = rr.derive(report)
        if json_path:
            write_output(json_path, json.dumps(report, indent=1, ensure_ascii=False))
    if plots_dir:
        for p in rr.plots(report, plots_dir):
            click.echo(f"wrote {p}", err=True)
    rr.render(report, markdown)


__all__ = ["cipher_replay", "run_once", "summarize"]

if __name__ == "__main__":  # pragma: no cover
    cipher_replay(sys.argv[1:])
