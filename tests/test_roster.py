"""The federation's roster (``fedlgr.shell.deploy.roster``): ``fedlgr deploy node-key`` adds each
robot with its slot and public key, the ServerApp finds a node's robot by the key Flower
authenticated it with (Flower keeps it as PEM), and a broken roster is refused by name."""

from __future__ import annotations

import pytest
import yaml
from cryptography.hazmat.primitives import serialization

from fedlgr.errors import FedlgrError
from fedlgr.shell.cli import main
from fedlgr.shell.deploy.roster import Roster, roster_of


def pem(public_file) -> bytes:
    """The key as Flower's node list holds it (``public_key_to_bytes``: PEM SPKI)."""
    key = serialization.load_ssh_public_key(public_file.read_bytes())
    return key.public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )


def test_node_key_adds_each_robot_to_the_roster_in_the_lowest_free_slot(tmp_path, capsys):
    creds = tmp_path / "creds"
    for name in ("robot0", "robot1"):
        assert main(["deploy", "node-key", str(creds), name]) == 0
    assert main(["deploy", "node-key", str(creds), "spare", "--no-roster"]) == 0
    assert main(["deploy", "node-key", str(creds), "robot5", "--client", "5"]) == 0
    out = capsys.readouterr().out
    assert f"added robot1 (client 1) to {creds / 'roster.yaml'}" in out
    data = yaml.safe_load((creds / "roster.yaml").read_text())
    assert [(r["name"], r["client"]) for r in data["robots"]] == [
        ("robot0", 0),
        ("robot1", 1),
        ("robot5", 5),
    ]
    roster = Roster.read(creds / "roster.yaml")
    assert str(roster.member(pem(creds / "robot1.pub"))) == "robot1 (client 1)"
    assert roster.member((creds / "robot0.pub").read_text()).client == 0  # OpenSSH too
    assert roster.member(pem(creds / "spare.pub")) is None  # a key it does not list
    assert roster.member(b"") is None and roster.member(b"not a key") is None
    # The next robot takes the lowest free slot; a slot held is refused by name.
    assert main(["deploy", "node-key", str(creds), "robot2"]) == 0
    assert Roster.read(creds / "roster.yaml").member(pem(creds / "robot2.pub")).client == 2
    assert main(["deploy", "node-key", str(creds), "robot9", "--client", "1"]) == 1
    err = capsys.readouterr().err
    assert "--client 1: robot1 (client 1) holds that slot" in err
    assert not (creds / "robot9").exists()  # refused before any key was written
    # A new key for a robot keeps its slot (--force), and replaces the old key.
    old = pem(creds / "robot1.pub")
    assert main(["deploy", "node-key", str(creds), "robot1", "--force"]) == 0
    roster = Roster.read(creds / "roster.yaml")
    assert roster.member(old) is None
    assert roster.member(pem(creds / "robot1.pub")).client == 1


@pytest.mark.parametrize("name", ["roster.yaml", "ca.key", "server.pem", "robot0.pub"])
@pytest.mark.parametrize("roster", [[], ["--no-roster"]])
def test_a_robot_named_after_a_file_of_the_folder_is_refused(tmp_path, capsys, name, roster):
    """NAME and NAME.pub are written beside the roster, the certificates and the other
    robots' public keys: a robot named ``roster.yaml`` lost its private key to the roster
    (which was then written over it), one named ``robot0.pub`` would replace robot0's key."""
    creds = tmp_path / "creds"
    assert main(["deploy", "node-key", str(creds), "robot0"]) == 0
    before = {p.name: p.read_bytes() for p in creds.iterdir()}
    for force in ([], ["--force"]):
        assert main(["deploy", "node-key", str(creds), name, *roster, *force]) == 1
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"fedlgr: error: node-key NAME {name!r}: the name of a file")
        assert {p.name: p.read_bytes() for p in creds.iterdir()} == before  # nothing written


def test_a_name_too_long_or_a_roster_nested_too_deep_is_one_line(tmp_path, capsys):
    """A 300-character name (its NAME.pub longer than a file name may be) and a roster of
    3000 nested lists gave tracebacks (OSError, RecursionError)."""
    assert main(["deploy", "node-key", str(tmp_path / "a"), "r" * 300]) == 1
    said = "fedlgr: error: node-key NAME rrrrrrrrrrrrrrrrrrrr...: at most 100 characters"
    assert capsys.readouterr().err.strip() == said
    roster = tmp_path / "b" / "roster.yaml"
    roster.parent.mkdir()
    roster.write_text("robots: " + "[" * 3000 + "]" * 3000)
    assert main(["deploy", "node-key", str(roster.parent), "robot0"]) == 1
    said = f"fedlgr: error: roster {roster}: nested too deeply to be a roster"
    assert capsys.readouterr().err.strip() == said
    assert sorted(p.name for p in roster.parent.iterdir()) == ["roster.yaml"]


def test_a_run_needs_a_roster_with_a_robot_for_every_client(tmp_path):
    from fedlgr.shell.config import load_config

    creds = tmp_path / "creds"
    for name in ("robot0", "robot2"):
        assert main(["deploy", "node-key", str(creds), name, "--client", name[-1]]) == 0
    path = creds / "roster.yaml"
    with pytest.raises(FedlgrError, match=r"deploy\.roster is not set"):
        roster_of(load_config(None, ["data.clients=2"]))
    with pytest.raises(FedlgrError) as err:
        roster_of(load_config(None, ["data.clients=3", f"deploy.roster={path}"]))
    assert str(err.value) == (
        f"roster {path}: no robot for client 1 of data.clients=3 (fedlgr deploy node-key "
        "DIR NAME --client K adds one)"
    )
    assert roster_of(load_config(None, ["data.clients=1", f"deploy.roster={path}"])) is not None
    assert roster_of(load_config(None, ["deploy.roster=none"])) is None


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("robots: [", "not valid YAML"),
        ("robots: 3\n", "expected 'robots:' and a list of robots"),
        ("robots:\n- name: a\n  client: 0\n", "robot 1: expected name, client and key"),
        ("robots:\n- {name: a, client: 0, key: x, scenes: 0}\n", "robot 1 (a): scenes must be"),
        ("robots:\n- {name: a, client: 0, key: x, host: h}\n", "(and scenes, optional)"),
        ("robots:\n- {name: a, client: -1, key: x}\n", "robot 1 (a): client must be an integer"),
        ("robots:\n- {name: a, client: 0, key: nope}\n", "robot 1 (a): key is not a public key"),
    ],
)
def test_a_broken_roster_is_refused_naming_the_file_and_robot(tmp_path, text, message):
    path = tmp_path / "roster.yaml"
    path.write_text(text)
    with pytest.raises(FedlgrError) as err:
        Roster.read(path)
    assert str(err.value).startswith(f"roster {path}: ") and message in str(err.value)


def test_two_robots_with_one_key_or_one_slot_are_refused(tmp_path):
    creds = tmp_path / "creds"
    assert main(["deploy", "node-key", str(creds), "robot0"]) == 0
    key = (creds / "robot0.pub").read_text().strip()
    path = tmp_path / "roster.yaml"
    path.write_text(
        f"robots:\n- {{name: a, client: 0, key: {key}}}\n- {{name: b, client: 1, key: {key}}}\n"
    )
    with pytest.raises(FedlgrError, match=r"a \(client 0\) and b \(client 1\) hold the same key"):
        Roster.read(path)
    path.write_text(
        f"robots:\n- {{name: a, client: 0, key: {key}}}\n- {{name: b, client: 0, key: {key}}}\n"
    )
    with pytest.raises(FedlgrError, match="share a client"):
        Roster.read(path)
