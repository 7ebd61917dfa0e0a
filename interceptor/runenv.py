"""``cryptoros env`` and ``cryptoros run``: a node's environment for one interceptor.

The secure deployment is the easy one: nodes behind an interceptor must reach its local
master and listen on loopback only (``ROS_IP=127.0.0.1``, ``ROS_HOSTNAME`` unset), and a
robot's ROS 2 nodes must stay on its private DDS domain (its ``domain_id``, discovery on
localhost, the Fast DDS profile that binds 127.0.0.1 and shared memory only, no static
peers). ``cryptoros env --config FILE`` prints those as shell lines (``eval "$(cryptoros
env --config FILE)"``); ``cryptoros run --config FILE -- CMD ARGS...`` execs a node,
roslaunch, rosmaster or a stock tool with them (the exit status is CMD's).

For a master configuration (the master role alone) ``ROS_MASTER_URI`` is its
``[master] upstream``: ``cryptoros run --config master.toml -- rosmaster --core -p PORT``
starts rosmaster on loopback. Only what nodes need is read from the file (roles,
``[listen] local_master``, ``[master] upstream``, ``[ros2] domain_id``): a node's user
needs no access to the interceptor's keys.
"""

from __future__ import annotations

import errno
import os
import shlex
import shutil
import sys
from pathlib import Path

import click

from cryptoros.errors import ConfigError
from cryptoros.ros1.uri import UriError, host_port
from cryptoros.exposure import is_loopback_host
from interceptor.config import ROLES, Endpoint, check_key_names, read_toml

#: the directory of the refusal hook (its ``sitecustomize.py``): first on the
#: ``PYTHONPATH`` of every ROS 1 node and tool started through ``cryptoros run``/``env``
TOOL_HOOK = Path(__file__).resolve().parent / "toolhook"


def node_environment(path: str | os.PathLike[str]) -> tuple[dict[str, str], tuple[str, ...]]:
    """(variables to set, variables to unset) for a node of the interceptor configured
    in ``path``; ConfigError (one line) for a file that does not say where nodes go."""
    path = Path(path)
    raw = read_toml(path)
    try:  # CLI audit: a typo ("managre") was taken silently here, refused by the interceptor
        check_key_names(raw)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    roles = raw.get("roles", ["node"])
    if not isinstance(roles, list) or not roles or any(r not in ROLES for r in roles):
        raise ConfigError(f"{path}: roles must be a non-empty list of {', '.join(ROLES)}, got {roles!r}")
    listen, master, ros2 = (raw.get(k, {}) for k in ("listen", "master", "ros2"))
    if not all(isinstance(t, dict) for t in (listen, master, ros2)):
        raise ConfigError(f"{path}: [listen], [master] and [ros2] must be tables")
    env: dict[str, str] = {}
    unset: list[str] = []
    if "node" in roles:
        if "local_master" not in listen:
            raise ConfigError(f"{path}: the node role needs [listen] local_master (the ROS_MASTER_URI of local nodes)")
        local = Endpoint.parse(listen["local_master"], f"{path}: [listen] local_master")
        env["ROS_MASTER_URI"] = f"http://{local.host}:{local.port}/"
    elif "master" in roles:
        upstream = master.get("upstream")
        try:
            host, _ = host_port(upstream, ("http",))
        except UriError:
            raise ConfigError(f"{path}: the master role needs [master] upstream = http://host:port, "
                              f"got {upstream!r}") from None
        if not is_loopback_host(host):
            raise ConfigError(f"{path}: [master] upstream {upstream} is not on loopback: rosmaster and its nodes "
                              "belong on this host's loopback")
        env["ROS_MASTER_URI"] = upstream
    if env:
        env["ROS_IP"] = "127.0.0.1"
        unset.append("ROS_HOSTNAME")
        env["PYTHONPATH"] = str(TOOL_HOOK)  # prepended to the caller's (python_path)
    if "ros2" in roles:
        from cryptoros.ros2.profile import LOCALHOST_PROFILE, PROFILE_ENV

        domain = ros2.get("domain_id")
        if not isinstance(domain, int) or isinstance(domain, bool) or not 0 <= domain <= 232:
            raise ConfigError(f"{path}: the ros2 role needs [ros2] domain_id, an integer in 0..232, got {domain!r}")
        # what the interceptor's own DDS bridge runs with (interceptor/ros2.py)
        env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   RMW_IMPLEMENTATION="rmw_fastrtps_cpp", **{PROFILE_ENV: str(LOCALHOST_PROFILE)})
        unset += ["ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS"]
    return env, tuple(unset)


def python_path(hook: str, existing: str | None) -> str:
    """``PYTHONPATH`` with the refusal hook first and the caller's entries after it."""
    return hook if not existing else f"{hook}{os.pathsep}{existing}"


def shell_lines(env: dict[str, str], unset: tuple[str, ...]) -> list[str]:
    """POSIX shell lines that set ``env`` (``PYTHONPATH`` prepended to the shell's own)
    and unset ``unset``."""
    lines = []
    for name, value in env.items():
        if name == "PYTHONPATH":
            lines.append(f'export PYTHONPATH={shlex.quote(value)}"${{PYTHONPATH:+:$PYTHONPATH}}"')
        else:
            lines.append(f"export {name}={shlex.quote(value)}")
    return lines + [f"unset {n}" for n in unset]


def _environment_or_exit(config_path: str, prog: str) -> tuple[dict[str, str], tuple[str, ...]]:
    try:
        return node_environment(config_path)
    except ConfigError as exc:
        click.echo(f"{prog}: error: {exc}", err=True)
        raise SystemExit(2) from None


@click.command()
@click.option("--config", "config_path", required=True, help="The interceptor's configuration file.")
def env(config_path: str) -> None:
    """Print the shell exports a node's shell needs for this interceptor:
    eval "$(cryptoros env --config FILE)"."""
    variables, unset = _environment_or_exit(config_path, "cryptoros env")
    click.echo(f"# nodes behind the interceptor of {config_path}: loopback only")
    click.echo("\n".join(shell_lines(variables, unset)))


@click.command(context_settings={"ignore_unknown_options": True, "allow_interspersed_args": False})
@click.option("--config", "config_path", required=True, help="The interceptor's configuration file.")
@click.argument("command", nargs=-1, required=True, type=click.UNPROCESSED)
def run(config_path: str, command: tuple[str, ...]) -> None:
    """Run CMD (a node, roslaunch, rosmaster, a stock tool) with this interceptor's node
    environment: cryptoros run --config FILE -- CMD ARGS..."""
    variables, unset = _environment_or_exit(config_path, "cryptoros run")
    environ = {k: v for k, v in os.environ.items() if k not in unset}
    if "PYTHONPATH" in variables:
        variables = {**variables, "PYTHONPATH": python_path(variables["PYTHONPATH"], os.environ.get("PYTHONPATH"))}
    environ.update(variables)
    # The command is found on the caller's PATH; what it starts is not given this
    # interpreter's venv: Debian's ROS tools and catkin's Python nodes start with
    # "#!/usr/bin/env python3", and with the venv's bin first on PATH (an activated
    # venv) roslaunch's nodes ran the venv's Python and died without rospy.
    program = shutil.which(command[0], path=environ.get("PATH"))
    if sys.prefix != sys.base_prefix:
        venv_bin = os.path.join(sys.prefix, "bin")
        environ["PATH"] = os.pathsep.join(d for d in environ.get("PATH", "").split(os.pathsep)
                                          if d and os.path.realpath(d) != os.path.realpath(venv_bin))
        if environ.get("VIRTUAL_ENV") and os.path.realpath(environ["VIRTUAL_ENV"]) == os.path.realpath(sys.prefix):
            del environ["VIRTUAL_ENV"]
    sys.stdout.flush()
    try:
        if program is None:
            raise FileNotFoundError(errno.ENOENT, "No such file or directory")
        os.execve(program, list(command), environ)
    except OSError as exc:
        click.echo(f"cryptoros run: error: cannot run {command[0]}: {exc.strerror or exc}", err=True)
        raise SystemExit(127 if isinstance(exc, FileNotFoundError) else 126) from None


__all__ = ["TOOL_HOOK", "env", "node_environment", "python_path", "run", "shell_lines"]
