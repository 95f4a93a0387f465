"""The cases of issue 20's fourth fault sweep that were not clean (273 cases on a4b5fc3):
a server-chosen run key that named a folder outside the robot's state folder, a store's
lock file created through a planted link, in-memory stores that kept nothing, ``data
synth`` with a negative seed, no bound on scenes and a half dataset left by an
interruption, a text file named as a config echoed into the error, and a credentials
folder made 0777 under umask 000."""

from __future__ import annotations

import contextlib
import os
import sqlite3
import stat
from pathlib import Path

import pytest
from flwr.app import ConfigRecord, RecordDict

from fedlgr.errors import ConfigError, FedlgrError
from fedlgr.shell.checks.stores import TrackingUnreachable, check_reachable
from fedlgr.shell.cli import main
from fedlgr.shell.config import load_config
from fedlgr.shell.data.synth import MAX_SCENES, synthesize
from fedlgr.shell.deploy.credentials import make_node_key
from fedlgr.shell.deploy.flower import robot, wire
from fedlgr.shell.sweep.storage import check_storage
from fedlgr.shell.tracking.store import StoreError, store_lock


def plan(run_key: str) -> RecordDict:
    return RecordDict({"plan": ConfigRecord({"round": 1, "run": run_key})})


@pytest.mark.parametrize("key", ["../../../escape", "/tmp/abs", "a/b", "..", "x" * 65, "r un"])
def test_a_robot_refuses_a_run_key_that_is_not_a_run_id_and_writes_nothing(tmp_path, key):
    state = tmp_path / "robot" / "state"
    node = {"data-path": str(tmp_path), "state-dir": str(state), "client": 0}
    with pytest.raises(FedlgrError, match=r"is not a run id .* refused, nothing written"):
        robot.handle("train", 7, node, plan(key))
    assert not (tmp_path / "robot").exists() and not (tmp_path / "escape").exists()
    for good in ("4c1d3ad0f4be4dbe8c5e0a19b8c2f0d1", "18446744073709551615", "run_1-b"):
        assert wire.run_key(plan(good)) == good


def test_a_stores_lock_file_is_never_created_through_a_link(tmp_path):
    target = tmp_path / "created-through-the-link"
    (tmp_path / "mlflow.db.lock").symlink_to(target)
    lock = store_lock(f"sqlite:///{tmp_path}/mlflow.db")
    with (
        pytest.raises(StoreError, match=r"its lock file .*mlflow\.db\.lock is a symbolic link"),
        lock,
    ):
        pass
    (tmp_path / "optuna.db.lock").symlink_to(target)
    with pytest.raises(FedlgrError, match=r"^--storage .*: its lock file .* symbolic link"):
        check_storage(f"sqlite:///{tmp_path}/optuna.db")
    assert not target.exists()


@pytest.mark.parametrize(
    "uri",
    [
        "sqlite://",
        "sqlite:///:memory:",
        "sqlite:///file::memory:?cache=shared&uri=true",
        "sqlite:///file:db?mode=memory&uri=true",
    ],
)
def test_in_memory_stores_are_refused_they_keep_nothing(uri):
    with pytest.raises(TrackingUnreachable, match="in-memory sqlite store keeps nothing"):
        check_reachable(uri)
    with pytest.raises(FedlgrError, match="in-memory sqlite database keeps nothing"):
        check_storage(uri)


def test_synth_refuses_a_seed_and_a_count_out_of_range_before_writing(tmp_path):
    for seed in (-1, 2**32):
        with pytest.raises(ConfigError, match=f"seed={seed}: seeds are 0 to 2\\*\\*32 - 1"):
            synthesize(tmp_path / "out", scenes=4, seed=seed, size=32)
    with pytest.raises(ConfigError, match="scenes=1000001: 1 to 1,000,000 scenes"):
        synthesize(tmp_path / "out", scenes=MAX_SCENES + 1, size=32)
    assert not (tmp_path / "out").exists()
    assert main(["data", "synth", "--out", str(tmp_path / "cli"), "--seed", "-1"]) == 1
    assert not (tmp_path / "cli").exists()


def test_an_interrupted_synth_leaves_no_half_dataset(tmp_path):
    def interrupt(done, total):
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        synthesize(tmp_path / "new", scenes=8, size=32, progress=interrupt)
    assert not (tmp_path / "new").exists()  # made by this call: removed
    kept = tmp_path / "kept"
    synthesize(kept, scenes=4, size=32)
    with pytest.raises(KeyboardInterrupt):
        synthesize(kept, scenes=8, size=32, force=True, progress=interrupt)
    assert not any(kept.iterdir())  # the old dataset went with --force; nothing half-made


def test_a_text_file_named_as_a_config_is_refused_without_its_text(tmp_path):
    secret = tmp_path / "notes.yaml"
    secret.write_text("root:x:0:0:root:/root:/bin/bash\ndaemon:x:1:1:the secret line\n")
    with pytest.raises(ConfigError) as err:
        load_config(secret, [])
    assert str(err.value) == (
        f"{secret}: not a config file: its top level is not `setting: value` lines "
        "(a setting name is letters, digits, _ and .)"
    )


def test_the_credentials_folder_is_private_under_any_umask(tmp_path):
    old = os.umask(0)
    try:
        make_node_key(tmp_path / "creds", "robot0")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "creds").stat().st_mode) == 0o700


def test_robot_refuses_a_path_as_a_run_id_however_it_is_reached(tmp_path):
    """The re-test reached robot.robot with a Flower run id that was a path (a string: a
    Flower run id is an integer, but nothing here may rely on it)."""
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
    node = {"data-path": str(tmp_path), "state-dir": str(tmp_path / "state"), "client": 0}
    with pytest.raises(FedlgrError, match="the server's train message is malformed") as err:
        robot.handle("train", 7, node, content)
    assert missing in str(err.value) and len(str(err.value).splitlines()) == 1


def test_data_show_refuses_its_bad_arguments_in_one_line(tmp_path, synth_dir, capsys):
    cases = {
        "--scenes 0": (["--scenes", "0", "--out", str(tmp_path / "s.png")], "--scenes 0"),
        "--seed -1": (["--seed", "-1", "--out", str(tmp_path / "s.png")], "--seed -1"),
        "a folder": (["--out", str(tmp_path)], "name the picture file"),
        "a .txt": (["--out", str(tmp_path / "s.txt")], "ending in .png or .jpg or .jpeg"),
    }
    for case, (args, said) in cases.items():
        assert main(["data", "show", str(synth_dir), *args]) == 1, case
        [line] = capsys.readouterr().err.strip().splitlines()
        assert line.startswith("fedlgr: error: --") and said in line, case


def test_a_text_file_named_as_a_sweep_is_refused_without_its_text(tmp_path, capsys):
    for text in ("API_KEY=sk-live-SECRET123\nDB_PASSWORD=hunter2\n", "_apt:*:20228:0:99999:7:::\n"):
        sweep = tmp_path / "sweep.yaml"
        sweep.write_text(text)
        assert main(["sweep", str(sweep), "--storage", f"sqlite:///{tmp_path}/o.db"]) == 1
        err = capsys.readouterr().err
        assert "SECRET" not in err and "hunter2" not in err and "20228" not in err
        assert f"fedlgr: error: {sweep}: " in err


def test_the_robots_config_is_never_written_through_a_link(tmp_path, synth_dir):
    """A link planted at <state>/run-<id>/config.yaml is replaced, its target untouched."""
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


@pytest.mark.parametrize("setting", ["train.betas=[1.5,0.9]", "federated.opt.betas=[0.9,1.0]"])
def test_adams_decay_rates_are_checked_with_the_config(setting):
    """The fifth sweep: train.betas=[1.5,0.9] failed inside torch's Adam after 13 s."""
    with pytest.raises(ConfigError, match=r"betas=\[.*\]: two decay rates, each in \[0, 1\)"):
        load_config(None, [setting])


def test_a_symbolic_link_that_loops_is_one_line(tmp_path, synth_dir, capsys):
    """The seventh fault sweep (v27): a config path that is a looping link gave Python
    3.11's ``RuntimeError: Symlink loop from ...`` traceback; a looping checkpoint folder
    too, and no run was started for either."""
    (tmp_path / "a.yaml").symlink_to(tmp_path / "b.yaml")
    (tmp_path / "b.yaml").symlink_to(tmp_path / "a.yaml")
    assert main(["run", str(tmp_path / "a.yaml"), "--print-config"]) == 1
    said = f"fedlgr: error: {tmp_path / 'a.yaml'}: a symbolic link that loops"
    assert capsys.readouterr().err.strip() == said
    store = tmp_path / "mlflow.db"
    argv = [
        "run",
        "debug/tiny",
        f"data.path={synth_dir}",
        f"tracking.checkpoint_dir={tmp_path / 'a.yaml'}",
    ]
    assert main([*argv, "--tracking-uri", f"sqlite:///{store}"]) == 1
    said = (
        f"fedlgr: error: tracking.checkpoint_dir={tmp_path / 'a.yaml'}: a symbolic link that loops"
    )
    assert capsys.readouterr().err.strip().splitlines()[-1] == said
    if store.exists():  # no run left RUNNING: none was started
        with contextlib.closing(sqlite3.connect(store)) as db:
            tables = {name for (name,) in db.execute("select name from sqlite_master")}
            assert "runs" not in tables or not db.execute("select * from runs").fetchall()


def test_a_store_path_that_is_a_dangling_link_is_refused_before_anything_is_made(
    tmp_path, synth_dir, capsys
):
    """The re-check of the seventh fault sweep (u79): the new store replaced the link with
    a file, and a checkpoints folder was made beside the link's missing target."""
    link = tmp_path / "store.db"
    link.symlink_to(tmp_path / "gone" / "x.db")
    argv = ["run", "debug/tiny", f"data.path={synth_dir}", "--tracking-uri", f"sqlite:///{link}"]
    assert main(argv) == 1
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"fedlgr: error: tracking store sqlite:///{link}: {link} is a symbolic link to "
        f"{tmp_path / 'gone' / 'x.db'}, which does not exist"
    )
    assert link.is_symlink() and not (tmp_path / "gone").exists()


def test_a_link_that_loops_or_leads_nowhere_is_named_as_such_wherever_a_path_is_given(
    tmp_path, synth_dir, capsys
):
    """The eighth fault sweep: a looping link as the tracking store was "a symbolic link
    to l2, which does not exist" (u50); as a report's store, a sweep's --storage, --key,
    --ca or --weights, "does not exist", "cannot open the sqlite file" (after a minute) or
    "no such file" (a46-a50, a60, a78, a79); a dangling --state-dir "cannot make it (File
    exists)" (a81); a FIFO as --certs "ca.pem does not exist" (a53). Nothing is made."""
    loop, dangling = tmp_path / "l1", tmp_path / "dangling"
    loop.symlink_to(tmp_path / "l2")
    (tmp_path / "l2").symlink_to(loop)
    dangling.symlink_to(tmp_path / "gone" / "x")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    looping, leads_nowhere = "a symbolic link that loops", f"a symbolic link to {tmp_path}/gone/x"
    run = ["run", "debug/tiny", f"data.path={synth_dir}", "--tracking-uri"]
    supernode = ["deploy", "supernode", "--superlink", "127.0.0.1:9092", "--data", str(synth_dir)]
    cases = {
        (*run, f"sqlite:///{loop}"): f"tracking store sqlite:///{loop}: {loop} is {looping}",
        (
            "report",
            "--tracking-uri",
            f"sqlite:///{loop}",
            "--no-log",
            "--out",
            str(tmp_path / "r"),
        ): (f"no MLflow store at sqlite:///{loop}: {loop} is {looping}"),
        (*supernode, "--insecure", "--weights", str(loop), "--print-command"): (
            f"--weights {loop}: {looping}"
        ),
        (*supernode, "--insecure", "--weights", str(fifo), "--print-command"): (
            f"--weights {fifo}: not a regular file (a device, pipe or socket)"
        ),
        (*supernode, "--ca", str(loop), "--key", str(loop), "--print-command"): (
            f"--ca: {loop} is {looping} (made by fedlgr deploy certs)"
        ),
        (*supernode, "--insecure", "--state-dir", str(dangling), "--print-command"): (
            f"--state-dir {dangling}: {leads_nowhere}, which does not exist"
        ),
        ("deploy", "superlink", "--certs", str(fifo), "--print-command"): (
            f"--certs {fifo}: a device, pipe or socket, not a folder (made by fedlgr deploy "
            "certs DIR)"
        ),
    }
    for argv, said in cases.items():
        assert main(list(argv)) == 1, argv
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"fedlgr: error: {said}", argv
    for storage in (loop, dangling):
        with pytest.raises(FedlgrError) as err:
            check_storage(f"sqlite:///{storage}")
        why = looping if storage == loop else f"{leads_nowhere}, which does not exist"
        assert str(err.value) == f"--storage sqlite:///{storage}: {storage} is {why}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dangling", "fifo", "l1", "l2"]


@pytest.mark.parametrize(
    ("overrides", "said"),
    [
        (
            ["data.path=d48", "data=[1,2]"],
            "command line: 'data.path=d48' and 'data=[1,2]' set data both whole and by its "
            "parts; give one of them",
        ),
        (
            ["data=[1,2]", "data.path=d48"],
            "command line: 'data=[1,2]' and 'data.path=d48' set data both whole and by its "
            "parts; give one of them",
        ),
        (
            [f"model.mlp_hidden={'[' * 45}16{']' * 45}"],
            f"model.mlp_hidden=[{'[' * 44}16{']' * 44}]: a list or mapping where a number goes",
        ),
        (
            ["train.betas=[[0.9],0.99]"],
            "train.betas=[[0.9], 0.99]: a list or mapping where a number goes",
        ),
        (
            ["model.mlp_hidden=[{a: 1}]"],
            "model.mlp_hidden=[{'a': 1}]: a list or mapping where a number goes",
        ),
        (  # the ninth sweep, c50: read, the 5 dropped, nothing said
            ["train=5", "train.lr_root=0.1"],
            "command line: 'train=5' and 'train.lr_root=0.1' set train both whole and by its "
            "parts; give one of them",
        ),
        (  # c52
            ["data=null", "data.path=d48"],
            "command line: 'data=null' and 'data.path=d48' set data both whole and by its "
            "parts; give one of them",
        ),
        (  # c100: "Merge error: int is not a subclass of TrainConfig. value: 5"
            ["train=5"],
            "command line: train=5: a section of settings, not one value; set its parts "
            "(e.g. train.epochs=...)",
        ),
        (  # c128: "TupleConfig length 1 does not match type hint length 2"
            ["train.betas=[0.9]"],
            "command line: train.betas=[0.9]: a list of 2 values expected, 1 given",
        ),
    ],
)
def test_a_setting_given_whole_and_by_parts_or_nested_where_numbers_go_is_named(overrides, said):
    """The eighth fault sweep: ``data.path=D 'data=[1,2]'`` was OmegaConf's bare "Cannot
    merge incompatible container types" (a12); lists nested where a size goes were
    "'<' not supported between instances of 'list' and 'int'" (a24, a29, a75)."""
    with pytest.raises(ConfigError) as err:
        load_config(Path(__file__).parents[1] / "conf/debug/fast.yaml", overrides)
    assert str(err.value) == said


def test_a_config_from_a_pipe_an_include_with_a_suffix_and_loops_are_named(tmp_path, capsys):
    """The eighth fault sweep: ``/dev/stdin`` as a config was "/proc/PID/fd/pipe:[N]:
    config file not found" (u37); ``includes: [cfg.fifo]`` and ``[/dev/zero]`` named
    cfg.yaml and /dev/zero.yaml, files never given (u38, u39); a looping data.path was
    "no such folder" (u48), a looping sweep file "no such file" (u53)."""
    from fedlgr.errors import DataError
    from fedlgr.shell.checks.paths import check_data_path
    from fedlgr.shell.sweep.spec import find_sweep

    if not Path("/proc/self/fd").is_dir():
        pytest.skip("needs Linux's /proc")
    fifo = tmp_path / "cfg.fifo"
    os.mkfifo(fifo)
    (tmp_path / "inc_fifo.yaml").write_text("includes: [cfg.fifo]\nseed: 1\n")
    (tmp_path / "inc_zero.yaml").write_text("includes: [/dev/zero]\nseed: 1\n")
    (tmp_path / "base.yml").write_text("seed: 7\n")
    (tmp_path / "inc_yml.yaml").write_text("includes: [base.yml]\n")
    loop = tmp_path / "l1"
    loop.symlink_to(tmp_path / "l2")
    (tmp_path / "l2").symlink_to(loop)
    special = "not a regular file (a device, pipe or socket)"
    read, write = os.pipe()  # /dev/stdin of `echo seed: 3 | fedlgr run /dev/stdin`
    pipe = f"/proc/self/fd/{read}"  # resolves to /proc/PID/fd/pipe:[N], which is no file
    cases = {
        pipe: f"{pipe}: {special}",
        tmp_path / "inc_fifo.yaml": f"{fifo}: {special}",
        tmp_path / "inc_zero.yaml": f"/dev/zero: {special}",
        loop: f"{loop}: a symbolic link that loops",
    }
    for path, said in cases.items():
        with pytest.raises(ConfigError) as err:
            load_config(path)
        assert str(err.value) == said
    os.close(read)
    os.close(write)
    assert load_config(tmp_path / "inc_yml.yaml").seed == 7  # was read as base.yaml
    with pytest.raises(DataError) as err:
        check_data_path(loop)
    assert str(err.value) == f"data.path={loop}: a symbolic link that loops"
    with pytest.raises(ConfigError) as err:
        find_sweep(loop)
    assert str(err.value) == f"sweep {loop}: a symbolic link that loops"


def test_a_device_pipe_or_socket_as_a_store_is_refused_before_anything_opens_it(
    tmp_path, synth_dir, capsys
):
    """The ninth fault sweep: a FIFO as the tracking store hung with no word (c06); a link
    to /dev/null, /dev/null itself or a FIFO as the store or --storage made
    ``/dev/null-journal``, ``/dev/null.lock``, ``FIFO.lock`` (c07, c16, c17, c120, c135);
    a report said "does not exist" (c11-c13). Now one line each, and nothing is made."""
    import signal
    import socket

    fifo, null, sock = tmp_path / "fifo", tmp_path / "null", tmp_path / "sock"
    os.mkfifo(fifo)
    null.symlink_to("/dev/null")
    server = socket.socket(socket.AF_UNIX)
    server.bind(str(sock))
    special = "not a regular file (a device, pipe or socket)"

    def hung(*_):
        raise TimeoutError("opened a FIFO as a store and waited on it")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(60)
    try:
        for store in (fifo, null, sock):
            uri = f"sqlite:///{store}"
            run = ["run", "debug/tiny", f"data.path={synth_dir}", "--tracking-uri", uri]
            assert main(run) == 1
            said = capsys.readouterr().err.strip().splitlines()[-1]
            assert said == f"fedlgr: error: tracking store {uri}: {store} is {special}"
            report = ["report", "--tracking-uri", uri, "--no-log", "--out", str(tmp_path / "r")]
            assert main(report) == 1
            said = capsys.readouterr().err.strip().splitlines()[-1]
            assert said == f"fedlgr: error: no MLflow store at {uri}: {store} is {special}"
            with pytest.raises(FedlgrError) as err:
                check_storage(uri)
            assert str(err.value) == f"--storage {uri}: {store} is {special}"
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
        server.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fifo", "null", "sock"]


def test_a_folder_given_as_a_link_that_leads_nowhere_or_to_a_device_is_named(
    tmp_path, synth_dir, capsys
):
    """The ninth fault sweep: data.path a FIFO or /dev/null was, after 15 s, "file not
    found (expected the MANNERS-DB ratings CSV)" (c41, c42, c110); --data a loop or a FIFO
    "no such folder" (c137-c139); --out, node-key DIR and certs DIR given a dangling link
    or loop "(File exists)" (c112-c116); tracking.checkpoint_dir a dangling link had its
    target made (c118), a link to /dev/null was "(File exists)" (c69); superlink
    --database a loop was passed on to Flower (c117)."""
    from fedlgr.errors import DataError
    from fedlgr.shell.checks.paths import check_data_path
    from fedlgr.shell.run.checkpoint import checkpoint_root

    fifo, null, loop = tmp_path / "fifo", tmp_path / "null", tmp_path / "l1"
    os.mkfifo(fifo)
    null.symlink_to("/dev/null")
    loop.symlink_to(tmp_path / "l2")
    (tmp_path / "l2").symlink_to(loop)
    dangling = tmp_path / "dangling"
    dangling.symlink_to(tmp_path / "gone")
    device = "a device, pipe or socket, not a folder"
    looping, nowhere = "a symbolic link that loops", f"a symbolic link to {tmp_path}/gone"
    nowhere += ", which does not exist"
    for path, said in (
        (fifo, device),
        (null, "a device, pipe or socket (/dev/null), not a folder"),
    ):
        with pytest.raises(DataError) as err:
            check_data_path(path)
        assert str(err.value) == f"data.path={path}: {said}"
    supernode = ["deploy", "supernode", "--superlink", "127.0.0.1:9092", "--insecure"]
    cases = {
        (*supernode, "--data", str(loop), "--print-command"): (
            f"--data {loop}: {looping} (the robot's dataset, MANNERS-DB layout)"
        ),
        (*supernode, "--data", str(fifo), "--print-command"): (
            f"--data {fifo}: {device} (the robot's dataset, MANNERS-DB layout)"
        ),
        ("data", "synth", "--out", str(dangling), "--scenes", "4", "--size", "32"): (
            f"{dangling}: {nowhere}"
        ),
        ("deploy", "node-key", str(loop), "robot0"): f"{loop}: {looping}",
        ("deploy", "certs", str(dangling)): f"{dangling}: {nowhere}",
        ("deploy", "superlink", "--insecure", "--database", str(loop), "--print-command"): (
            f"--database {loop}: {looping}"
        ),
    }
    for argv, said in cases.items():
        assert main(list(argv)) == 1, argv
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"fedlgr: error: {said}", argv
    for out in (loop, dangling):
        argv = ["report", "--tracking-uri", f"sqlite:///{tmp_path / 'no.db'}", "--out", str(out)]
        assert main(argv) == 1
        why = looping if out == loop else nowhere
        said = f"fedlgr: error: {out}: {why}; the report (--out) is a folder"
        assert capsys.readouterr().err.strip().splitlines()[-1] == said
    for folder, why in (
        (dangling, nowhere),
        (null, "a device, pipe or socket (/dev/null), not a folder"),
    ):
        config = load_config(None, [f"data.path={synth_dir}", f"tracking.checkpoint_dir={folder}"])
        with pytest.raises(FedlgrError) as err:
            checkpoint_root(config, "sqlite:///x.db")
        assert str(err.value) == f"tracking.checkpoint_dir={folder}: {why}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dangling", "fifo", "l1", "l2", "null"]


def test_a_path_under_a_dangling_link_is_named_and_the_links_target_is_not_made(
    tmp_path, synth_dir, capsys
):
    """The tenth fault sweep: a path whose folder is a dangling symbolic link was "File
    exists" as the tracking store, --storage, --database, data synth --out, node-key DIR,
    certs DIR, report --out and --cache-dir (d24, d28, d32, d39, d50, d53, d56, d60, d71);
    as tracking.checkpoint_dir the run made the link's target and went on (d74)."""
    from fedlgr.shell.data.images import _check_cache_dir
    from fedlgr.shell.run.checkpoint import checkpoint_root

    link = tmp_path / "dir"
    link.symlink_to(tmp_path / "made_by_link")
    under = f"under {link}, a symbolic link to {tmp_path / 'made_by_link'}, which does not exist"
    sub = link / "sub"
    cases = {
        ("run", "debug/tiny", f"data.path={synth_dir}", "--tracking-uri", f"sqlite:///{sub}"): (
            f"tracking store sqlite:///{sub}: {sub} is {under}"
        ),
        ("data", "synth", "--out", str(sub), "--scenes", "4", "--size", "32"): f"{sub}: {under}",
        ("deploy", "node-key", str(sub), "robot0"): f"{sub}: {under}",
        ("deploy", "certs", str(sub)): f"{sub}: {under}",
        ("deploy", "superlink", "--insecure", "--database", str(sub), "--print-command"): (
            f"--database {sub}: {under}"
        ),
        (
            *("deploy", "supernode", "--superlink", "127.0.0.1:9092", "--data", str(synth_dir)),
            *("--insecure", "--cache-dir", str(sub), "--print-command"),
        ): f"--cache-dir {sub}: {under}",
        ("report", "--tracking-uri", f"sqlite:///{tmp_path / 'no.db'}", "--out", str(sub)): (
            f"{sub}: {under}; the report (--out) is a folder"
        ),
    }
    for argv, said in cases.items():
        assert main(list(argv)) == 1, argv
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"fedlgr: error: {said}", argv
    with pytest.raises(FedlgrError) as err:
        check_storage(f"sqlite:///{sub}")
    assert str(err.value) == f"--storage sqlite:///{sub}: {sub} is {under}"
    config = load_config(None, [f"data.path={synth_dir}", f"tracking.checkpoint_dir={sub}"])
    with pytest.raises(FedlgrError) as err:
        checkpoint_root(config, "sqlite:///x.db")
    assert str(err.value) == f"tracking.checkpoint_dir={sub}: {under}"
    with pytest.raises(ConfigError) as err:
        _check_cache_dir(sub)
    assert str(err.value).startswith(f"data.cache_dir={sub}: {under} (point data.cache_dir at")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir"]


def test_a_setting_given_twice_a_report_into_a_device_and_a_shared_store_are_refused(
    tmp_path, synth_dir, capsys
):
    """The tenth fault sweep: a setting given twice with two values kept the last and
    dropped the first without a word (d101, d145, d146), as did --tracking-uri with another
    tracking.uri= (d163); report --out /dev/null or a FIFO was "is a file" (d36, d37); a
    sweep whose base: is a FIFO "no such file" (d88); one sqlite file as --storage and
    tracking store failed after 11 s with Alembic's "No such revision" (d167)."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    run = ["run", "debug/tiny", f"data.path={synth_dir}"]
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    (tmp_path / "fifo_base.yaml").write_text(f"base: {fifo}\nspace:\n  seed: [1, 2]\n")
    (tmp_path / "grid.yaml").write_text("base: debug/tiny.yaml\nspace:\n  seed: [1, 2]\n")
    cases = {
        (*run, "seed=1", "seed=2", "--print-config"): (
            "command line: 'seed=1' and 'seed=2' both set seed; give one of them"
        ),
        (*run, f"data.path={tmp_path}", "--print-config"): (
            f"command line: 'data.path={synth_dir}' and 'data.path={tmp_path}' both set "
            "data.path; give one of them"
        ),
        (*run, "--tracking-uri", store, f"tracking.uri=sqlite:///{tmp_path / 'b.db'}"): (
            f"command line: --tracking-uri {store} and 'tracking.uri=sqlite:///"
            f"{tmp_path / 'b.db'}' name two tracking stores; give one of them"
        ),
        ("report", "--tracking-uri", store, "--out", "/dev/null"): (
            "/dev/null: is a device, pipe or socket; the report (--out) is a folder of tables "
            "and plots: name a new or existing folder"
        ),
        ("sweep", str(tmp_path / "fifo_base.yaml"), "--tracking-uri", store): (
            f"config {fifo}: {fifo} is not a regular file (a device, pipe or socket)"
        ),
        (
            *("sweep", str(tmp_path / "grid.yaml"), f"data.path={synth_dir}"),
            *("--tracking-uri", store, "--storage", store),
        ): (
            f"--storage {store}: the tracking store's file too; Optuna's study and MLflow's "
            f"runs each need a database of their own (e.g. --storage sqlite:///"
            f"{tmp_path / 'optuna.db'})"
        ),
    }
    for argv, said in cases.items():
        assert main(list(argv)) == 1, argv
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"fedlgr: error: {said}", argv
    assert main([*run, f"data.path={synth_dir}", "--print-config"]) == 0  # the same twice
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fifo", "fifo_base.yaml", "grid.yaml"]


@pytest.mark.slow
def test_a_checkpoint_folder_the_user_made_is_kept_when_a_run_finishes(
    tmp_path, synth_dir, cache_dir
):
    """The tenth fault sweep: a finished run removed an empty tracking.checkpoint_dir the
    user had made (d196), and the folder a link there led to, leaving the link leading
    nowhere (d190). fedlgr's own checkpoints/ beside the store still goes."""
    mine, real = tmp_path / "mine", tmp_path / "real"
    mine.mkdir()
    real.mkdir()
    (tmp_path / "link").symlink_to(real)
    base = ["run", "debug/tiny", f"data.path={synth_dir}", f"data.cache_dir={cache_dir}"]
    for folder in (mine, tmp_path / "link"):
        store = f"sqlite:///{tmp_path / 'mlflow.db'}"
        assert main([*base, f"tracking.checkpoint_dir={folder}", "--tracking-uri", store]) == 0
        assert folder.is_dir() and not any(folder.iterdir())
    assert main([*base, "--tracking-uri", f"sqlite:///{tmp_path / 'own' / 'mlflow.db'}"]) == 0
    assert "checkpoints" not in {p.name for p in (tmp_path / "own").iterdir()}


def test_an_interrupt_while_a_run_is_being_started_ends_it_killed(tmp_path, synth_dir, monkeypatch):
    """The tenth fault sweep (d07, d155): Ctrl-C or SIGHUP 0.1 s into a sweep's trial, while
    its MLflow run was being set up, ended the run FAILED, as an error would; an interrupt
    later in the run ends it KILLED."""
    import mlflow

    from fedlgr.shell.tracking import mlflow_run

    def interrupted(*_args, **_kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(mlflow_run.context, "log_dataset", interrupted)
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    config = load_config(None, [f"data.path={synth_dir}", f"tracking.uri={store}"])
    with pytest.raises(KeyboardInterrupt):
        mlflow_run.Tracker(config)
    client = mlflow.MlflowClient(store)
    experiments = [e.experiment_id for e in client.search_experiments()]
    (run,) = client.search_runs(experiments)
    assert run.info.status == "KILLED"


@pytest.mark.slow
def test_one_value_spelled_twice_passes_and_what_a_sweep_would_drop_is_refused(
    tmp_path, synth_dir, cache_dir, capsys, monkeypatch
):
    """The eleventh fault sweep: one value spelled two ways (``seed=1 seed=01``, one sqlite
    file by two paths, ``tracking.uri=null``) was refused as two (e64, e73, d178); one
    sqlite file as --storage and store by a link or ``..`` was not caught (e81, e84); a
    sweep file's overrides: setting a key twice, or an override of a setting the space
    varies, were dropped without a word (e162, e163, e168); a config or sweep under a FIFO
    or a file was "not found" (e50, e147, e148); a tracking.checkpoint_dir of the user's
    named checkpoints was removed after the run (e92)."""
    monkeypatch.chdir(tmp_path)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    run = ["run", "debug/tiny", f"data.path={synth_dir}"]
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    for same in (
        ["seed=1", "seed=01"],
        ["tracking.uri=null", "--tracking-uri", store],
        ["tracking.uri=sqlite:///mlflow.db", "--tracking-uri", store],
    ):
        assert main([*run, *same, "--print-config"]) == 0, same
    capsys.readouterr()
    (tmp_path / "mlflow.db").touch()
    (tmp_path / "link.db").symlink_to(tmp_path / "mlflow.db")
    space = "space:\n  seed: [1, 2]\n"
    (tmp_path / "grid.yaml").write_text(f"base: debug/tiny.yaml\n{space}")
    (tmp_path / "twice.yaml").write_text(
        f"base: debug/tiny.yaml\noverrides: [seed=1, seed=2]\n{space}"
    )
    (tmp_path / "rounds.yaml").write_text(
        "base: debug/tiny.yaml\noverrides: [federated.rounds=1, federated.rounds=2]\n"
        "space:\n  train.lr_top: [0.1, 0.2]\n"
    )

    def sweep(name: str, *more: str) -> tuple[str, ...]:
        return ("sweep", name, f"data.path={synth_dir}", "--tracking-uri", store, *more)

    cases = {
        sweep("grid.yaml", "--storage", f"sqlite:///{tmp_path / 'link.db'}"): (
            f"--storage sqlite:///{tmp_path / 'link.db'}: the tracking store's file too; "
            "Optuna's study and MLflow's runs each need a database of their own (e.g. "
            f"--storage sqlite:///{tmp_path / 'optuna.db'})"
        ),
        sweep("grid.yaml", "seed=3"): (
            "sweep grid: 'seed=3' (the command line) sets seed, which its space: varies, "
            "each trial its own value; drop it, or take seed out of space:"
        ),
        sweep("rounds.yaml"): (
            "sweep rounds: its overrides: set federated.rounds twice ('federated.rounds=1', "
            "'federated.rounds=2'); keep one"
        ),
        sweep("twice.yaml"): (
            "sweep twice: 'seed=1' (its overrides:) sets seed, which its space: varies, each "
            "trial its own value; drop it, or take seed out of space:"
        ),
        ("run", f"{fifo}/x.yaml", "--print-config"): (
            f"{fifo}/x.yaml: under {fifo}, a device, pipe or socket, not a folder"
        ),
        ("sweep", f"{fifo}/s.yaml"): (
            f"sweep {fifo}/s.yaml: under {fifo}, a device, pipe or socket, not a folder"
        ),
    }
    for argv, said in cases.items():
        assert main(list(argv)) == 1, argv
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"fedlgr: error: {said}", argv
    mine = tmp_path / "mine" / "checkpoints"
    mine.mkdir(parents=True)
    base = [*run, f"data.cache_dir={cache_dir}", f"tracking.checkpoint_dir={mine}"]
    assert main([*base, "--tracking-uri", store]) == 0
    assert mine.is_dir() and not any(mine.iterdir())
