"""Secrets stay secret (issue 20): private keys are 0600 from their first byte and never
written through a symbolic link; configs resolve no environment variable but FEDLGR_*
and their ``${...}`` errors are one line; a robot reads the server's config as data."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import textwrap

import pytest
import yaml

from fedlgr.errors import ConfigError, FedlgrError
from fedlgr.shell.cli import main
from fedlgr.shell.config import load_config, to_plain, to_yaml
from fedlgr.shell.deploy.credentials import make_node_key
from fedlgr.shell.deploy.flower import robot as robot_module
from fedlgr.shell.deploy.flower.service import reply_error
from tests.support.runs import FAST

# ---------------------------------------------------------------------- private keys

# Writes the credentials into a watched folder and prints the mode each file had when it
# was first seen. Two watchers: a thread polling the folder in a tight loop, and an audit
# hook that looks at the folder at every audited call of the process - among them the
# chmod that would tighten a key written with the umask's mode, so a key that is ever
# readable by others is seen so, not by chance.
WATCH = textwrap.dedent(
    """
    import json, os, sys, threading
    from pathlib import Path

    folder = Path(sys.argv[1])
    folder.mkdir()
    first, busy, done = {}, threading.local(), threading.Event()

    def look():
        if getattr(busy, "on", False):
            return
        busy.on = True
        try:
            for name in os.listdir(folder):
                if name not in first:
                    try:
                        first.setdefault(name, os.lstat(folder / name).st_mode & 0o777)
                    except FileNotFoundError:
                        pass
        finally:
            busy.on = False

    def poll():
        while not done.is_set():
            look()

    sys.addaudithook(lambda event, args: look())
    os.umask(0o022)
    from fedlgr.shell.deploy.credentials import make_certificates, make_node_key

    watcher = threading.Thread(target=poll)
    watcher.start()
    make_certificates(folder)
    make_node_key(folder, "robot0")
    done.set()
    watcher.join()
    look()
    print(json.dumps(first))
    """
)


def test_private_keys_are_0600_from_their_first_byte(tmp_path):
    done = subprocess.run(
        [sys.executable, "-c", WATCH, str(tmp_path / "creds")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    first = json.loads(done.stdout)
    assert set(first) == {"ca.pem", "ca.key", "server.pem", "server.key", "robot0", "robot0.pub"}
    for name in ("ca.key", "server.key", "robot0"):
        assert first[name] == 0o600, (name, oct(first[name]))
        assert (tmp_path / "creds" / name).stat().st_mode & 0o777 == 0o600


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_a_symbolic_link_at_a_credential_path_is_refused_even_with_force(tmp_path, capsys):
    keys, target = tmp_path / "keys", tmp_path / "planted"
    keys.mkdir()
    (keys / "robot0").symlink_to(target)  # dangling: Path.exists() is False
    for force in ([], ["--force"]):
        assert main(["deploy", "node-key", str(keys), "robot0", *force]) == 1
        line = one_line_error(capsys)
        assert str(keys / "robot0") in line and "symbolic link" in line
        assert not target.exists() and not (keys / "robot0.pub").exists()

    creds = tmp_path / "creds"
    creds.mkdir()
    (creds / "ca.pem").symlink_to(target)  # a public file follows no link either
    assert main(["deploy", "certs", str(creds)]) == 1
    assert str(creds / "ca.pem") in one_line_error(capsys)
    assert not target.exists() and sorted(p.name for p in creds.iterdir()) == ["ca.pem"]
    (creds / "ca.pem").unlink()

    victim = tmp_path / "victim.txt"  # a link to an existing file: its bytes stay
    victim.write_text("mine")
    (creds / "server.key").symlink_to(victim)
    assert main(["deploy", "certs", str(creds), "--force"]) == 1
    assert str(creds / "server.key") in one_line_error(capsys)
    assert victim.read_text() == "mine"
    assert sorted(p.name for p in creds.iterdir()) == ["server.key"]  # nothing half-made


def test_an_existing_key_is_kept_unless_forced_and_force_writes_a_new_file(tmp_path, capsys):
    assert main(["deploy", "node-key", str(tmp_path), "robot0"]) == 0
    key = tmp_path / "robot0"
    old = key.read_bytes()
    os.link(key, tmp_path / "elsewhere")  # another name of the same file
    assert main(["deploy", "node-key", str(tmp_path), "robot0"]) == 1
    assert "--force" in one_line_error(capsys) and key.read_bytes() == old
    assert main(["deploy", "node-key", str(tmp_path), "robot0", "--force"]) == 0
    assert key.read_bytes() != old and key.stat().st_mode & 0o777 == 0o600
    assert (tmp_path / "elsewhere").read_bytes() == old  # replaced, not written into

    creds = tmp_path / "creds"
    assert main(["deploy", "certs", str(creds)]) == 0
    ca_key = (creds / "ca.key").read_bytes()
    assert main(["deploy", "certs", str(creds), "--force"]) == 0
    assert (creds / "ca.key").read_bytes() != ca_key
    assert (creds / "ca.key").stat().st_mode & 0o777 == 0o600


# ---------------------------------------------------------------------- configs


def error(overrides, path=None) -> str:
    with pytest.raises(ConfigError) as caught:
        load_config(path, overrides)
    message = str(caught.value)
    assert "\n" not in message
    return message


def test_configs_resolve_no_environment_variable_but_fedlgr_ones(monkeypatch):
    monkeypatch.setenv("SECRET", "hunter2")
    monkeypatch.setenv("FEDLGR_RUN", "from-env")
    for value in (
        "${oc.env:SECRET}",
        "${oc.env:HOME}",
        "x-${oc.env:SECRET,none}",
        "${oc.decode:${oc.env:SECRET}}",
        "${oc.create:abc}",
        "${oc.select:tracking.experiment}",
        "${oc.env:FEDLGR_${oc.env:SECRET}}",
    ):
        message = error([f"tracking.run_name={value}"])
        assert message.startswith("command line: tracking.run_name="), message
        assert "FEDLGR_" in message and "hunter2" not in message

    def run_name(value: str) -> str:
        return load_config(None, [f"tracking.run_name={value}"]).tracking.run_name

    assert run_name("${oc.env:FEDLGR_RUN}") == "from-env"
    assert run_name("${oc.env:FEDLGR_UNSET,fallback}") == "fallback"
    assert run_name("${tracking.experiment}-${data.clients}") == "fedlgr-2"  # references
    assert run_name("\\${oc.env:SECRET}") == "${oc.env:SECRET}"  # escaped: a literal


def test_interpolation_errors_are_one_line_naming_the_setting_and_its_layer(tmp_path):
    conf = tmp_path / "conf.yaml"
    for value, says in (
        ("${nope}", "nope"),
        ("${tracking.experiment_x}", "experiment_x"),
        ("${tracking.run_name}", "Recursive"),
        ("${oc.env:FEDLGR_UNSET_FOR_TEST}", "FEDLGR_UNSET_FOR_TEST"),
        ("${unknown_resolver:x}", "FEDLGR_"),
    ):
        conf.write_text(yaml.safe_dump({"tracking": {"run_name": value}}))
        message = error([], conf)
        assert message.startswith(f"{conf}: tracking.run_name="), message
        assert says in message, message
    conf.write_text("federated:\n  rounds: ${tracking.experiment}\n")
    assert error([], conf).startswith(f"{conf}: federated.rounds=")  # a string for an int
    assert "command line: tracking.run_name=" in error(
        ["tracking.run_name=${tracking.experiment}", "tracking.experiment=${tracking.run_name}"]
    )
    assert error(["data.tasks=[{name: ${x}"]).startswith("command line: 'data.tasks=")
    conf.write_text("includes: ['${oc.env:FEDLGR_CONF}']\n")
    assert error([], conf).startswith(f"{conf}: includes:")


def test_the_cli_prints_an_interpolation_error_as_one_line(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "fedlgr", "run", "tracking.run_name=${nope}", "--print-config"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert done.returncode == 1 and done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fedlgr: error: command line: "), lines
    assert "tracking.run_name" in lines[0] and "nope" in lines[0]


# ---------------------------------------------------------------------- the robot


@pytest.fixture
def built(monkeypatch):
    """``robot()`` builds the robot's config and hands it to this instead of a Robot
    (which would import torch and read the data)."""
    monkeypatch.setattr(robot_module, "_robots", {})
    monkeypatch.setattr(robot_module, "Robot", lambda config, client, folder, **_: config)


def server_yaml(**sections) -> str:
    """The ServerApp's message config (``to_yaml``), with ``sections`` merged in."""
    settings = to_plain(load_config(FAST))
    for name, values in sections.items():
        settings[name] = (
            {**settings.get(name, {}), **values} if isinstance(values, dict) else values
        )
    return yaml.safe_dump(settings)


def node(tmp_path, **extra) -> dict:
    data = tmp_path / "robot-data"
    data.mkdir(exist_ok=True)
    return {"data-path": str(data), "client": 0, "state-dir": str(tmp_path / "state"), **extra}


def test_a_robot_resolves_nothing_the_server_sends(tmp_path, monkeypatch, built):
    monkeypatch.setenv("ROBOT_SECRET", "s3cr3t-value")
    for run_id, sent in enumerate(
        ({"modality": "${oc.env:ROBOT_SECRET}"}, {"partition": "${data.path}"})
    ):
        with pytest.raises(FedlgrError) as caught:
            robot_module.robot(run_id, node(tmp_path), server_yaml(data=sent))
        message = str(caught.value)
        assert f"data.{next(iter(sent))}" in message and "${" in message
        assert "s3cr3t" not in message and str(tmp_path) not in message
    # what the service tells the server of any failure: one line
    assert reply_error(ValueError("first\nsecond: s3cr3t-value")) == "ValueError: first"


def test_a_robot_refuses_a_slot_or_a_config_it_cannot_take_before_writing_anything(tmp_path, built):
    """A slot outside the run's clients, and a config nested thousands of levels deep (a
    RecursionError in the YAML parser), are one line each, and the run's state folder is
    not created."""
    with pytest.raises(FedlgrError, match=r"client=-1: the run has data.clients=2 \(clients"):
        robot_module.robot("12346", node(tmp_path), server_yaml(), slot=-1)
    deep = "data:\n" + "".join(f"{'  ' * (i + 1)}k{i}:\n" for i in range(500))
    for sent in (deep, "data: " + "[" * 3000 + "]" * 3000):
        with pytest.raises(FedlgrError, match="the server's config: nested too deeply"):
            robot_module.robot("12347", node(tmp_path), sent)
    assert not (tmp_path / "state").exists()


def test_a_robot_reads_no_file_the_server_names(tmp_path, built):
    private = tmp_path / "robot-private.yaml"
    private.write_text("robot_private_setting_name: 1\n")
    sent = server_yaml(includes=[str(private)])
    with pytest.raises(FedlgrError) as caught:
        robot_module.robot(1, node(tmp_path), sent)
    assert "includes" in str(caught.value)
    assert "robot_private_setting_name" not in str(caught.value)


def test_a_robots_paths_are_its_supernodes_never_the_servers(tmp_path, monkeypatch, built):
    monkeypatch.setenv("FEDLGR_CACHE_DIR", str(tmp_path / "robot-cache"))
    server = "/srv/server-chosen"
    sent = server_yaml(
        data={"path": f"{server}/data", "cache_dir": f"{server}/cache"},
        model={"weights": f"{server}/root.pt"},
        tracking={"uri": f"sqlite:///{server}/mlflow.db", "checkpoint_dir": f"{server}/ckpt"},
    )
    weights = tmp_path / "robot-root.pt"
    config = robot_module.robot(1, node(tmp_path, weights=str(weights)), sent)
    assert str(config.data.path) == str(tmp_path / "robot-data")
    assert config.data.cache_dir == tmp_path / "robot-cache"  # the robot's default
    assert config.model.weights == str(weights)
    assert config.tracking.uri is None and config.tracking.checkpoint_dir is None
    assert server not in to_yaml(config)
    # everything else is the server's
    expected = to_plain(load_config(FAST))
    for section, key in (("data", "path"), ("data", "cache_dir"), ("model", "weights")):
        expected[section].pop(key)
    got = to_plain(config)
    for section, key in (("data", "path"), ("data", "cache_dir"), ("model", "weights")):
        got[section].pop(key)
    assert {**got, "tracking": None} == {**expected, "tracking": None}

    chosen = tmp_path / "node-cache"
    config = robot_module.robot(
        2, node(tmp_path, weights=str(weights), **{"cache-dir": str(chosen)}), sent
    )
    assert config.data.cache_dir == chosen
    with pytest.raises(FedlgrError, match="--weights"):  # a file only the server has
        robot_module.robot(3, node(tmp_path), sent)


@pytest.mark.parametrize(
    ("option", "said"),
    [
        (["--days", "-5"], "--days -5: certificates must be valid for 1 to 3650 days"),
        (["--days", "0"], "--days 0: certificates must be valid for 1 to 3650 days"),
        (["--days", "99999999"], "--days 99999999: certificates must be valid for 1 to 3650"),
        (["--host", ""], "--host '': not an IP address or a DNS name"),
        (["--host", "bad host!"], "--host 'bad host!': not an IP address or a DNS name"),
        (["--host", "a" * 64 + ".lan"], "not an IP address or a DNS name"),
        (["--host", "999.1.1.1"], "--host '999.1.1.1': not an IP address or a DNS name"),
        (["--host", "robot.example."], "no trailing dot"),
    ],
)
def test_certificates_no_robot_could_use_are_refused_before_anything_is_written(
    tmp_path, capsys, option, said
):
    folder = tmp_path / "creds"
    assert main(["deploy", "certs", str(folder), *option]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and said in err, err
    assert not folder.exists()


def test_the_credentials_folder_is_private_under_any_umask(tmp_path):
    """Found by issue 20's fourth fault sweep."""
    old = os.umask(0)
    try:
        make_node_key(tmp_path / "creds", "robot0")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "creds").stat().st_mode) == 0o700


# ------------------------------------------------------------- private state, by mode


def test_private_state_is_0600_in_0700_folders_under_umask_022(tmp_path):
    """Issue 50's fault sweep: under umask 022 a robot's ``run-*/client-N.ckpt``, a run's
    ``round-*.ckpt`` and the idle clients' spill files were 0644 (every client's model, a
    robot's private top, optimiser and CL memories, readable by any user)."""
    import torch

    from fedlgr.core.client.idle import IdleStates
    from fedlgr.shell.run import checkpoint as ckpt

    state = {"model": {"top.w": torch.ones(3)}, "optimizer": {}}
    old = os.umask(0o022)
    try:
        # a temporary an older fedlgr left 0644 (a kill mid-write) is written 0600
        (tmp_path / "robot" / "run-abc").mkdir(parents=True, mode=0o700)
        (tmp_path / "robot" / "run-abc" / ".client-1.ckpt.tmp").write_bytes(b"old")
        robot = ckpt.write(tmp_path / "robot" / "run-abc" / "client-1.ckpt", {"client": state})
        run = ckpt.save(None, tmp_path / "checkpoints" / "run1", 1, {"clients": {0: state}}, 2)
        idle = IdleStates(budget=0, folder=tmp_path / "spill" / ".idle-clients-x")
        idle.put(3, state, set())
    finally:
        os.umask(old)
    spilled = tmp_path / "spill" / ".idle-clients-x" / "client-3.pt"
    for path in (robot, run, spilled):
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
        assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700, path.parent
    assert torch.equal(idle.get(3)["model"]["top.w"], torch.ones(3))  # and read back


def test_a_link_planted_at_a_checkpoints_temporary_name_is_not_written_through(tmp_path):
    """The temporary a checkpoint is written to first is opened without following a link."""
    from fedlgr.shell.run import checkpoint as ckpt

    target = tmp_path / "elsewhere.txt"
    target.write_text("kept")
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / ".client-1.ckpt.tmp").symlink_to(target)
    with pytest.raises(OSError):
        ckpt.write(folder / "client-1.ckpt", {"client": {}})
    assert target.read_text() == "kept" and not (folder / "client-1.ckpt").exists()


def test_tokens_in_a_tracking_uri_are_masked_like_passwords(capsys):
    """Issue 50's fault sweep: ``?access_token=`` and an HTTP URI's bare ``token@`` were
    printed by ``deploy run --print-command`` and would have travelled as passwords did."""
    from fedlgr.shell.tracking.uri import mask_password, masked_text, masked_uris

    cases = {
        "https://ghp_T0ken@mlflow.lab/": "https://***@mlflow.lab/",
        "http://127.0.0.1:5000/?access_token=T0ken&x=1": "http://127.0.0.1:5000/?access_token=***&x=1",
        "https://h/?api_key=K3y&client_secret=S3c&run=3": (
            "https://h/?api_key=***&client_secret=***&run=3"
        ),
        "https://ghp_T0ken:x-oauth-basic@mlflow.lab/": "https://***@mlflow.lab/",
        "https://ghp_T0ken:@mlflow.lab/": "https://***@mlflow.lab/",
        "postgresql://me@db/mlflow": "postgresql://me@db/mlflow",  # a user name, no secret
        # libpq's sslkey and MySQL's ssl_key are file paths, not secrets
        "postgresql://me@db/x?sslmode=verify-full&sslkey=/k/client.key": (
            "postgresql://me@db/x?sslmode=verify-full&sslkey=/k/client.key"
        ),
        "postgresql://me:pw@db/x?sslpassword=q": "postgresql://me:***@db/x?sslpassword=***",
    }
    assert {uri: mask_password(uri) for uri in cases} == cases
    uri = "https://ghp_T0ken@mlflow.lab/"
    assert (
        masked_text("no answer from ghp_T0ken@mlflow.lab", uri) == "no answer from ***@mlflow.lab"
    )
    assert masked_uris("see https://ghp_T0ken@mlflow.lab/x") == "see https://***@mlflow.lab/x"
    colon = "https://ghp_T0ken:x-oauth-basic@mlflow.lab/"
    assert masked_text("no answer (ghp_T0ken)", colon) == "no answer (***)"
    assert main(["deploy", "run", str(FAST), f"tracking.uri={uri}", "--print-command"]) == 1
    err = capsys.readouterr().err
    assert "tracking.uri=https://***@mlflow.lab/: a password or token on the command line" in err
    assert "T0ken" not in err and "$MLFLOW_TRACKING_TOKEN" in err


def test_the_superlinks_database_is_0600_before_flower_opens_it(tmp_path):
    """Every run's config and the fleet's state: made 0600 whatever the umask, and an older
    database (and its journals, whose mode SQLite copies from it) tightened; the review of
    issue 50's fix found an existing 0644 database kept 0644, -wal and -shm with it."""
    from fedlgr.shell.cli.deploy.superlink import _database

    old = os.umask(0o022)
    try:
        fresh = tmp_path / "fresh.db"
        assert _database(fresh, make=False) == ["--database", str(fresh)]
        assert not fresh.exists()  # --print-command writes nothing
        _database(fresh)
        older = tmp_path / "link.db"
        for path in (older, tmp_path / "link.db-wal", tmp_path / "link.db-shm"):
            path.write_bytes(b"")
        _database(older)
    finally:
        os.umask(old)
    made = [fresh, older, tmp_path / "link.db-wal", tmp_path / "link.db-shm"]
    assert {stat.S_IMODE(p.stat().st_mode) for p in made} == {0o600}
