"""Path checks (fedlgr/shell/checks/paths.py) as a user meets them: a link that loops or
leads nowhere, a device, pipe or socket, or a path under any of them, given wherever a
command takes a path, is named as such in one line, and nothing is made."""

from __future__ import annotations

import contextlib
import os
import sqlite3

import pytest

from fedlgr.errors import ConfigError, FedlgrError
from fedlgr.shell.cli import main
from fedlgr.shell.config import load_config
from fedlgr.shell.sweep.storage import check_storage


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
