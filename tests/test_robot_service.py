"""A robot between Flower messages: the robot service (``fedlgr.shell.deploy.flower.service``)
as a real process - a start-up probe is not logged as a failure, SIGTERM leaves no stale
pid file or socket - and the robot's data, its own or its slot's shard."""

from __future__ import annotations

import dataclasses
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from fedlgr.shell.config import load_config
from fedlgr.shell.deploy.flower import service


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
