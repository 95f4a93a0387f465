"""The tracking store's password on a real Flower federation (``fedlgr deploy``: a SuperLink
with TLS, its database in a file, and two SuperNodes) logging to a real PostgreSQL server
(tests/support/postgres.py). The password lives on the SuperLink's machine alone: in the
``PGPASSFILE`` of ``fedlgr deploy superlink`` (libpq's ``~/.pgpass``), which its ServerApp
inherits. Robot 1 reaches the SuperLink through a TLS relay (tests/support/relay.py) that
keeps what the robot really received: its run's config and every message. The password is
in none of what ``fedlgr deploy run`` printed, the SuperLink's database or what the robot
received, and no tracking URI reaches the robot; a password on the command line is refused
before anything is printed or submitted."""

from __future__ import annotations

import os
import stat

import mlflow
import pytest

from tests.support.flower import Federation
from tests.support.postgres import USER, missing, postgres_server
from tests.support.relay import TlsRelay
from tests.support.runs import FAST

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(missing() is not None, reason=missing() or ""),
]

DATABASE = "mlflow"


@pytest.fixture(scope="module")
def postgres():
    with postgres_server() as server:
        server.create_database(DATABASE)
        yield server


@pytest.fixture(scope="module")
def federation(tmp_path_factory, synth_dir, postgres):
    fed = Federation(tmp_path_factory.mktemp("flower-secrets"))
    # The SuperLink machine's ~/.pgpass (mode 0600, or libpq ignores it), for its processes only.
    pgpass = fed.folder / "superlink-pgpass"
    with os.fdopen(os.open(pgpass, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600), "w") as f:
        f.write(f"127.0.0.1:{postgres.port}:{DATABASE}:{USER}:{postgres.password}\n")
    fed.database = fed.folder / "superlink.db"
    relay = None
    try:
        fed.start_superlink(["--database", str(fed.database)], env={"PGPASSFILE": str(pgpass)})
        fed.keys = {name: fed.node_key(name) for name in ("robot0", "robot1")}
        relay = fed.relay = TlsRelay(fed.port, fed.creds)
        fed.start_supernode("robot0", fed.keys["robot0"], 0, synth_dir)
        fed.start_supernode("robot1", fed.keys["robot1"], 1, synth_dir, port=relay.port)
        yield fed
    finally:
        fed.stop()
        if relay is not None:
            relay.stop()
    assert not fed.leftovers()


def superlink_bytes(federation) -> bytes:
    """The SuperLink's database, every file of it (its journal too), as stored."""
    files = sorted(federation.database.parent.glob(federation.database.name + "*"))
    assert files, "no SuperLink database"
    return b"".join(path.read_bytes() for path in files)


def test_a_password_in_an_override_is_refused_before_anything_is_printed_or_submitted(
    federation, synth_dir, postgres
):
    """Issue 37, Deliver 6: ``tracking.uri=postgresql://fedlgr:PASSWORD@...`` ran: the password
    stood in the printed ``flwr run`` command, in the SuperLink's database and in every
    robot's run config."""
    uri = postgres.uri(DATABASE)
    overrides = [f"data.path={synth_dir}", f"deploy.roster={federation.roster}"]
    overrides += [f"tracking.uri={uri}", "tracking.run_name=refused"]
    proc = federation.run(FAST, overrides)
    out, _ = proc.communicate(timeout=600)
    assert proc.returncode == 1, out[-3000:]
    [line] = out.strip().splitlines()
    masked = f"postgresql://{USER}:***@127.0.0.1:{postgres.port}/{DATABASE}"
    said = f"fedlgr: error: tracking.uri={masked}: a password or token on the command line"
    assert line.startswith(said)
    assert "~/.pgpass" in line and postgres.password not in line
    assert postgres.password.encode() not in superlink_bytes(federation)
    assert b"tracking.run_name=refused" not in superlink_bytes(federation)  # never submitted
    assert postgres.password.encode() not in federation.relay.bodies()


def test_the_password_stays_on_the_superlinks_machine_and_no_tracking_uri_reaches_a_robot(
    federation, synth_dir, postgres
):
    """The run logs to PostgreSQL with the password from the SuperLink's ``PGPASSFILE``
    (``tracking.uri`` without one, in a config file on the SuperLink's machine). Issue 37,
    Deliver 6: the robots received ``tracking.uri`` (host, port, user, database) in the config
    text of every message."""
    config = federation.folder / "superlink-config.yaml"
    uri = f"postgresql://{USER}@127.0.0.1:{postgres.port}/{DATABASE}"
    config.write_text(f"includes: [{FAST}]\ntracking:\n  uri: {uri}\n")
    overrides = [f"data.path={synth_dir}", f"deploy.roster={federation.roster}"]
    overrides += ["method=FedRootAvg", "tracking.run_name=secrets"]
    proc = federation.run(config, overrides)
    out, _ = proc.communicate(timeout=900)
    assert proc.returncode == 0, out[-3000:]
    client = mlflow.MlflowClient(postgres.uri(DATABASE))
    experiment = client.get_experiment_by_name("fedlgr-debug")
    [run] = client.search_runs([experiment.experiment_id], "attributes.run_name = 'secrets'")
    assert run.info.status == "FINISHED" and run.data.tags["runtime"] == "flower"
    assert "round 1, evaluate: 2 of 2 replies" in out
    secret = postgres.password
    # (1) what fedlgr deploy run printed: the flwr command and the ServerApp's log
    assert "flwr run" in out and secret not in out
    # (2) the SuperLink's database: it keeps the run's config, without the password
    stored = superlink_bytes(federation)
    assert b"tracking.run_name=secrets" in stored and secret.encode() not in stored
    # (3) what robot 1 received: its run config (the overrides) and the config text in
    # every message - no password, no tracking URI at all
    received = federation.relay.bodies()
    assert b"tracking.run_name=secrets" in received  # the run's config
    assert b"experiment: fedlgr-debug" in received  # the config text of the messages
    assert secret.encode() not in received
    assert b"postgresql" not in received and f":{postgres.port}".encode() not in received
    # (4) private by mode, whatever the umask: each robot's state (its private top, optimiser
    # and CL memories), in a folder of its own, and the SuperLink's database; issue 50's fault
    # sweep found them 0644 in 0755 folders under umask 022
    robots = [federation.robot_dir(name) for name in ("robot0", "robot1")]
    states = [p for robot in robots for p in robot.glob("run-*/client-*.ckpt")]
    assert len(states) >= 2, states
    assert {stat.S_IMODE(p.parent.stat().st_mode) for p in states} == {0o700}
    database = list(federation.database.parent.glob(federation.database.name + "*"))
    assert {stat.S_IMODE(p.stat().st_mode) for p in [*states, *database]} == {0o600}
