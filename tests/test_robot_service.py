"""A robot between Flower messages: the robot service (``fedlgr.shell.deploy.flower.service``)
as a real process - a start-up probe is not logged as a failure, SIGTERM leaves no stale
pid file or socket - and the robot's data, its own or its slot's shard. A server's message a
robot cannot trust (a run key that is a path, a malformed plan) is refused in one line,
and nothing is written outside its state folder or through a link."""

from __future__ import annotations

import dataclasses
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from flwr.app import ConfigRecord, RecordDict

from fedlgr.errors import FedlgrError
from fedlgr.shell.config import load_config
from fedlgr.shell.deploy.flower import robot, service, wire


@pytest.mark.slow
def test_sigterm_leaves_no_pid_file_or_socket_and_a_probe_is_not_an_error(tmp_path):
    folder = tmp_path / "robot"
    folder.mkdir()
    log = (folder / "robot.log").open("wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "fedlgr.shell.deploy.flower.service", str(folder), "600"],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    try:
        # What ClientApp's start() does: connect until the service listens, then close.
        service._connect(service.socket_path(folder), wait=120).close()
        assert (folder / "robot.pid").read_text() == str(proc.pid)
        assert service.socket_path(folder).exists()
        time.sleep(0.5)  # the service has taken the probe
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    text = (folder / "robot.log").read_text()
    assert "SIGTERM: leaving" in text
    assert "could not answer" not in text and "Traceback" not in text
    assert not (folder / "robot.pid").exists()
    assert not service.socket_path(folder).exists()


def test_a_robot_with_its_own_data_trains_and_scores_on_its_own_scenes(synth_dir, tmp_path):
    """``--own-data``: the robot's whole folder is its shard - its own train/test split by
    data.seed, the split of a one-client run - under the slot the roster gives it; without
    it, the robot takes its slot's shard of the whole dataset, as ``fedlgr run`` does."""
    from fedlgr.shell.data.dataset import load_scenes
    from fedlgr.shell.data.splits import make_split
    from fedlgr.shell.deploy.flower.robot import Robot
    from tests.support.runs import FAST

    config = load_config(FAST, [f"data.path={synth_dir}", "method=FedRootAvg"])
    scenes = load_scenes(config.data)
    one = make_split(scenes.table, dataclasses.replace(config.data, clients=1))
    full = make_split(scenes.table, config.data)

    own = Robot(config, 1, tmp_path / "own", own_data=True)
    [shard] = own.side.split.clients
    assert shard.client == 1 and own.client.index == 1
    assert np.array_equal(shard.train, one.clients[0].train)  # all its training scenes
    assert np.array_equal(own.side.split.test, one.test)  # scored on its own test scenes
    assert len(shard.train) + len(own.side.split.test) == len(scenes.table)

    shared = Robot(config, 1, tmp_path / "shard")
    assert np.array_equal(shared.side.split.clients[1].train, full.clients[1].train)
    assert len(full.clients[1].train) < len(shard.train)


def test_a_robot_restarted_on_other_data_says_so_before_it_answers(synth_dir, tmp_path):
    """A robot's private state is of the data it trained on: restarted with --data holding
    other ratings, it refuses to go on - naming the data, both digests and the state file -
    rather than train on the new data with the old state; back on its own data, it goes on."""
    import shutil

    from fedlgr.errors import FedlgrError
    from fedlgr.shell.deploy.flower.robot import Robot
    from tests.support.runs import FAST

    data = tmp_path / "data"
    shutil.copytree(synth_dir, data)
    config = load_config(FAST, [f"data.path={data}", "method=FedRootAvg"])
    robot = Robot(config, 1, tmp_path / "state")
    robot.answered, robot.reply = ["train", 1, -1], b"its reply"  # as after a message
    robot.save()
    table = next(data.glob("*.csv"))
    original = table.read_text()
    lines = original.splitlines(keepends=True)
    table.write_text("".join([*lines[:-2], lines[-1], lines[-2]]))  # two scenes swapped
    with pytest.raises(FedlgrError) as err:
        Robot(config, 1, tmp_path / "state")
    message = str(err.value)
    assert message.startswith(f"the data in --data {data} is not the data this robot's private")
    assert "client-1.ckpt was trained on (dataset digest " in message
    table.write_text(original)
    assert Robot(config, 1, tmp_path / "state").client.index == 1


def plan(run_key: str) -> RecordDict:
    return RecordDict({"plan": ConfigRecord({"round": 1, "run": run_key})})


@pytest.mark.parametrize("key", ["../../../escape", "/tmp/abs", "a/b", "..", "x" * 65, "r un"])
def test_a_robot_refuses_a_run_key_that_is_not_a_run_id_and_writes_nothing(tmp_path, key):
    """Found by issue 20's fourth fault sweep."""
    state = tmp_path / "robot" / "state"
    node = {"data-path": str(tmp_path), "state-dir": str(state), "client": 0}
    with pytest.raises(FedlgrError, match=r"is not a run id .* refused, nothing written"):
        robot.handle("train", 7, node, plan(key))
    assert not (tmp_path / "robot").exists() and not (tmp_path / "escape").exists()
    for good in ("4c1d3ad0f4be4dbe8c5e0a19b8c2f0d1", "18446744073709551615", "run_1-b"):
        assert wire.run_key(plan(good)) == good


def test_robot_refuses_a_path_as_a_run_id_however_it_is_reached(tmp_path):
    """The re-test reached robot.robot with a Flower run id that was a path (a string: a
    Flower run id is an integer, but nothing here may rely on it).
    Found by issue 20's fourth fault sweep."""
    state = tmp_path / "a" / "state"
    node = {"data-path": str(tmp_path), "state-dir": str(state), "client": 0}
    for run in ("../../../escape", "/tmp/abs"):
        with pytest.raises(FedlgrError, match="not a run id; refused, nothing written"):
            robot.robot(run, node, "{}", 0)
        with pytest.raises(FedlgrError, match="not a run id; refused, nothing written"):
            robot.handle("train", run, node, plan(""))
    assert not (tmp_path / "a").exists() and not (tmp_path / "escape").exists()


@pytest.mark.parametrize(
    ("content", "missing"),
    [
        (RecordDict({}), "KeyError: 'plan'"),
        (RecordDict({"plan": ConfigRecord({"round": 1, "client": "abc"})}), "ValueError"),
        (plan("r1"), "KeyError"),  # no config, no tensors
    ],
)
def test_a_malformed_message_is_one_line_to_the_server(tmp_path, content, missing):
    """Found by issue 20's fourth fault sweep."""
    node = {"data-path": str(tmp_path), "state-dir": str(tmp_path / "state"), "client": 0}
    with pytest.raises(FedlgrError, match="the server's train message is malformed") as err:
        robot.handle("train", 7, node, content)
    assert missing in str(err.value) and len(str(err.value).splitlines()) == 1


def test_the_robots_config_is_never_written_through_a_link(tmp_path, synth_dir):
    """A link planted at <state>/run-<id>/config.yaml is replaced, its target untouched.
    Found by issue 20's fourth fault sweep."""
    from fedlgr.shell.config import load_config, to_yaml

    state = tmp_path / "state"
    (state / "run-r1").mkdir(parents=True)
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    (state / "run-r1" / "config.yaml").symlink_to(victim)
    node = {"data-path": str(synth_dir), "state-dir": str(state), "client": 0}
    config = to_yaml(load_config(None, [f"data.path={synth_dir}"]))
    robot.robot("r1", node, config, 0)
    assert victim.read_text() == "precious"
    written = state / "run-r1" / "config.yaml"
    assert not written.is_symlink() and "method:" in written.read_text()
