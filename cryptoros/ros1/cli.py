"""``cryptoros master``: run the embedded ROS 1 master."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import signal

import click


@click.command()
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to bind: a loopback address unless --unsafe-expose.")
@click.option("--port", "-p", default=11311, show_default=True, type=click.IntRange(0, 65535), help="XML-RPC port.")
@click.option("--unsafe-expose", is_flag=True,
              help="Allow a non-loopback --host: every host that reaches it can register, read and set parameters "
                   "and shut the master down, past any interceptor.")
@click.option("-v", "--verbose", is_flag=True, help="Log registrations and callbacks.")
def master(host: str, port: int, unsafe_expose: bool, verbose: bool) -> None:
    """Run an embedded ROS 1 master (master and parameter-server APIs), on loopback only
    unless told otherwise: the master's interceptor fronts it there."""
    from cryptoros.exposure import is_loopback_host
    from cryptoros.ros1.master import Master
    from cryptoros.ros1.node import install_uvloop

    if not unsafe_expose and not is_loopback_host(host):
        click.echo(f"cryptoros master: error: --host {host or '(every address)'} is not a loopback address: other "
                   "hosts would reach the master past every interceptor; use 127.0.0.1 (the master's interceptor "
                   "fronts it there) or add --unsafe-expose", err=True)
        raise SystemExit(1)

    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(asctime)s %(name)s %(message)s")
    install_uvloop()

    async def main() -> None:
        m = Master(host, port)
        try:
            await m.start()
        except OSError as exc:  # a port in use, an address this host does not have: one line
            why = {errno.EADDRINUSE: "address already in use", errno.EADDRNOTAVAIL: "no such address on this host"}
            click.echo(f"cryptoros master: error: cannot listen on {host}:{port}: "
                       f"{why.get(exc.errno, exc.strerror or str(exc))}", err=True)
            raise SystemExit(1) from None
        click.echo(f"ROS_MASTER_URI={m.uri}", err=True)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError):
                loop.add_signal_handler(sig, stop.set)
        waiters = [asyncio.ensure_future(stop.wait()), asyncio.ensure_future(m.shutdown_requested.wait())]
        await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
        for w in waiters:
            w.cancel()
        await m.close()

    asyncio.run(main())

