"""``fedlgr deploy superlink``'s gateway, on real processes on localhost: the robots' port
passes on Flower's Fleet API only (a SuperNode joins through it; ``flwr supernode register``
and the Control API are refused there with a 403 and work on the loopback port), SIGTERM
stops Flower too, Flower dying ends the gateway; ``--expose-control-api`` warns."""

from __future__ import annotations

import http.client
import json
import re
import shlex
import signal
import ssl
import subprocess
import time

import psutil
import pytest

from fedlgr.shell.cli import main
from fedlgr.shell.deploy.gateway import refusal
from tests.support.flower import BIN, Federation

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def federation(tmp_path_factory):
    fed = Federation(tmp_path_factory.mktemp("gateway"))
    try:
        fed.start_superlink()
        ca = str(fed.creds / "ca.pem")
        fed.fedlgr("connect", "robots-port", "--superlink", f"127.0.0.1:{fed.port}", "--ca", ca)
        yield fed
    finally:
        fed.stop()
    assert not fed.leftovers()


@pytest.fixture
def own_federation(tmp_path):
    """A federation of its own, for the tests that end its SuperLink."""
    fed = Federation(tmp_path)
    try:
        fed.start_superlink()
        yield fed
    finally:
        fed.stop()
    assert not fed.leftovers()


def flwr(fed: Federation, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(BIN / "flwr"), *args], env=fed.env, capture_output=True, text=True, timeout=120
    )


def request(fed: Federation, port: int, method: str, path: str) -> tuple[int, bytes, str]:
    """``method path`` sent as written (http.client keeps ``..``), over TLS checked with
    the deployment's ca.pem: status, body, content type."""
    context = ssl.create_default_context(cafile=str(fed.creds / "ca.pem"))
    conn = http.client.HTTPSConnection("127.0.0.1", port, context=context, timeout=30)
    try:
        conn.request(method, path, body=b"", headers={"content-type": "application/protobuf"})
        answer = conn.getresponse()
        return answer.status, answer.read(), answer.getheader("content-type")
    finally:
        conn.close()


def wait_for(read, pattern: str, proc: subprocess.Popen | None = None) -> re.Match:
    """``pattern`` in the text ``read()`` gives, within a minute (and while ``proc`` runs)."""
    deadline = time.monotonic() + 60
    while True:
        ended = proc is not None and proc.poll() is not None
        found = re.search(pattern, read())
        if found or ended or time.monotonic() > deadline:
            assert found, f"{pattern!r} not seen (ended: {ended}):\n{read()[-3000:]}"
            return found
        time.sleep(0.2)


def test_keys_register_on_the_superlinks_machine_only(federation):
    public = str(federation.node_key("stranger", register=False)) + ".pub"
    out = flwr(federation, "supernode", "register", public, "robots-port")
    assert out.returncode == 1
    assert "403 Forbidden" in out.stderr and "/v1/control/register-node" in out.stderr
    log = federation.log("superlink")
    assert "fedlgr gateway: refused POST '/v1/control/register-node' from 127.0.0.1" in log
    assert "ControlServicer.RegisterNode" not in log  # Flower never saw it
    assert '"POST /v1/control/register-node HTTP/1.1"' not in log  # its access log

    out = flwr(federation, "supernode", "register", public, "local")  # the loopback port
    assert out.returncode == 0, out.stdout + out.stderr
    node = re.search(r"SuperNode (\d+) registered successfully", out.stdout).group(1)
    wait_for(lambda: federation.log("superlink"), rf"Created node_id={node}\b")


def test_a_registered_robot_joins_through_the_robots_port(federation, synth_dir):
    key = federation.node_key("robot0")  # registered on the loopback port
    robot = federation.start_supernode("robot0", key, 0, synth_dir)  # the robots' port
    node = wait_for(lambda: federation.log("robot0"), r"SuperNode ID: (\d+)", robot).group(1)
    wait_for(lambda: federation.log("superlink"), rf"Activated node_id={node}\b")
    out = flwr(federation, "supernode", "list", "local", "--format", "json")
    listed = json.loads(out.stdout)
    assert listed["success"], out.stdout
    assert {n["node-id"]: n["status"] for n in listed["nodes"]}[node] == "online"


@pytest.mark.parametrize(
    ("method", "path"),
    [
        ("POST", "/v1/control/start-run"),
        ("POST", "/v1/control/register-node"),
        ("POST", "/v1/fleet/../control/start-run"),  # Flower would answer it (404 here)
        ("POST", "/v1/fleet/%2e%2e/control/start-run"),
        ("GET", "/v1/fleet/get-run"),
        ("POST", "/health"),
    ],
)
def test_the_robots_port_refuses_all_but_the_fleet_api(federation, method, path):
    status, body, kind = request(federation, federation.port, method, path)
    assert (status, kind) == (403, "text/plain; charset=utf-8")
    assert body.decode() == refusal(f"127.0.0.1:{federation.internal_port}")
    assert body.decode().count("\n") == 1


def test_the_robots_port_passes_the_fleet_api_on(federation):
    """Flower's own answer (no SuperNode signature: 401), byte for byte."""
    through = request(federation, federation.port, "POST", "/v1/fleet/get-run")
    direct = request(federation, federation.internal_port, "POST", "/v1/fleet/get-run")
    assert (
        through
        == direct
        == (401, b'{"detail":"Invalid SuperNode authentication"}', "application/json")
    )


def child_of(gateway: subprocess.Popen, name: str) -> psutil.Process:
    """The gateway's child whose command line holds ``name``."""
    children = psutil.Process(gateway.pid).children()
    [child] = [c for c in children if name in " ".join(c.cmdline())]
    return child


def flower_of(gateway: subprocess.Popen) -> psutil.Process:
    return child_of(gateway, "flower-superlink")


def test_sigterm_stops_flower_too(own_federation):
    gateway = own_federation.procs["superlink"]
    child = flower_of(gateway)
    executor = child_of(gateway, "fedlgr.shell.deploy.flower.executor")
    gateway.send_signal(signal.SIGTERM)
    assert gateway.wait(timeout=30) == 128 + signal.SIGTERM
    assert not child.is_running() and not executor.is_running()
    assert "fedlgr: terminated (SIGTERM)" in own_federation.log("superlink")


def test_flower_dying_ends_the_gateway(own_federation):
    gateway = own_federation.procs["superlink"]
    flower_of(gateway).kill()
    assert gateway.wait(timeout=30) == 1
    line = (
        "fedlgr: error: flower-superlink ended (killed by SIGKILL); its log is above. "
        "The gateway stops too."
    )
    assert line in own_federation.log("superlink").splitlines()


def test_the_serverapp_executor_dying_ends_the_gateway(own_federation):
    """In process isolation Flower starts no ServerApp of its own: without fedlgr's
    executor a run would wait for ever, so the gateway stops, saying why."""
    gateway = own_federation.procs["superlink"]
    flower = flower_of(gateway)
    child_of(gateway, "fedlgr.shell.deploy.flower.executor").kill()
    assert gateway.wait(timeout=30) == 1
    line = (
        "fedlgr: error: its ServerApp executor ended (killed by SIGKILL); its log is above. "
        "The gateway stops too."
    )
    assert line in own_federation.log("superlink").splitlines()
    assert not flower.is_running()


def test_print_command_shows_flower_on_loopback_and_the_gateway(tmp_path, capsys):
    assert main(["deploy", "certs", str(tmp_path)]) == 0
    capsys.readouterr()
    args = ["deploy", "superlink", "--certs", str(tmp_path), "--host", "0.0.0.0"]
    assert main([*args, "--port", "9200", "--print-command"]) == 0
    out = capsys.readouterr()
    flower, executor, gateway, connect = out.out.strip().splitlines()
    cmd = shlex.split(flower)
    assert cmd[cmd.index("--host") + 1 :][:3] == ["127.0.0.1", "--port", "9201"]
    assert "--enable-supernode-auth" in cmd
    # Flower runs no ServerApp itself: fedlgr's executor forks them, over TLS on loopback
    assert cmd[-2:] == ["--isolation", "process"]
    assert shlex.split(executor)[1:] == [
        "-m",
        "fedlgr.shell.deploy.flower.executor",
        "--preload",
        "serverapp",
        "--runtime-api-address",
        "127.0.0.1:9201",
        "--root-certificates",
        str(tmp_path / "ca.pem"),
    ]
    assert gateway == (
        "fedlgr: the robots' port https://0.0.0.0:9200 is fedlgr's gateway: POST "
        "/v1/fleet/<name> forwarded to https://127.0.0.1:9201, the rest refused (403)"
    )
    assert connect.endswith(
        f"fedlgr deploy connect NAME --superlink 127.0.0.1:9201 --ca {tmp_path / 'ca.pem'}"
    )
    assert "WARNING" not in out.err

    assert main([*args, "--internal-port", "9300", "--print-command"]) == 0
    assert "--port 9300" in capsys.readouterr().out
    assert main([*args, "--cold-apps", "--print-command"]) == 0  # Flower's own SuperExec
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3 and "--isolation" not in lines[0]
    assert main([*args, "--internal-port", "9200", "--port", "9200", "--print-command"]) == 1
    assert "--internal-port 9200: must differ from --port" in capsys.readouterr().err


def test_expose_control_api_warns(tmp_path, capsys):
    assert main(["deploy", "certs", str(tmp_path)]) == 0
    capsys.readouterr()
    args = ["deploy", "superlink", "--certs", str(tmp_path), "--host", "0.0.0.0"]
    assert main([*args, "--expose-control-api", "--print-command"]) == 0
    out = capsys.readouterr()
    cmd = shlex.split(out.out)
    assert cmd[cmd.index("--host") + 1 :][:3] == ["0.0.0.0", "--port", "9092"]
    assert "WARNING: --expose-control-api" in out.err
    assert "anyone\nfedlgr: who reaches it (ca.pem is public) can register a SuperNode key" in (
        out.err
    )
    assert "submit runs with flwr run - code\nfedlgr: that runs on this server" in out.err
    assert main([*args, "--expose-control-api", "--internal-port", "9300"]) == 1
    assert "--internal-port is the gateway's" in capsys.readouterr().err


def test_a_certificate_without_loopback_is_refused(tmp_path, capsys):
    """``fedlgr deploy certs`` always adds 127.0.0.1; a certificate made otherwise (an
    organisation's CA, an older fedlgr) may lack it."""
    from fedlgr.shell.deploy.credentials import make_certificates

    make_certificates(tmp_path, ("robots.lab",), days=30)
    assert main(["deploy", "superlink", "--certs", str(tmp_path), "--print-command"]) == 1
    err = capsys.readouterr().err
    assert f"{tmp_path / 'server.pem'} does not name 127.0.0.1" in err
    assert "--host 127.0.0.1" in err
