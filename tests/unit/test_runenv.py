"""``cryptoros run`` (interceptor/runenv.py) as a subprocess: what the command it starts
is given."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

VENV_BIN = Path(sys.executable).parent


def test_run_finds_the_command_on_the_callers_path_but_gives_it_no_venv(tmp_path):
    """Day-2 audit: with the venv's bin first on PATH (an activated venv), roslaunch's
    nodes (Debian's tools and catkin's nodes start with ``#!/usr/bin/env python3``)
    ran the venv's Python and died without rospy."""
    config = tmp_path / "robot.toml"
    config.write_text('manager = "robot_a"\nroles = ["node"]\n[listen]\nlocal_master = "127.0.0.1:11311"\n')
    child = ("import json, os, sys; print(json.dumps({'prefix': sys.prefix, 'path': os.environ['PATH'], "
             "'venv': os.environ.get('VIRTUAL_ENV'), 'master': os.environ['ROS_MASTER_URI']}))")
    env = {**os.environ, "PATH": f"{VENV_BIN}{os.pathsep}/usr/bin{os.pathsep}/bin", "VIRTUAL_ENV": sys.prefix}
    r = subprocess.run([str(VENV_BIN / "cryptoros"), "run", "--config", str(config), "--", "python3", "-c", child],
                       capture_output=True, text=True, timeout=60, env=env)
    assert r.returncode == 0, r.stderr
    seen = json.loads(r.stdout)
    assert seen["master"] == "http://127.0.0.1:11311/"
    assert os.path.realpath(seen["prefix"]) != os.path.realpath(sys.prefix)  # the system's python3, not the venv's
    assert str(VENV_BIN) not in seen["path"].split(os.pathsep) and seen["venv"] is None
    # a command found only in the venv is still run (by its path), and one found nowhere is one line
    r = subprocess.run([str(VENV_BIN / "cryptoros"), "run", "--config", str(config), "--", "cryptoros-certs", "--help"],
                       capture_output=True, text=True, timeout=60, env=env)
    assert r.returncode == 0 and "Usage" in r.stdout, r.stderr
    r = subprocess.run([str(VENV_BIN / "cryptoros"), "run", "--config", str(config), "--", "no-such-tool-here"],
                       capture_output=True, text=True, timeout=60, env=env)
    assert r.returncode == 127 and r.stderr.strip() == \
        "cryptoros run: error: cannot run no-such-tool-here: No such file or directory", r.stderr
