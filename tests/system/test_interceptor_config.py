"""Interceptor configuration: valid files load; every mistake is one ConfigError line."""

from __future__ import annotations

import textwrap

import pytest

from cryptoros.errors import ConfigError
from interceptor.config import load


@pytest.fixture
def material(pki, tmp_path):
    issued = pki.issue("robot1", kind="interceptor", sans=("IP:127.0.0.2",))
    return {"ca": pki.ca_cert, "cert": issued.cert_path, "key": issued.key_path, "crl": pki.crl}


def write(tmp_path, text: str):
    path = tmp_path / "interceptor.toml"
    path.write_text(textwrap.dedent(text))
    return path


def good(material, **replace) -> str:
    text = f"""
        manager = "robot1"
        roles = ["node"]
        [tls]
        ca = "{material['ca']}"
        cert = "{material['cert']}"
        key = "{material['key']}"
        crl = "{material['crl']}"
        [authz]
        url = "https://127.0.0.1:8443"
        [listen]
        public = "127.0.0.2:11400"
        local_master = "127.0.0.1:11311"
        [master]
        interceptor = "127.0.0.4:11400"
        [limits]
        max_connections_per_peer = 8
        """
    for old, new in replace.items():
        text = text.replace(old, new)
    return text


def test_valid_file_loads_frozen(material, tmp_path):
    cfg = load(write(tmp_path, good(material)))
    assert cfg.manager == "robot1" and cfg.roles == ("node",)
    assert cfg.public.host == "127.0.0.2" and cfg.public.port == 11400
    assert cfg.master.interceptor.port == 11400
    assert cfg.limits.max_connections_per_peer == 8
    assert cfg.tls.crl_file == material["crl"]
    with pytest.raises(AttributeError):
        cfg.manager = "intruder"  # type: ignore[misc]


def test_a_peers_message_rate_is_limited_by_default_and_0_turns_the_limit_off(material, tmp_path):
    """Secure by default: with no line a peer is held to the default rate; ``0`` is no
    limit (what the throughput benches set); a number is that rate."""
    from interceptor.config import DEFAULT_MESSAGES_PER_SECOND

    assert load(write(tmp_path, good(material))).limits.max_messages_per_second == DEFAULT_MESSAGES_PER_SECOND
    assert DEFAULT_MESSAGES_PER_SECOND == 5000
    off = good(material, **{"max_connections_per_peer = 8": "max_messages_per_second = 0"})
    assert load(write(tmp_path, off)).limits.max_messages_per_second is None
    set_ = good(material, **{"max_connections_per_peer = 8": "max_messages_per_second = 250"})
    assert load(write(tmp_path, set_)).limits.max_messages_per_second == 250.0


def test_relative_paths_are_relative_to_the_file(material, tmp_path):
    text = good(material).replace(str(material["ca"]), "pki/ca.crt")
    cfg = load(write(tmp_path, text))
    assert cfg.tls.ca_file == tmp_path / "pki" / "ca.crt"


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        ({'roles = ["node"]': 'roles = ["node"]\ncolour = "red"'}, "unknown key 'colour' in top level"),
        ({'crl = "': 'cipher = "RC4"\ncrl = "'}, "unknown key 'cipher' in \\[tls\\]"),
        ({"max_connections_per_peer = 8": "max_conections_per_peer = 8"}, "unknown key 'max_conections_per_peer'"),
        ({"max_connections_per_peer = 8": "max_connections_per_peer = -1"}, "must be positive"),
        # operator audit: nan passed every "<= 0" check and each public connection then raised
        ({"max_connections_per_peer = 8": "preamble_timeout = nan"}, "preamble_timeout must be positive and finite"),
        ({"max_connections_per_peer = 8": "handshake_timeout = inf"}, "handshake_timeout must be positive and finite"),
        ({"max_connections_per_peer = 8": "stalled_stream_timeout = nan"}, "stalled_stream_timeout must be seconds"),
        ({"max_connections_per_peer = 8": 'max_connections_per_peer = "many"'}, "must be int"),
        ({'manager = "robot1"': ""}, "manager is required"),
        ({'roles = ["node"]': 'roles = ["robot"]'}, "roles must be"),
        ({"https://127.0.0.1:8443": "http://127.0.0.1:8443"}, "must be an https:// URL"),
        ({'public = "127.0.0.2:11400"': 'public = "127.0.0.2"'}, "expected host:port"),
        ({'local_master = "127.0.0.1:11311"': 'local_master = "10.1.2.3:11311"'}, "must be a loopback address"),
        ({'interceptor = "127.0.0.4:11400"': ""}, "needs \\[master\\] interceptor"),
        ({"manager = \"robot1\"": "manager = \"robot1\"\nroles2 = 1"}, "unknown key 'roles2'"),
        # deployment audit: a top-level flag written under a section said only "unknown key"
        ({"max_connections_per_peer = 8": "allow_exposed_nodes = []"},
         "unknown key 'allow_exposed_nodes' in \\[limits\\] \\(it belongs at the top level"),
        ({"max_connections_per_peer = 8": "tunnel_idle_timeout = 600"}, "tunnel_idle_timeout must be seconds"),
        ({"max_connections_per_peer = 8": "tunnel_idle_timeout = 0"}, "tunnel_idle_timeout must be seconds"),
        ({"max_connections_per_peer = 8": "dead_node_check = 0.5"}, "dead_node_check must be seconds"),
        ({"max_connections_per_peer = 8": "dead_node_check = true"}, "dead_node_check must be seconds"),
        ({"max_connections_per_peer = 8": "max_messages_per_second = -5"}, "max_messages_per_second must be messages"),
        ({"max_connections_per_peer = 8": "max_messages_per_second = true"}, "max_messages_per_second must be messages"),
        ({"max_connections_per_peer = 8": 'max_messages_per_second = "off"'}, "max_messages_per_second must be messages"),
    ],
)
def test_mistakes_are_one_line_config_errors(material, tmp_path, edit, message):
    with pytest.raises(ConfigError, match=message) as info:
        load(write(tmp_path, good(material, **edit)))
    assert "\n" not in str(info.value)


def test_a_state_dir_that_is_a_file_is_a_config_error(material, tmp_path):
    """Operator audit: ``state_dir = "robot.toml"`` passed ``--check``; the start then failed
    on the instance lock inside it."""
    config = write(tmp_path, good(material, **{'roles = ["node"]': 'roles = ["node"]\nstate_dir = "interceptor.toml"'}))
    with pytest.raises(ConfigError, match="state_dir .*interceptor.toml exists and is not a directory"):
        load(config)


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load(write(tmp_path, "manager = \n"))


def test_refuses_to_start_without_tls_material_or_token_source(material, tmp_path):
    no_tls = "\n".join(l for l in good(material).splitlines() if not l.strip().startswith(("ca", "cert", "key", "crl", "[tls]")))
    with pytest.raises(ConfigError, match="\\[tls\\] is required"):
        load(write(tmp_path, no_tls))
    with pytest.raises(ConfigError, match="\\[tls\\] key is required"):
        load(write(tmp_path, good(material, **{f'key = "{material["key"]}"': ""})))
    with pytest.raises(ConfigError, match="not found"):
        load(write(tmp_path, good(material, **{str(material["cert"]): "/nonexistent/robot1.crt"})))
    no_authz = good(material).replace("[authz]\n", "").replace('url = "https://127.0.0.1:8443"', "")
    with pytest.raises(ConfigError, match="\\[authz\\] is required"):
        load(write(tmp_path, no_authz))


def test_plaintext_upstream_off_loopback_needs_an_unsafe_setting(material, tmp_path):
    master = good(material, **{'roles = ["node"]': 'roles = ["master"]'}).replace(
        'interceptor = "127.0.0.4:11400"', 'upstream = "http://192.0.2.10:11311"'
    )
    with pytest.raises(ConfigError, match="unsafe_plaintext_upstream"):
        load(write(tmp_path, master))
    allowed = master.replace('manager = "robot1"', 'manager = "robot1"\nunsafe_plaintext_upstream = true')
    assert load(write(tmp_path, allowed)).unsafe_plaintext_upstream is True
    local = master.replace("192.0.2.10", "127.0.0.1")
    assert load(write(tmp_path, local)).master.upstream == "http://127.0.0.1:11311"


def test_passphrase_file_is_read(material, tmp_path, pki):
    encrypted = pki.pki.issue("robot2", passphrase=b"s3cret passphrase")
    (tmp_path / "pass").write_text("s3cret passphrase\n")
    text = good(material).replace(str(material["cert"]), str(encrypted.cert_path)).replace(
        f'key = "{material["key"]}"', f'key = "{encrypted.key_path}"\nkey_passphrase_file = "pass"'
    )
    assert load(write(tmp_path, text)).tls.key_passphrase == b"s3cret passphrase"


def test_check_names_the_certificate_and_manager_mismatches_and_an_unreachable_authz_server(tmp_path):
    """`--check` (day 2): the certificate must name the public address, the registry must
    bind it to the configured manager, and the authorization server must answer; each
    mistake is one line, and a good file prints the token it got."""
    from cryptoros.lab.network import free_port
    from tests.authz_support import authz, build_team, ok, running_daemon
    from tests.support import expired_certificate, run, script

    team = build_team(tmp_path)
    issued = team.pki.issue("robot_x", kind="interceptor", sans=("IP:127.0.0.2",))
    ok(authz("add-manager", "robot_x", "--fingerprint", issued.fingerprint_sha256, db=team.db))
    material = {"ca": team.pki.ca_cert, "cert": issued.cert_path, "key": issued.key_path, "crl": team.pki.crl}

    def check(url: str, **replace: str):
        path = tmp_path / "check.toml"
        path.write_text(textwrap.dedent(good(material, **{'"robot1"': '"robot_x"', "https://127.0.0.1:8443": url,
                                                          **replace})))
        return run([script("cryptoros-interceptor"), "--config", str(path), "--check"], timeout=60)

    with running_daemon(team.pki, team.db, tmp_path) as daemon:
        good_run = check(daemon.base)
        assert good_run.returncode == 0, good_run.stderr
        assert "token for manager robot_x" in good_run.stdout
        for replace, needle in (({"127.0.0.2:11400": "127.0.0.3:11400"}, "127.0.0.3 is not in"),
                                ({'manager = "robot_x"': 'manager = "robot_y"'}, "binds")):
            bad = check(daemon.base, **replace)
            assert bad.returncode == 2 and "Traceback" not in bad.stderr, bad.stderr
            assert len(bad.stderr.strip().splitlines()) == 1 and needle in bad.stderr, bad.stderr
        foreign = {"ca": team.pki.ca_cert, "cert": team.other_pki.pki.cert_path_for("alice"),
                   "key": team.other_pki.pki.key_path_for("alice"), "crl": team.pki.crl}
        path = tmp_path / "foreign.toml"
        path.write_text(textwrap.dedent(good(foreign, **{'"robot1"': '"alice"', "https://127.0.0.1:8443": daemon.base,
                                                         "127.0.0.2:11400": "0.0.0.0:11400"})))
        other_ca = run([script("cryptoros-interceptor"), "--config", str(path), "--check"], timeout=60)
        # CLI audit: this was "no authorization server answers (...ServerDisconnectedError)"
        assert other_ca.returncode == 2 and len(other_ca.stderr.strip().splitlines()) == 1, other_ca.stderr
        assert f"was not issued by the CA {team.pki.ca_cert}" in other_ca.stderr, other_ca.stderr
        # a certificate the registry binds to no manager (a renewal without set-cert) says what to do
        unbound = team.pki.issue("robot_x", kind="interceptor", sans=("IP:127.0.0.2",), force=True)
        assert unbound.fingerprint_sha256 != issued.fingerprint_sha256
        renewed = check(daemon.base)
        assert renewed.returncode == 1 and "invalid_client" in renewed.stderr, renewed.stderr
        assert "cryptoros-authz set-cert MANAGER --cert FILE" in renewed.stderr, renewed.stderr
        ok(authz("set-cert", "robot_x", "--fingerprint", unbound.fingerprint_sha256, db=team.db))
        # replicas, the first one down: each is checked, the line names the one that answered
        # (day-2 audit: the dead first replica was named as having issued the token)
        dead = f"https://127.0.0.1:{free_port()}"
        replicas = check(daemon.base, **{f'url = "{daemon.base}"': f'url = ["{dead}", "{daemon.base}"]'})
        assert replicas.returncode == 0, replicas.stderr
        assert f"authorization server {daemon.base}: token for manager robot_x" in replicas.stdout, replicas.stdout
        assert f"warning: authorization server {dead}:" in replicas.stdout, replicas.stdout
        assert f"authorization server {dead}: token" not in replicas.stdout
    down = check(f"https://127.0.0.1:{free_port()}")
    assert down.returncode == 1 and "nothing answers there" in down.stderr and "Traceback" not in down.stderr, \
        down.stderr
    # an expired certificate is named as such (it was "the authorization server closed the connection")
    material["cert"], material["key"] = expired_certificate(tmp_path, "robot_x", ip="127.0.0.2")
    expired = check(f"https://127.0.0.1:{free_port()}")
    assert expired.returncode == 2 and len(expired.stderr.strip().splitlines()) == 1, expired.stderr
    assert "expired on" in expired.stderr and "renew it" in expired.stderr, expired.stderr
    started = run([script("cryptoros-interceptor"), "--config", str(tmp_path / "check.toml")], timeout=60)
    assert started.returncode == 1 and len(started.stderr.strip().splitlines()) == 1, started.stderr
    assert "expired on" in started.stderr, started.stderr  # nor does it start


def test_weakening_settings_are_warned_alike_at_start_and_by_check(tmp_path):
    """No CRL, a TLS key and its passphrase file others may read, a public listener on
    every address: one warning line each, the same from --check and at start (here
    stopped by a squatter on the public port, after the warnings); a file with none of
    them says no warning."""
    import socket

    from cryptoros.lab.network import free_port
    from tests.authz_support import authz, build_team, ok, running_daemon
    from tests.support import run, script

    team = build_team(tmp_path)
    issued = team.pki.pki.issue("robot_x", kind="interceptor", sans=("IP:127.0.0.2",), passphrase=b"s3cret passphrase")
    ok(authz("add-manager", "robot_x", "--fingerprint", issued.fingerprint_sha256, db=team.db))
    passphrase = tmp_path / "robot_x.pass"
    passphrase.touch(mode=0o600)
    passphrase.write_text("s3cret passphrase\n")
    material = {"ca": team.pki.ca_cert, "cert": issued.cert_path, "key": issued.key_path, "crl": team.pki.crl}
    port = free_port()
    with running_daemon(team.pki, team.db, tmp_path) as daemon:
        text = good(material, **{'"robot1"': '"robot_x"', "https://127.0.0.1:8443": daemon.base,
                                 f'key = "{issued.key_path}"': f'key = "{issued.key_path}"\n'
                                                                f'        tls_key_passphrase_file = "{passphrase}"'})
        path = write(tmp_path, text)
        quiet = run([script("cryptoros-interceptor"), "--config", str(path), "--check"], timeout=60)
        assert quiet.returncode == 0 and "warning" not in quiet.stdout + quiet.stderr, quiet.stderr
        issued.key_path.chmod(0o644)
        passphrase.chmod(0o640)
        path = write(tmp_path, text.replace(f'crl = "{team.pki.crl}"\n', "").replace("127.0.0.2:11400",
                                                                                      f"0.0.0.0:{port}"))
        check = run([script("cryptoros-interceptor"), "--config", str(path), "--check"], timeout=60)
        assert check.returncode == 0 and "token for manager robot_x" in check.stdout, check.stderr
        with socket.socket() as squatter:
            squatter.bind(("0.0.0.0", port))
            squatter.listen(1)
            started = run([script("cryptoros-interceptor"), "--config", str(path)], timeout=60)
    assert started.returncode == 1 and f"cannot listen on 0.0.0.0:{port} (public)" in started.stderr, started.stderr
    key = issued.key_path
    for warning in (
            "[tls] has no crl: a certificate revoked at the CA is refused here only once the authorization server's "
            "revocation feed lists it (it does when that server runs with --crl)",
            f"the TLS key {key} has mode 0644, open to its group and other users on this host: chmod 600 {key}",
            f"the TLS key's passphrase file {passphrase} has mode 0640, open to its group on this host: "
            f"chmod 600 {passphrase}",
            f"public 0.0.0.0:{port} listens on every address; peers reach it on one of 127.0.0.2"):
        assert f"warning: {warning}" in check.stderr, check.stderr
        assert f"WARNING {warning}" in started.stderr, started.stderr


def test_authz_url_may_list_replicas(material, tmp_path):
    cfg = load(write(tmp_path, good(material, **{'url = "https://127.0.0.1:8443"':
                                                 'url = ["https://127.0.0.1:8443/", "https://127.0.0.9:8443"]'})))
    assert cfg.authz.url == "https://127.0.0.1:8443"
    assert cfg.authz.urls == ("https://127.0.0.1:8443", "https://127.0.0.9:8443")
    with pytest.raises(ConfigError, match="list of them"):
        load(write(tmp_path, good(material, **{'url = "https://127.0.0.1:8443"':
                                               'url = ["https://127.0.0.1:8443", "http://127.0.0.9:8443"]'})))


def test_a_monitor_whose_model_does_not_load_stops_the_start_with_one_line(material, tmp_path):
    """[monitor] (docs/monitor.md): the model file is read and checked at start-up."""
    from tests.support import run, script

    model = tmp_path / "model.json"
    for content, needle in (("{not json", "monitor model"), ('{"format": "other"}', "not a cryptoros-monitor-model"),
                            (None, "monitor model not found")):
        model.unlink(missing_ok=True)
        if content is not None:
            model.write_text(content)
        path = write(tmp_path, good(material) + f'\n        [monitor]\n        model = "{model}"\n')
        with pytest.raises(ConfigError, match=needle):
            load(path)
        cli = run([script("cryptoros-interceptor"), "--config", str(path), "--check"], timeout=60)
        assert cli.returncode == 2 and len(cli.stderr.strip().splitlines()) == 1 and needle in cli.stderr, cli.stderr
    path = write(tmp_path, good(material) + '\n        [monitor]\n        model = "m.json"\n        colour = 1\n')
    with pytest.raises(ConfigError, match="unknown key 'colour' in \\[monitor\\]"):
        load(path)


def test_every_key_of_the_file_is_applied_or_refused_by_a_reload():
    """SIGHUP (Gateway.reload) applies a key or refuses the reload naming it: every key
    the file may hold is decided in interceptor.config.RELOAD, none forgotten."""
    from interceptor.config import _SECTIONS, APPLY, RELOAD, RESTART

    sections = {name for name in _SECTIONS if name}
    keys = {key for key in _SECTIONS[""] if key not in sections}
    keys |= {f"[{section}] {key}" for section in sections for key in _SECTIONS[section]}
    keys.discard("[authz] urls")  # the list [authz] url gives, not a key of its own
    assert set(RELOAD) == keys | {"[monitor]"}  # [monitor] itself: added or removed
    assert {action for action, _value in RELOAD.values()} == {APPLY, RESTART}


def test_a_reload_is_refused_naming_each_key_that_needs_a_restart(material, tmp_path):
    from interceptor.config import check_reload, reload_refusals

    running = load(write(tmp_path, good(material)))
    limits = load(write(tmp_path, good(material, **{"max_connections_per_peer = 8": "max_connections_per_peer = 2\n"
                                                    "max_new_connections_per_second = 1.5"})))
    assert reload_refusals(running, limits) == []
    check_reload(running, limits)  # limits are applied
    moved = load(write(tmp_path, good(material, **{"https://127.0.0.1:8443": "https://127.0.0.9:8443",
                                                   "127.0.0.2:11400": "127.0.0.2:11401",
                                                   "max_connections_per_peer = 8": "max_connections_per_peer = 2"})))
    assert reload_refusals(running, moved) == ["[authz] url", "[listen] public"]
    with pytest.raises(ConfigError) as info:
        check_reload(running, moved)
    assert str(info.value) == ("[authz] url changed; [listen] public changed: needs a restart of the interceptor")
    renamed = load(write(tmp_path, good(material, **{'manager = "robot1"': 'manager = "robot9"'})))
    with pytest.raises(ConfigError, match="^manager changed: needs a restart"):
        check_reload(running, renamed)


def test_urls_is_not_a_key_of_its_own(tmp_path):
    """``[authz] url`` takes one URL or a list; ``urls`` is the parsed form, not a key."""
    for name in ("ca", "c", "k"):
        (tmp_path / name).write_text("")
    cfg = tmp_path / "i.toml"
    cfg.write_text('manager = "m"\nroles = ["node"]\n[tls]\nca = "ca"\ncert = "c"\nkey = "k"\n'
                   '[authz]\nurl = "https://127.0.0.1:8443"\nurls = ["https://127.0.0.1:8444"]\n')
    with pytest.raises(ConfigError, match="unknown key 'urls' in \\[authz\\]"):
        load(cfg)


def test_ros2_profile_makes_its_directory_and_an_unwritable_place_is_one_line(tmp_path):
    """``--ros2-profile /etc/cryptoros/dds-localhost.xml`` (docs/ros2.md) makes the
    directory as the other CLI outputs do; a place that cannot be written (a file where a
    directory should be) is one line, not a traceback."""
    from click.testing import CliRunner

    from interceptor.cli import main

    written = CliRunner().invoke(main, ["--ros2-profile", str(tmp_path / "etc" / "cryptoros" / "p.xml")])
    assert written.exit_code == 0, written.output
    assert (tmp_path / "etc" / "cryptoros" / "p.xml").read_text().startswith("<?xml"), written.output
    (tmp_path / "file").write_text("")
    result = CliRunner().invoke(main, ["--ros2-profile", str(tmp_path / "file" / "p.xml")])
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cryptoros-interceptor: error: cannot write "), result.output
