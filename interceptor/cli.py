"""``cryptoros-interceptor --config FILE``: run one host's interceptor.

One instance per configuration: the lock in ``state_dir`` (interceptor/statefile.py) is
taken before any state is read or written; a second start exits 1 naming the running
pid. The master role refuses to start while its rosmaster answers other hosts
(interceptor/exposure.py), exit status 1 and one line saying how to fix it.

SIGHUP reloads certificates, CRL, policy and settings without dropping open streams
(a failed reload, or a file changing a key that needs a restart, keeps the old state);
SIGTERM and SIGINT stop accepting, cut the streams with nothing in flight, give calls
under way a grace period and exit 0. Configuration mistakes are one line on stderr and
exit status 2.
"""

from __future__ import annotations

import asyncio
import dataclasses
import gc
import logging
import signal
import sys
import time
from pathlib import Path

import click

from cryptoros import logfmt
from cryptoros.errors import ConfigError, CryptorosError
from cryptoros.fdlimit import raise_descriptor_limit
from cryptoros.tls import PeerCertificateCheck, checking_server, client_context, server_context
from interceptor.config import load

log = logging.getLogger("cryptoros.interceptor")


def _fail(message: str, code: int = 2) -> None:
    click.echo(f"cryptoros-interceptor: error: {message}", err=True)
    sys.exit(code)


def build_interceptor(cfg):
    """The gateway composed with the roles ``cfg.roles`` names: ROS 1 (``node``,
    ``master``) and ``ros2`` (imported only when named: rclpy runs in a child)."""
    from interceptor.gateway import Gateway

    gateway = Gateway(cfg)
    if "node" in cfg.roles or "master" in cfg.roles:
        from interceptor.ros1 import Ros1Role

        gateway.add_role(Ros1Role(gateway))
    if "ros2" in cfg.roles:
        from interceptor.ros2 import Ros2Role

        gateway.add_role(Ros2Role(gateway))
    return gateway


def deployment_problems(cfg) -> tuple[list[str], list[str]]:
    """(refusals, warnings) of the deployment checks that need no network beyond this
    host: this host's loopback must answer this host only (``route_localnet``: every
    role trusts what reaches it there), and the master role's rosmaster must answer on
    loopback only (warned, not refused, with ``allow_exposed_master``); the warnings of
    :func:`setting_warnings` too. Both the start and ``--check`` say them."""
    from cryptoros.exposure import ExposureError
    from interceptor.exposure import PortExposure, master_problem

    warnings = setting_warnings(cfg)
    domain = ros2_domain_problem(cfg)
    if domain is not None:
        if cfg.ros2.require_private_domain:
            return [domain], warnings
        warnings.append(domain)
    exposure = PortExposure()
    try:
        loopback = exposure.loopback_problem()
    except ExposureError as exc:
        loopback = f"cannot tell whether it does: {exc}"
    if loopback is not None:
        return [f"this host's loopback answers other hosts: {loopback}"], warnings
    if "master" not in cfg.roles or not cfg.master.upstream:
        return [], warnings
    problem = master_problem(cfg.master.upstream, exposure, cfg.source)
    if problem is None:
        return [], warnings
    if cfg.allow_exposed_master:
        return [], [f"allow_exposed_master = true, serving anyway: {problem}", *warnings]
    return [problem], warnings


def ros2_domain_problem(cfg) -> str | None:
    """Why the ROS 2 role's domain cannot be kept private on this host, or None: its DDS
    ports overlap the kernel's ephemeral ports, so nodes' own sending sockets would now
    and then be taken for participants reachable from the network and their topics not
    carried, at random (refused with ``require_private_domain``, else warned)."""
    if "ros2" not in cfg.roles or cfg.ros2 is None:
        return None
    from cryptoros.ros2.exposure import domain_ports, ephemeral_overlap, highest_private_domain

    overlap = ephemeral_overlap(cfg.ros2.domain_id)
    if overlap is None:
        return None
    ports = domain_ports(cfg.ros2.domain_id)
    return (f"[ros2] domain_id {cfg.ros2.domain_id}: its DDS ports {ports.start}-{ports.stop - 1} overlap this host's "
            f"ephemeral ports ({overlap.start}-{overlap.stop - 1} of them; net.ipv4.ip_local_port_range), where "
            "nodes' own sending sockets land now and then and are taken for participants other hosts reach (their "
            f"topics not carried): use a domain_id from 0 to {highest_private_domain()}, or move the ephemeral range "
            "above the domain's ports")


def setting_warnings(cfg) -> list[str]:
    """What the configuration allows but weakens, one line each: no CRL, a secret file
    other users may read, a public listener on every address."""
    from cryptoros.files import open_to_others
    from cryptoros.pemfiles import cert_der
    from interceptor.streams import cert_hosts

    lines = []
    if cfg.tls.crl_file is None:
        # PeerCertificateCheck then has only the feed's serials (revoked_serials), which
        # the authorization server lists only when it runs with --crl
        lines.append("[tls] has no crl: a certificate revoked at the CA is refused here only once the authorization "
                     "server's revocation feed lists it (it does when that server runs with --crl); set [tls] crl "
                     "to the fleet's CRL file")
    lines += open_to_others(cfg.tls.secret_files())
    if cfg.public.host in ("0.0.0.0", "::"):
        try:
            hosts = ", ".join(sorted(cert_hosts(cert_der(cfg.tls.cert_file)))) or "no name"
        except CryptorosError:
            hosts = "no name"  # the TLS context says what is wrong with the file
        lines.append(f"public {cfg.public} listens on every address; peers reach it on one of {hosts} "
                     "(the certificate's IP/DNS names)")
    return lines


def quiet_closed_transport(loop: asyncio.AbstractEventLoop, context: dict) -> None:
    """The event loop's handler of errors nothing awaited. A write an SSL connection makes
    to a transport already closed (TLS had bytes to send when a peer or the interceptor
    closed it; seen when a failed start-up closed the authorization client's connections)
    is a debug line, not an ERROR with uvloop's traceback under the operator's one-line
    refusal; everything else goes to the default handler."""
    exc = context.get("exception")
    if isinstance(exc, RuntimeError) and "closed" in str(exc) and "protocol" in context:
        log.debug("%s: %s", context.get("message", "transport error"), exc)
        return
    loop.default_exception_handler(context)


async def _run(config_path: str, grace: float) -> None:
    from interceptor.statefile import lock_instance

    asyncio.get_running_loop().set_exception_handler(quiet_closed_transport)

    cfg = load(config_path)
    lock = lock_instance(cfg.state_dir, cfg.manager) if cfg.state_dir is not None else None
    refusals, warnings = deployment_problems(cfg)
    if refusals:
        raise ConfigError(refusals[0])
    problem = own_certificate_problem(cfg)
    if problem is not None:
        raise ConfigError(problem)
    for warning in warnings:
        log.warning("%s", warning)
    interceptor = build_interceptor(cfg)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()  # set before start-up ends (its ports are open): stopped right after
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    try:
        await interceptor.start()  # a listener that cannot bind: a ConfigError naming it and its address
    except (CryptorosError, OSError) as exc:
        await interceptor.stop(grace=0)
        if isinstance(exc, OSError):
            raise ConfigError(f"cannot start: {exc}") from None
        raise
    # What start-up made (modules, the message typestore, tables: some 60,000 objects) is
    # kept for good: moved out of the collector's reach, a full collection no longer scans
    # it. Measured: a full collection stopped the event loop (every stream of the host) for
    # 17 to 37 ms; after the freeze, the later ones took 0.1 to 6.8 ms. (A collection just
    # before the freeze found no garbage, so none is made: it cost 20 to 90 ms per start.)
    gc.freeze()

    async def reload() -> None:
        if interceptor.monitor is not None:  # an operator's release needs no valid configuration
            interceptor.monitor.apply_releases()
        try:
            await interceptor.reload(load(config_path))
            interceptor.metrics.reloads.labels("ok").inc()
        except (CryptorosError, OSError) as exc:
            interceptor.metrics.reloads.labels("failed").inc()
            log.error("reload failed, keeping the old state: %s", exc)

    loop.add_signal_handler(signal.SIGHUP, lambda: loop.create_task(reload()))
    print(f"cryptoros-interceptor: ready (manager {cfg.manager}, public {cfg.public})", flush=True)
    await stop.wait()
    log.info("stopping: calls under way get up to %.0f s to finish", grace)
    await interceptor.stop(grace=grace)
    if lock is not None:
        lock.close()


class _Unreachable(CryptorosError):
    """--check could not get a token: not a mistake in the file, exit 1."""

    exit_code = 1


def own_certificate_problem(cfg, now: float | None = None) -> str | None:
    """Why this interceptor's certificate is not valid now (every peer and the
    authorization server would refuse it), in one line, or None."""
    from cryptography import x509

    from cryptoros.errors import PKIError
    from cryptoros.pemfiles import cert_der, issued_by_any, load_certificates

    cert = x509.load_der_x509_certificate(cert_der(cfg.tls.cert_file))
    now = time.time() if now is None else now
    if cert.not_valid_after_utc.timestamp() <= now:
        return (f"{cfg.tls.cert_file} expired on {cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC: every peer and the "
                "authorization server refuse it; renew it (cryptoros-certs renew)")
    if cert.not_valid_before_utc.timestamp() > now:
        return (f"{cfg.tls.cert_file} is not valid before {cert.not_valid_before_utc:%Y-%m-%d %H:%M} UTC "
                "(is this host's clock right?)")
    # every peer checks it against the same CA file (the fleet's; any certificate in it)
    try:
        if issued_by_any(cert, load_certificates(cfg.tls.ca_file)):
            return None
    except PKIError:
        return None  # the TLS context says what is wrong with the CA file
    return (f"{cfg.tls.cert_file} was not issued by the CA {cfg.tls.ca_file} (issuer: "
            f"{cert.issuer.rfc4514_string()}): every peer and the authorization server refuse it")


async def _preflight(cfg) -> list[str]:
    """What --check checks beyond the file: the certificate names the public address
    (peers accept endpoints only on their owner's IP SAN), and the authorization server
    issues this certificate a token for ``manager`` (the registry's binding), verified
    with its JWKS."""
    from cryptography import x509

    from cryptoros.tokens import verify_access_token
    from interceptor.authz_client import AuthzClient
    from cryptoros.pemfiles import cert_der
    from interceptor.streams import cert_hosts

    der = cert_der(cfg.tls.cert_file)
    problem = own_certificate_problem(cfg)
    if problem is not None:  # else the server only "closed the connection"
        raise ConfigError(problem)
    hosts = cert_hosts(der)
    lines = []
    if cfg.public.host not in hosts and cfg.public.host not in ("0.0.0.0", "::"):  # every address: a warning
        raise ConfigError(f"public address {cfg.public.host} is not in {cfg.tls.cert_file}'s IP/DNS names "
                          f"({', '.join(sorted(hosts)) or 'none'}): peers would refuse every endpoint of this host")
    # each replica on its own: the line names the one that answered, and one that does not is said
    ctx = checking_server(client_context(cfg.tls, check_hostname=True), PeerCertificateCheck(cfg.tls.crl_file).check)
    urls = cfg.authz.urls or (cfg.authz.url,)
    not_after = x509.load_der_x509_certificate(der).not_valid_after_utc
    down: list[str] = []
    for url in urls:
        client = AuthzClient(dataclasses.replace(cfg.authz, url=url, urls=(url,)), ctx)
        try:
            own = await client.fetch_token()
            keys = await client.fetch_jwks()
        except CryptorosError as exc:
            down.append(f"authorization server {url}: {getattr(exc, 'detail', exc)}")
            continue
        finally:
            await client.close()
        access = verify_access_token(own.token, keys=keys, issuer=cfg.authz.issuer, audience=cfg.authz.audience,
                                     peer_cert_der=der)
        if access.subject != cfg.manager:
            raise ConfigError(f"the registry binds {cfg.tls.cert_file} to manager {access.subject!r}, "
                              f"not {cfg.manager!r} (manager in the configuration)")
        lines.append(f"authorization server {url}: token for manager {access.subject}, "
                     f"{len(access.grants)} grants, valid {access.expires_at - access.issued_at} s; "
                     f"certificate valid until {not_after:%Y-%m-%d}")
    if len(down) == len(urls):
        raise _Unreachable("; ".join(down))
    lines += [f"warning: {line} (the other replicas answer)" for line in down]
    return lines


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--config", "config_path", help="TOML configuration file (see interceptor/config.py).")
@click.option("--check", is_flag=True,
              help="Validate the configuration and TLS material, that the rosmaster of the master role answers on "
                   "loopback only, that the certificate names the public address and that the authorization "
                   "server issues it a token for this manager, then exit.")
@click.option("--ros2-profile", "ros2_profile", type=click.Path(dir_okay=False, allow_dash=True),
              help="Write the Fast DDS profile that keeps a robot's ROS 2 nodes on loopback to this file "
                   "('-': standard output), then exit.")
@click.option("--grace", default=5.0, show_default=True, help="Seconds calls under way get to finish on SIGTERM (topic streams and idle connections are cut at once).")
@click.option(
    "--log-level", default="info", show_default=True, type=click.Choice(["debug", "info", "warning", "error"])
)
@click.option("--no-uvloop", is_flag=True, help="Use the standard asyncio event loop.")
def main(config_path: str | None, check: bool, ros2_profile: str | None, grace: float, log_level: str,
         no_uvloop: bool) -> None:
    """Run the cryptoros interceptor: a drop-in mutual-TLS/JWT proxy for unmodified ROS nodes."""
    if ros2_profile:
        from cryptoros.ros2.profile import LOCALHOST_PROFILE, PROFILE_ENV

        text = LOCALHOST_PROFILE.read_text(encoding="utf-8")
        if ros2_profile == "-":
            click.echo(text, nl=False)
        else:
            from cryptoros.outputs import writing

            try:
                with writing(ros2_profile) as target:  # its directories made (/etc/cryptoros/..., docs/ros2.md)
                    target.write_text(text, encoding="utf-8")
            except click.ClickException as exc:
                _fail(exc.message)
            click.echo(f"wrote {ros2_profile}: start every ROS 2 node of this robot with "
                       f"{PROFILE_ENV}={Path(ros2_profile).resolve()} ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST "
                       "and ROS_DOMAIN_ID of its [ros2] domain_id (cryptoros run / cryptoros env set all three)")
        return
    if not config_path:
        raise click.UsageError("--config is required")
    logfmt.configure(log_level, "%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        cfg = load(config_path)
        server_context(cfg.tls)
        client_context(cfg.tls)
    except CryptorosError as exc:
        _fail(str(exc))
    if check:
        refusals, warnings = deployment_problems(cfg)
        if refusals:
            _fail(refusals[0], code=1)
        try:
            lines = asyncio.run(_preflight(cfg))
        except CryptorosError as exc:
            _fail(str(exc), code=getattr(exc, "exit_code", 2))
        click.echo(f"configuration ok: manager {cfg.manager}, roles {', '.join(cfg.roles)}, public {cfg.public}")
        for line in lines:
            click.echo(line)
        for warning in warnings:
            click.echo(f"warning: {warning}", err=True)
        if "ros2" in cfg.roles:
            from cryptoros.ros2.profile import environment_problem

            problem = environment_problem()
            if problem:
                click.echo(f"warning: {problem}: ROS 2 nodes started from this environment answer discovery from "
                           "other hosts; write the profile with --ros2-profile FILE and export it", err=True)
            from cryptoros.ros2.exposure import ExposureScan

            for item in ExposureScan(cfg.ros2.domain_id).scan():
                click.echo(f"warning: a DDS participant on domain {cfg.ros2.domain_id} is reachable from the network: "
                           f"{item.describe()}; start it with the localhost profile (docs/ros2.md)", err=True)
        return
    raise_descriptor_limit()  # every relayed stream holds two descriptors, every relay listener one
    runner = asyncio.run
    if not no_uvloop:
        try:
            import uvloop

            runner = uvloop.run
        except ImportError:  # pragma: no cover - uvloop is a dependency
            pass
    try:
        runner(_run(config_path, grace))
    except CryptorosError as exc:
        _fail(str(exc), code=1)


if __name__ == "__main__":  # pragma: no cover
    main()
