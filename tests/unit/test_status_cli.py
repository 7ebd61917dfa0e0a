"""``cryptoros status`` / ``denials`` when the status endpoint cannot be asked or answers
as something else than an interceptor's ``/status``: one line that says what to try, exit 2."""

from __future__ import annotations

import json
import socket
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from click.testing import CliRunner

from interceptor.status import denials, status


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def answering():
    """A real HTTP server on loopback answering every GET with the body it is given."""
    servers = []

    def serve(body: bytes, content_type: str = "application/json", code: int = 200) -> str:
        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 (http.server's name)
                self.send_response(code)
                self.send_header("Content-Type", content_type)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args):
                pass

        server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        servers.append(server)
        return f"http://127.0.0.1:{server.server_address[1]}/healthz"

    yield serve
    for server in servers:
        server.shutdown()
        server.server_close()


def test_a_refused_status_read_asks_whether_the_interceptor_runs(tmp_path, monkeypatch):
    config = tmp_path / "robot_a.toml"  # its [listen] metrics endpoint: a port nobody listens on
    url = f"http://127.0.0.1:{_closed_port()}/status"
    monkeypatch.setattr("interceptor.status._url_from_config", lambda path: (url, "robot_a"))
    r = CliRunner().invoke(status, ["--config", str(config)])
    assert r.exit_code == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert "Connection refused" in lines[0]
    assert f"is the interceptor running? start it with cryptoros-interceptor --config {config}" in lines[0]


def test_without_a_config_the_hint_names_a_placeholder():
    r = CliRunner().invoke(status, ["--url", f"http://127.0.0.1:{_closed_port()}/status"])
    assert r.exit_code == 2
    assert r.stderr.strip().endswith("(is the interceptor running? start it with cryptoros-interceptor --config FILE)")


INTERCEPTOR_HEALTHZ = json.dumps({"status": "ok", "open_streams": 0, "feed_age": 0.5}).encode()
AUTHZ_PROBE = json.dumps({"status": "ok", "database": "ok", "kid": "k1", "certificate": "ok"}).encode()


@pytest.mark.parametrize("command", [status, denials], ids=["status", "denials"])
@pytest.mark.parametrize(("body", "missing"), [
    (INTERCEPTOR_HEALTHZ, "no manager, roles, public, health, certificate, feed, denials"),
    (AUTHZ_PROBE, "no manager, roles, public, health, feed, open_streams, denials; "
                  "certificate is not an object"),
    (b"[1, 2]", "not a JSON object"),
    (b"# HELP cryptoros_streams\n", "not JSON"),
], ids=["interceptor-healthz", "authz-probe", "json-list", "prometheus-text"])
def test_an_answer_that_is_not_an_interceptors_status_is_one_line(answering, command, body, missing):
    url = answering(body)
    r = CliRunner().invoke(command, ["--url", url])
    assert r.exit_code == 2, r.output
    assert r.stdout == ""  # denials: no false "no refusals recorded"
    assert r.stderr.strip() == (f"cryptoros {command.name}: error: {url} did not answer as an interceptor's "
                                f"/status ({missing}): give its [listen] metrics endpoint's /status")


@pytest.mark.parametrize("command", [status, denials], ids=["status", "denials"])
def test_an_http_error_answer_is_not_an_interceptors_status(answering, command):
    url = answering(json.dumps({"status": "token_expired", "detail": "expired"}).encode(), code=503)
    r = CliRunner().invoke(command, ["--url", url])
    assert r.exit_code == 2, r.output
    assert r.stderr.strip() == (f"cryptoros {command.name}: error: {url} did not answer as an interceptor's "
                                "/status (HTTP 503 Service Unavailable): give its [listen] metrics endpoint's /status")


def test_an_answer_with_a_field_render_cannot_read_is_one_line(answering):
    body = {"manager": "robot_a", "roles": ["node"], "public": "127.0.0.1:11411", "health": "ok",
            "certificate": {"serial": "1f"}, "feed": {"age": 1.0, "revoked_tokens": 0, "disabled_managers": []},
            "open_streams": 0, "denials": []}
    url = answering(json.dumps(body).encode())
    r = CliRunner().invoke(status, ["--url", url])
    assert r.exit_code == 2, r.output
    assert r.stderr.strip() == (f"cryptoros status: error: {url} did not answer as an interceptor's /status "
                                "(certificate has no not_after, days_left): give its [listen] metrics "
                                "endpoint's /status")
