"""``fedlgr deploy``: credentials that verify, the flwr connection file, the Flower command
lines (TLS and SuperNode authentication unless --insecure), refusals that name the missing
file, and ``deploy run``'s exit status from the run's final state (a stand-in ``flwr``)."""

from __future__ import annotations

import datetime as dt
import ipaddress
import logging
import os
import shlex
import shutil
import stat
import sys
import tomllib
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.x509.verification import PolicyBuilder, Store, VerificationError
from flwr.common.config import parse_config_args

from fedlgr.errors import FedlgrError
from fedlgr.shell.cli import main
from fedlgr.shell.cli.deploy import launch
from fedlgr.shell.deploy.credentials import make_node_key
from fedlgr.shell.deploy.flower import APP_DIR


def option(cmd: list[str], flag: str) -> str:
    return cmd[cmd.index(flag) + 1]


def printed(capsys) -> list[str]:
    """The one command line a --print-command run printed, split as the shell would."""
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1, lines
    return shlex.split(lines[0])


@pytest.fixture
def certs(tmp_path, capsys):
    folder = tmp_path / "creds"
    assert main(["deploy", "certs", str(folder)]) == 0
    capsys.readouterr()
    return folder


def test_certs_verify_for_the_hosts_given(tmp_path, capsys):
    folder = tmp_path / "creds"
    hosts = ["--host", "robots.lab", "--host", "10.0.0.5"]
    assert main(["deploy", "certs", str(folder), *hosts]) == 0
    out = capsys.readouterr().out
    for name in ("ca.pem", "ca.key", "server.pem", "server.key"):
        assert (folder / name).is_file() and str(folder / name) in out
    assert "every robot" in out and "offline" in out
    assert (folder / "ca.key").stat().st_mode & 0o077 == 0

    ca = x509.load_pem_x509_certificate((folder / "ca.pem").read_bytes())
    server = x509.load_pem_x509_certificate((folder / "server.pem").read_bytes())
    store, now = Store([ca]), dt.datetime.now(dt.UTC)
    # and 127.0.0.1, where Flower's own processes reach the SuperLink behind the gateway
    loopback = x509.IPAddress(ipaddress.ip_address("127.0.0.1"))
    for name in (x509.DNSName("robots.lab"), x509.IPAddress(ipaddress.ip_address("10.0.0.5"))):
        verifier = PolicyBuilder().store(store).time(now).build_server_verifier(name)
        chain = verifier.verify(server, [])
        assert chain[-1] == ca
    for name in (loopback,):
        verifier = PolicyBuilder().store(store).time(now).build_server_verifier(name)
        chain = verifier.verify(server, [])
        assert chain[-1] == ca
    localhost = (
        PolicyBuilder().store(store).time(now).build_server_verifier(x509.DNSName("localhost"))
    )
    with pytest.raises(VerificationError):
        localhost.verify(server, [])  # only the hosts given, and 127.0.0.1

    assert main(["deploy", "certs", str(folder)]) == 1  # would lock the robots out
    assert str(folder / "ca.pem") in capsys.readouterr().err


def test_certs_default_to_localhost(certs):
    server = x509.load_pem_x509_certificate((certs / "server.pem").read_bytes())
    names = server.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert names.get_values_for_type(x509.DNSName) == ["localhost"]
    assert {str(a) for a in names.get_values_for_type(x509.IPAddress)} == {"127.0.0.1", "::1"}


def test_node_key_pair_matches(tmp_path, capsys):
    assert main(["deploy", "node-key", str(tmp_path), "robot0"]) == 0
    out = capsys.readouterr().out
    assert f"flwr supernode register {tmp_path / 'robot0.pub'}" in out
    key = serialization.load_ssh_private_key((tmp_path / "robot0").read_bytes(), None)
    public = key.public_key().public_bytes(
        serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH
    )
    assert (tmp_path / "robot0.pub").read_bytes().strip() == public
    assert main(["deploy", "node-key", str(tmp_path), "robot0"]) == 1  # no silent replacement
    assert str(tmp_path / "robot0") in capsys.readouterr().err


def test_connect_writes_flwr_config_and_keeps_the_rest(tmp_path, certs, monkeypatch, capsys):
    home = tmp_path / "flwr-home"
    home.mkdir()
    monkeypatch.setenv("FLWR_HOME", str(home))
    (home / "config.toml").write_text(
        '[superlink]\ndefault = "other"\n\n[superlink.other]\naddress = "10.1.1.1:9093"\n'
        "insecure = true\n"
    )
    monkeypatch.chdir(tmp_path)
    args = ["deploy", "connect", "robots", "--superlink", "robots.lab:9092"]
    assert main([*args, "--ca", "creds/ca.pem"]) == 0
    assert "--federation robots" in capsys.readouterr().out  # the default stays "other"
    config = tomllib.loads((home / "config.toml").read_text())
    assert config["superlink"]["robots"] == {
        "address": "robots.lab:9092",
        "root-certificates": str(certs / "ca.pem"),  # absolute, as flwr requires
    }
    assert config["superlink"]["other"] == {"address": "10.1.1.1:9093", "insecure": True}
    assert config["superlink"]["default"] == "other"

    assert main([*args, "--ca", "creds/ca.pem", "--default"]) == 0
    assert tomllib.loads((home / "config.toml").read_text())["superlink"]["default"] == "robots"

    assert main([*args, "--insecure"]) == 0
    assert "No TLS" in capsys.readouterr().err
    entry = tomllib.loads((home / "config.toml").read_text())["superlink"]["robots"]
    assert entry == {"address": "robots.lab:9092", "insecure": True}

    assert main([*args, "--ca", "creds/nope.pem"]) == 1
    assert str(tmp_path / "creds" / "nope.pem") in capsys.readouterr().err


def test_connect_starts_a_config(tmp_path, certs, monkeypatch):
    monkeypatch.setenv("FLWR_HOME", str(tmp_path / "new-home"))
    cmd = ["deploy", "connect", "local", "--superlink", "127.0.0.1:9092"]
    assert main([*cmd, "--ca", str(certs / "ca.pem")]) == 0
    config = tomllib.loads((tmp_path / "new-home" / "config.toml").read_text())
    assert config["superlink"]["default"] == "local"
    assert config["superlink"]["local"]["address"] == "127.0.0.1:9092"


def test_superlink_command_has_tls_and_node_auth(certs, capsys):
    """Flower on loopback (port + 1) behind fedlgr's Fleet-only gateway on the port."""
    assert main(["deploy", "superlink", "--certs", str(certs), "--print-command"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 4, lines
    cmd = shlex.split(lines[0])
    assert cmd[-2:] == ["--isolation", "process"]  # fedlgr's executor runs the ServerApps
    assert "--root-certificates" in lines[1] and "fedlgr.shell.deploy.flower.executor" in lines[1]
    del lines[1]
    assert cmd[0] == str(launch.flower_command("flower-superlink"))
    assert option(cmd, "--ssl-ca-certfile") == str(certs / "ca.pem")
    assert option(cmd, "--ssl-certfile") == str(certs / "server.pem")
    assert option(cmd, "--ssl-keyfile") == str(certs / "server.key")
    assert "--enable-supernode-auth" in cmd and "--insecure" not in cmd
    assert "--disable-runtime-dependency-installation" in cmd
    assert option(cmd, "--host") == "127.0.0.1" and option(cmd, "--port") == "9093"
    assert lines[1] == (
        "fedlgr: the robots' port https://127.0.0.1:9092 is fedlgr's gateway: POST "
        "/v1/fleet/<name> forwarded to https://127.0.0.1:9093, the rest refused (403)"
    )
    assert lines[2].endswith(
        f"fedlgr deploy connect NAME --superlink 127.0.0.1:9093 --ca {certs / 'ca.pem'}"
    )


def test_superlink_insecure_warns_and_drops_auth(capsys):
    cmd = ["deploy", "superlink", "--insecure", "--host", "0.0.0.0", "--print-command"]
    assert main(cmd) == 0
    out = capsys.readouterr()
    assert "No TLS" in out.err and "No SuperNode authentication" in out.err
    cmd = shlex.split(out.out.strip().splitlines()[0])
    assert "--insecure" in cmd and "--enable-supernode-auth" not in cmd
    assert not any(c.startswith("--ssl") for c in cmd)
    assert option(cmd, "--host") == "127.0.0.1"  # Flower; the gateway takes 0.0.0.0
    executor = shlex.split(out.out.strip().splitlines()[1])
    assert executor[-1] == "--insecure" and "--root-certificates" not in executor
    assert "http://0.0.0.0:9092 is fedlgr's gateway" in out.out


def test_superlink_refuses_a_missing_certificate(certs, capsys):
    (certs / "server.key").unlink()
    assert main(["deploy", "superlink", "--certs", str(certs), "--print-command"]) == 1
    err = capsys.readouterr().err
    assert str(certs / "server.key") in err and "fedlgr deploy certs" in err
    assert main(["deploy", "superlink", "--print-command"]) == 1
    assert "--certs" in capsys.readouterr().err


def test_impossible_ports_waits_and_database_folders_are_one_line(
    tmp_path, synth_dir, capsys, monkeypatch
):
    """Refused before anything is written or started (Flower took them, or wrote port 99999
    into its config, or ended in a SQLAlchemy traceback for a missing database folder)."""
    data = str(Path(shutil.copytree(synth_dir, tmp_path / "robot")))
    node = ["deploy", "supernode", "--data", data, "--insecure", "--print-command"]
    link = ["deploy", "superlink", "--insecure", "--port", "47105", "--print-command"]
    cases = {
        ("--superlink", "127.0.0.1:0"): "--superlink '127.0.0.1:0': a port is 1 to 65535",
        ("--superlink", "h:99999"): "--superlink 'h:99999': a port is 1 to 65535",
        ("--max-wait-time", "-1"): "--max-wait-time -1.0: must be 0 or more",
        ("--max-retries", "-1"): "--max-retries -1: must be 0 or more",
    }
    for extra, said in cases.items():
        argv = [*node, *(() if extra[0] == "--superlink" else ("--superlink", "h:9092")), *extra]
        assert main(argv) == 1, extra
        assert capsys.readouterr().err.strip() == f"fedlgr: error: {said}"
    home = tmp_path / "flwr-home"
    monkeypatch.setenv("FLWR_HOME", str(home))
    assert main(["deploy", "connect", "robots", "--superlink", "h:99999", "--insecure"]) == 1
    assert capsys.readouterr().err.strip().endswith("'h:99999': a port is 1 to 65535")
    assert not home.exists()
    missing = tmp_path / "no" / "such" / "link.db"
    assert main([*link, "--database", str(missing)]) == 1
    said = f"fedlgr: error: --database {missing}: no folder {missing.parent} (make it first)"
    assert capsys.readouterr().err.strip() == said
    assert main([*link, "--database", str(tmp_path)]) == 1
    assert "a folder; name the SuperLink's database file" in capsys.readouterr().err


def test_supernode_node_config(tmp_path, certs, synth_dir, capsys):
    data = Path(shutil.copytree(synth_dir, tmp_path / "robot data"))
    key, _ = make_node_key(tmp_path / "keys", "robot1")
    state = tmp_path / "it's state"
    args = ["deploy", "supernode", "--superlink", "robots.lab:9092", "--ca", str(certs / "ca.pem")]
    args += ["--key", str(key), "--data", str(data), "--client", "1", "--state-dir", str(state)]
    assert main([*args, "--threads", "2", "--port", "9095", "--print-command"]) == 0
    cmd = printed(capsys)
    # flower-supernode through fedlgr's launcher, its idle poll shortened
    assert cmd[:5] == [
        sys.executable,
        "-m",
        "fedlgr.shell.deploy.flower.supernode",
        "--poll-s",
        "0.5",
    ]
    assert option(cmd, "--heartbeat-s") == "30"  # Flower's own interval
    assert option(cmd, "--superlink") == "robots.lab:9092"
    assert option(cmd, "--root-certificates") == str(certs / "ca.pem")
    assert option(cmd, "--auth-supernode-private-key") == str(key)
    assert option(cmd, "--port") == "9095" and "--insecure" not in cmd
    # read back as flower-supernode reads it
    assert parse_config_args([option(cmd, "--node-config")]) == {
        "data-path": str(data),
        "client": 1,
        "state-dir": str(state),
        "threads": 2,
    }


def test_supernode_refuses_missing_files(tmp_path, certs, synth_dir, capsys):
    data = tmp_path / "data"
    data.mkdir()
    key, _ = make_node_key(tmp_path / "keys", "robot1")
    base = ["deploy", "supernode", "--superlink", "127.0.0.1:9092", "--client", "0"]
    cases = {
        "no data": (
            ["--ca", str(certs / "ca.pem"), "--key", str(key), "--data", "nodata"],
            "nodata",
        ),
        "no key": (["--ca", str(certs / "ca.pem"), "--key", "nokey", "--data", str(data)], "nokey"),
        "no ca": (["--ca", "noca.pem", "--key", str(key), "--data", str(data)], "noca.pem"),
        "key unset": (["--ca", str(certs / "ca.pem"), "--data", str(data)], "--key"),
    }
    for case, (extra, named) in cases.items():
        assert main([*base, *extra, "--print-command"]) == 1, case
        assert named in capsys.readouterr().err, case

    data = Path(shutil.copytree(synth_dir, tmp_path / "robot"))
    assert main([*base, "--data", str(data), "--insecure", "--print-command"]) == 0
    out = capsys.readouterr()
    assert "No TLS" in out.err
    cmd = shlex.split(out.out.strip())
    assert "--insecure" in cmd and "--root-certificates" not in cmd
    # Node authentication needs TLS: refused here, not passed on to Flower.
    insecure = [*base, "--data", str(data), "--insecure", "--key", str(key), "--print-command"]
    assert main(insecure) == 1
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "fedlgr: error: --insecure turns TLS off, and SuperNode authentication needs TLS: "
        "drop --key (or drop --insecure)"
    )


def test_supernode_refuses_the_wrong_kind_of_file_or_folder(tmp_path, certs, synth_dir, capsys):
    """A key's public half as --key, a key as --ca, a file as --state-dir or under
    --cache-dir, a folder in /proc, a key as --weights, 100,000 threads: one line each
    before Flower starts (the fifth to seventh fault sweeps: k30, k37, k38, k62, e16, e17,
    e25), with --print-command too; a missing state folder is made only by a start."""
    key, pub = make_node_key(tmp_path / "keys", "robot1")
    ca = str(certs / "ca.pem")
    base = ["deploy", "supernode", "--superlink", "127.0.0.1:9092", "--data", str(synth_dir)]
    cases = {
        ("--ca", ca, "--key", str(pub)): f"--key {pub}: not a private node key (the public "
        "half: give NAME, not NAME.pub); fedlgr deploy node-key DIR NAME writes one",
        ("--ca", str(key), "--key", str(key)): f"--ca {key}: not a PEM certificate (the "
        "deployment's ca.pem, made by fedlgr deploy certs DIR)",
        ("--insecure", "--state-dir", str(key)): f"--state-dir {key}: a file, not a folder",
        ("--insecure", "--cache-dir", str(key / "x")): f"--cache-dir {key / 'x'}: under {key}, "
        "a file, not a folder",
        ("--insecure", "--weights", str(key)): f"--weights {key}: cannot read a state dict",
        ("--insecure", "--threads", "100000"): "--threads 100000: 1 to 1024",
    }
    cases[("--ca", ca, "--key", str(tmp_path))] = f"--key: {tmp_path} is a folder"
    cases[("--ca", "/dev/zero", "--key", str(key))] = "--ca: /dev/zero is not a regular file"
    if Path("/proc/self").is_dir():  # Linux: no folder can be made there, even by root
        cases[("--insecure", "--state-dir", "/proc/fedlgr")] = (
            "--state-dir /proc/fedlgr: cannot make it"
        )
    for extra, said in cases.items():
        assert main([*base, *extra, "--print-command"]) == 1, extra
        assert capsys.readouterr().err.strip().splitlines()[-1].startswith(f"fedlgr: error: {said}")
    state = tmp_path / "state" / "robot1"
    assert (
        main([*base, "--ca", ca, "--key", str(key), "--state-dir", str(state), "--print-command"])
        == 0
    )
    assert f'state-dir="{state}"' in capsys.readouterr().out and not state.exists()


def test_a_private_key_others_can_read_is_refused_and_an_open_folder_is_said(
    tmp_path, synth_dir, capsys
):
    """The seventh fault sweep: a robot's private key of mode 0644 was taken as --key (z06;
    ssh refuses such a key), and keys were written into a folder every user can write
    (x12) without a word."""
    key, _ = make_node_key(tmp_path / "keys", "robot1")
    ca = tmp_path / "creds" / "ca.pem"
    assert main(["deploy", "certs", str(ca.parent)]) == 0
    key.chmod(0o644)
    node = ["deploy", "supernode", "--superlink", "h:9092", "--data", str(synth_dir)]
    assert main([*node, "--ca", str(ca), "--key", str(key), "--print-command"]) == 1
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"fedlgr: error: --key {key}: a private key others can read or write (mode 0644); "
        f"chmod 600 {key}"
    )
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    assert main(["deploy", "node-key", str(shared), "robot2"]) == 0
    assert (
        f"fedlgr: warning: {shared} can be written by every user (mode 0777): anyone could "
        f"replace a public key, the roster or ca.pem in it; chmod 700 {shared}"
    ) in capsys.readouterr().err
    assert stat.S_IMODE((shared / "robot2").stat().st_mode) == 0o600
    # The eighth sweep: the SuperNode took a key from that folder without a word (u04),
    # and the SuperLink a server.key of mode 0644 (u31).
    node = [*node, "--ca", str(ca), "--key", str(shared / "robot2"), "--print-command"]
    assert main(node) == 0
    assert (
        f"fedlgr: warning: {shared} can be written by every user (mode 0777): anyone could "
        f"replace the key in it; chmod 700 {shared}"
    ) in capsys.readouterr().err
    (ca.parent / "server.key").chmod(0o644)
    assert main(["deploy", "superlink", "--certs", str(ca.parent), "--print-command"]) == 1
    server_key = ca.parent / "server.key"
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"fedlgr: error: --certs {server_key}: a private key others can read or write "
        f"(mode 0644); chmod 600 {server_key}"
    )
    # The tenth sweep: a --key reached through a link into that folder (d188), and a
    # --certs folder every user can write (d198), were taken without a word.
    (tmp_path / "mine").mkdir(mode=0o700)
    (tmp_path / "mine" / "robot2").symlink_to(shared / "robot2")
    node[node.index("--key") + 1] = str(tmp_path / "mine" / "robot2")
    assert main(node) == 0
    assert (
        f"fedlgr: warning: {shared} can be written by every user (mode 0777): anyone could "
        f"replace the key in it; chmod 700 {shared}"
    ) in capsys.readouterr().err
    server_key.chmod(0o600)
    ca.parent.chmod(0o777)
    assert main(["deploy", "superlink", "--certs", str(ca.parent), "--print-command"]) == 0
    assert (
        f"fedlgr: warning: {ca.parent} can be written by every user (mode 0777): anyone could "
        f"replace the certificates or server.key in it; chmod 700 {ca.parent}"
    ) in capsys.readouterr().err


@pytest.mark.parametrize("host", ["bad host", "999.1.1.1", "host:1", ""])
def test_superlink_refuses_a_host_it_cannot_listen_on(host, capsys):
    assert main(["deploy", "superlink", "--insecure", "--host", host, "--print-command"]) == 1
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"fedlgr: error: --host {host!r}: not an address to listen on (an IP address such as "
        "0.0.0.0 or 127.0.0.1, or this machine's host name)"
    )


def test_a_robot_with_a_broken_dataset_is_refused_when_its_supernode_starts(
    tmp_path, certs, synth_dir, capsys
):
    """At start, in one line naming the file, row and cell - not when a run arrives."""
    data = Path(shutil.copytree(synth_dir, tmp_path / "robot"))
    csv_path = data / "all_data.csv"
    lines = csv_path.read_text().splitlines()
    cells = lines[5].split(",")
    cells[-1] = "abc"
    lines[5] = ",".join(cells)
    csv_path.write_text("\n".join(lines) + "\n")
    key, _ = make_node_key(tmp_path / "keys", "robot0")
    args = ["deploy", "supernode", "--superlink", "127.0.0.1:9092", "--client", "0"]
    args += ["--ca", str(certs / "ca.pem"), "--key", str(key), "--data", str(data)]
    assert main([*args, "--print-command"]) == 1
    out = capsys.readouterr()
    [line] = out.err.strip().splitlines()
    assert line.startswith(f"fedlgr: error: {csv_path}") and "'abc'" in line
    assert "flower-supernode" not in out.out  # nothing was started


def test_run_command(tmp_path, fake_flwr, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    items = ["conf.yaml", "method=FedRootAvg", "--federation", "robots"]
    odd = ['tracking.run_name=it\'s a "run"', "data.path=C:\\robots\\data"]
    assert main(["deploy", "run", *items, *odd, "--print-command"]) == 0
    cmd = printed(capsys)
    assert cmd[:5] == [
        str(launch.flower_command("flwr")),
        "run",
        str(APP_DIR),
        "robots",
        "--stream",
    ]
    run_config = parse_config_args([option(cmd, "--run-config")])  # as flwr reads it
    assert run_config["config"] == str(tmp_path / "conf.yaml")
    overrides = ["method=FedRootAvg", *odd]
    assert shlex.split(run_config["overrides"]) == overrides  # as the ServerApp splits them


@pytest.fixture
def fake_flwr(tmp_path, monkeypatch):
    """A stand-in ``flwr``: ``run`` prints Flower's start line, ``ls`` the status in
    $FAKE_STATUS; the arguments of each call go to calls.txt."""
    script = tmp_path / "flwr"
    script.write_text(
        f"#!{sys.executable}\n"
        "import json, os, sys\n"
        f"open({str(tmp_path / 'calls.txt')!r}, 'a').write(' '.join(sys.argv[1:]) + '\\n')\n"
        "if sys.argv[1] == 'run':\n"
        "    print('Successfully started run 4242')\n"
        "    print('round 1 ...')\n"
        "else:\n"
        "    status, details = os.environ['FAKE_STATUS'].split('|')\n"
        "    print(json.dumps({'success': True, 'runs': [{'run-id': '4242', "
        "'status': status, 'status-details': details}]}))\n"
    )
    script.chmod(0o755)
    monkeypatch.setattr(launch, "flower_command", lambda name: script)
    home = tmp_path / "flwr-home"  # what fedlgr deploy connect robots ... writes
    home.mkdir()
    (home / "config.toml").write_text(
        '[superlink]\ndefault = "robots"\n\n[superlink.robots]\naddress = "10.0.0.5:9093"\n'
    )
    monkeypatch.setenv("FLWR_HOME", str(home))
    return tmp_path / "calls.txt"


def test_run_without_a_connection_is_refused_before_flower_starts_one_of_its_own(
    tmp_path, fake_flwr, monkeypatch, capsys
):
    """With no SuperLink connection flwr 1.42 writes its own config, whose default starts
    a local simulation SuperLink and SuperExec, left running when the run fails."""
    config = tmp_path / "conf.yaml"
    config.write_text("seed: 3\ndeploy:\n  roster: none\n")
    home = tmp_path / "bare-home"
    monkeypatch.setenv("FLWR_HOME", str(home))
    cases = [([], "the default connection"), (["--federation", "lab"], "lab")]
    cases += [([*extra, "--print-command"], which) for extra, which in cases]  # e21
    for extra, which in cases:
        assert main(["deploy", "run", str(config), *extra]) == 1
        [line] = capsys.readouterr().err.strip().splitlines()
        assert line.startswith(f"fedlgr: error: {which.replace('lab', '--federation lab')}: ")
        assert "add one with fedlgr deploy connect NAME --superlink HOST:PORT" in line
    assert not home.exists() and not fake_flwr.exists()  # nothing written, flwr never called


def test_run_exit_status_follows_the_flower_run(tmp_path, fake_flwr, monkeypatch, capsys):
    config = tmp_path / "conf.yaml"
    config.write_text("seed: 3\ndeploy:\n  roster: none\n")
    monkeypatch.setenv("FAKE_STATUS", "finished:completed|")
    assert main(["deploy", "run", str(config), "--federation", "robots"]) == 0
    out = capsys.readouterr().out
    assert "round 1 ..." in out and "4242 finished:completed" in out
    assert "ls robots --run-id 4242 --format json" in fake_flwr.read_text()

    monkeypatch.setenv("FAKE_STATUS", "finished:failed|ServerApp failed with exception:\n boom")
    assert main(["deploy", "run", str(config)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "fedlgr: error: Flower run 4242 ended finished:failed: "
        "ServerApp failed with exception: boom"
    ]
    # Flower's words quoting the store's URI (a ServerApp that could not reach it): masked
    monkeypatch.setenv(
        "FAKE_STATUS",
        "finished:failed|cannot reach postgresql://me:S3cretPw@db.lab/ml or host=db password=Pw2",
    )
    assert main(["deploy", "run", str(config)]) == 1
    err = capsys.readouterr().err
    assert "S3cretPw" not in err and "Pw2" not in err
    assert "postgresql://me:***@db.lab/ml or host=db password=***" in err


def test_run_reports_a_config_typo_before_anything_is_submitted(tmp_path, fake_flwr, capsys):
    """Checked on the submitting machine when the config is there: one line, no flwr run."""
    config = tmp_path / "conf.yaml"
    config.write_text("seed: 3\n")
    assert main(["deploy", "run", str(config), "federated.roundz=3"]) == 1
    [line] = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("fedlgr: error: ") and "federated.roundz" in line
    assert not fake_flwr.exists()  # flwr was never called


def test_run_with_simulated_faults_is_refused_before_anything_is_submitted(
    tmp_path, fake_flwr, capsys
):
    config = tmp_path / "conf.yaml"
    config.write_text("seed: 3\n")
    assert main(["deploy", "run", str(config), "federated.faults.dropout=0.2"]) == 1
    [line] = capsys.readouterr().err.strip().splitlines()
    assert line == (
        "fedlgr: error: federated.faults: faults are simulated in one process or Fabric's "
        "processes (fedlgr run); robots on Flower are real and nothing is simulated there"
    )
    assert not fake_flwr.exists()  # flwr was never called


@pytest.mark.parametrize(
    "uri",
    [
        "postgresql://me:S3cretPw@db.lab:5432/mlflow",
        "postgresql://db.lab/mlflow?user=me&password=S3cretPw",
        "https://me:S3cretPw@mlflow.lab",
        "host=db.lab user=me password=S3cretPw dbname=mlflow",  # libpq's keyword form
    ],
)
@pytest.mark.parametrize("print_command", [[], ["--print-command"]])
def test_run_refuses_a_password_on_the_command_line_before_printing_anything(
    tmp_path, fake_flwr, capsys, uri, print_command
):
    """Issue 37, Deliver 6: such an override was printed in the flwr command, kept in the
    SuperLink's database and sent to every robot in the run's config
    (tests/test_flower_secrets.py shows it on a real federation)."""
    config = tmp_path / "conf.yaml"
    config.write_text("seed: 3\n")
    assert main(["deploy", "run", str(config), f"tracking.uri={uri}", *print_command]) == 1
    out = capsys.readouterr()
    [line] = out.err.strip().splitlines()
    assert out.out == "" and "S3cretPw" not in line
    assert line.startswith(f"fedlgr: error: tracking.uri={uri.replace('S3cretPw', '***')}: ")
    assert not fake_flwr.exists()  # flwr was never called
    # without its password the URI goes on (the password is then the SuperLink's)
    bare = "postgresql://me@db.lab:5432/mlflow"
    assert main(["deploy", "run", str(config), f"tracking.uri={bare}", "--print-command"]) == 0
    assert bare in capsys.readouterr().out


def test_run_without_a_roster_is_refused_before_anything_is_submitted(tmp_path, fake_flwr, capsys):
    config = tmp_path / "conf.yaml"
    config.write_text("seed: 3\n")
    assert main(["deploy", "run", str(config)]) == 1
    [line] = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("fedlgr: error: deploy.roster is not set: ")
    roster = tmp_path / "roster.yaml"
    assert main(["deploy", "run", str(config), f"deploy.roster={roster}"]) == 1
    [line] = capsys.readouterr().err.strip().splitlines()
    assert line == (
        f"fedlgr: error: roster {roster}: no such file (fedlgr deploy node-key DIR NAME "
        "writes DIR/roster.yaml)"
    )
    assert not fake_flwr.exists()  # flwr was never called


def test_the_supernode_launcher_shortens_only_flowers_idle_poll_and_reply_wait(monkeypatch):
    """flwr 1.42's SuperNode sleeps 3 s when the SuperLink has no message and 0.5 s between
    looks for the ClientApp's reply, with no setting for either; the launcher shortens those
    two, and looks up the run during the reply waits (issue 50). If a flwr upgrade changes the
    loop, this fails: look again at supernode.py."""
    import inspect

    from flwr.supernode import start_client_internal as internal

    from fedlgr.shell.deploy.flower import supernode

    source = inspect.getsource(internal)
    assert source.count("time.sleep(3)") == 1, "flwr's idle poll is no longer time.sleep(3)"
    assert source.count("time.sleep(0.5)") == 2, "flwr's reply wait is no longer 0.5 s"
    waits: list[float | str] = []
    monkeypatch.setattr(supernode.time, "sleep", waits.append)
    clock = supernode._Clock(0.25, lambda: waits.append("run looked up"))
    clock.sleep(3)
    clock.sleep(0.5)
    clock.sleep(0.05)
    # the reply waits look whether the run still runs (supernode._RunWatch), the idle poll not
    assert waits == [0.25, "run looked up", supernode.REPLY_WAIT_S, "run looked up", 0.05]
    assert clock.monotonic is supernode.time.monotonic  # the rest of time passes through
    # what supernode._RunWatch wraps: flwr's loop calls them by their module names, with
    # these keywords, and the Fleet connection yields GetRun fourth
    assert "= _pull_and_store_message(" in source and "_push_messages(\n" in source
    assert list(inspect.signature(internal._push_messages).parameters) == [
        "state",
        "object_store",
        "send",
        "push_object",
    ]
    assert "with _init_connection(" in source and "get_run,\n" in source
    assert "node_id,\n            receive,\n            send,\n            get_run," in source


@pytest.mark.parametrize("poll", ["0", "0.01", "4", "nan", "-1"])
def test_supernode_refuses_a_poll_outside_its_range(tmp_path, synth_dir, poll, capsys):
    data = Path(shutil.copytree(synth_dir, tmp_path / "robot"))
    args = ["deploy", "supernode", "--superlink", "127.0.0.1:9092", "--data", str(data)]
    assert main([*args, "--insecure", "--poll-s", poll, "--print-command"]) == 1
    [line] = capsys.readouterr().err.strip().splitlines()[-1:]
    assert line == (f"fedlgr: error: --poll-s {float(poll)}: must be between 0.05 and 3 seconds")


@pytest.mark.parametrize("beat", ["9.9", "1801", "nan", "-10"])
def test_supernode_refuses_a_heartbeat_outside_flowers_range(tmp_path, synth_dir, beat, capsys):
    data = Path(shutil.copytree(synth_dir, tmp_path / "robot"))
    args = ["deploy", "supernode", "--superlink", "127.0.0.1:9092", "--data", str(data)]
    assert main([*args, "--insecure", "--heartbeat-s", beat, "--print-command"]) == 1
    [line] = capsys.readouterr().err.strip().splitlines()[-1:]
    expected = f"--heartbeat-s {float(beat)}: must be between 10 and 1800 seconds"
    assert line == f"fedlgr: error: {expected}"


def test_the_supernode_launcher_sets_the_heartbeat_flower_declares_and_beats_at(monkeypatch):
    """flwr 1.42's SuperNode declares HEARTBEAT_DEFAULT_INTERVAL when it activates and with
    every beat (its REST connection), and its sender waits by it; --heartbeat-s sets that
    name in both modules. If a flwr upgrade stops reading it there, this fails."""
    import inspect

    from flwr.common import constant
    from flwr.supercore import heartbeat
    from flwr.supernode import fleet_http_connection

    from fedlgr.shell.deploy.flower import supernode

    connection = inspect.getsource(fleet_http_connection)
    assert connection.count("heartbeat_interval=HEARTBEAT_DEFAULT_INTERVAL") == 2
    assert "HEARTBEAT_DEFAULT_INTERVAL - HEARTBEAT_CALL_TIMEOUT" in inspect.getsource(heartbeat)
    assert supernode.HEARTBEAT_RANGE == (
        constant.HEARTBEAT_MIN_INTERVAL,
        constant.HEARTBEAT_MAX_INTERVAL,
    )
    for module in (fleet_http_connection, heartbeat):
        monkeypatch.setattr(module, "HEARTBEAT_DEFAULT_INTERVAL", 30)
    supernode.set_heartbeat(10.0)
    assert fleet_http_connection.HEARTBEAT_DEFAULT_INTERVAL == 10.0
    assert heartbeat.HEARTBEAT_DEFAULT_INTERVAL == 10.0


def test_a_supernode_interrupted_while_it_imports_flower_says_one_line(tmp_path):
    """The eighth fault sweep (b02-b04): Ctrl-C in the first seconds of ``fedlgr deploy
    supernode`` - the launcher still importing Flower, which took over 8 s under load -
    printed a 40-line KeyboardInterrupt traceback. The interrupt is raised inside that
    import here, where the signal fell (a timed signal is not: under load it can land
    later, in Flower's own handler)."""
    import subprocess

    interrupted = (
        "import builtins, runpy, sys\n"
        "real = builtins.__import__\n"
        "def stopped(name, *args, **kwargs):\n"
        "    if name.startswith('flwr.supernode'):\n"
        "        raise KeyboardInterrupt\n"
        "    return real(name, *args, **kwargs)\n"
        "builtins.__import__ = stopped\n"
        "sys.argv = ['supernode', '--poll-s', '0.5', '--superlink', '127.0.0.1:9', '--insecure']\n"
        "runpy.run_module('fedlgr.shell.deploy.flower.supernode', run_name='__main__')\n"
    )
    command = [sys.executable, "-c", interrupted]
    with subprocess.Popen(command, stderr=subprocess.PIPE, text=True, cwd=tmp_path) as proc:
        try:
            _, err = proc.communicate(timeout=120)
        finally:
            proc.kill()
    assert proc.returncode == 130
    assert err.strip().splitlines() == ["fedlgr: interrupted"], err


def test_a_robots_state_folder_is_made_private_whatever_the_umask(tmp_path):
    """Issue 50's fault sweep, case 7: --state-dir and --cache-dir were made 0755 under umask
    022 (their files were 0600): each folder fedlgr makes for them is 0700."""
    from fedlgr.shell.cli.deploy.launch import own_folder

    old = os.umask(0o022)
    try:
        made = own_folder(tmp_path / "robot" / "state", "--state-dir", make=True)
    finally:
        os.umask(old)
    assert made == tmp_path / "robot" / "state"
    for folder in (made, made.parent):
        assert stat.S_IMODE(folder.stat().st_mode) == 0o700, folder


def test_a_serverapps_fedlgr_error_is_logged_in_one_line_by_flower(caplog):
    """Issue 50's fault sweep, cases 5 and 6: Flower's run_serverapp logs the ServerApp's
    exception with exc_info, and the stream showed ~20 lines of traceback before the one-line
    error. Through Flower's own logger, a FedlgrError is one line; another error keeps its
    traceback."""
    from flwr.common.logger import log

    import fedlgr.shell.deploy.flower.server_app  # noqa: F401 - installs the filter

    def logged(err: Exception) -> str:
        caplog.clear()
        try:
            raise err
        except Exception as ex:
            log(logging.ERROR, "%s raised an exception", "ServerApp", exc_info=ex)
        return caplog.text

    one = logged(FedlgrError("round 2: SecAgg+ gave no sum (50% gone)\nsecond line"))
    assert "ServerApp raised an exception: round 2: SecAgg+ gave no sum (50% gone)" in one
    assert "Traceback" not in one and "second line" not in one
    assert "Traceback" in logged(ValueError("a bug"))
