"""``fedlgr deploy certs | node-key | app | connect | superlink | supernode | run``: fedlgr on
Flower's Deployment Runtime (docs/deployment.md).

``certs`` and ``node-key`` write the credentials, ``connect`` tells the ``flwr`` command
where the SuperLink is, ``superlink`` and ``supernode`` replace themselves with Flower's
processes (TLS and SuperNode authentication on unless ``--insecure``), and ``run`` submits
fedlgr's app with ``flwr run`` and exits 0 only if the run completed. Each prints the Flower
command it runs; ``--print-command`` prints it and stops there. Their arguments are in
:mod:`fedlgr.shell.cli.deploy_args`.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import sys
from pathlib import Path

from fedlgr.errors import FedlgrError, not_a_file, not_a_folder

INSECURE_WARNING = """\
fedlgr: ############################ WARNING: --insecure ############################
fedlgr: No TLS: model updates, configs and metrics travel in clear text.
fedlgr: No SuperNode authentication: any machine that reaches the SuperLink's port can
fedlgr: join as a robot, receive the model and send poisoned updates.
fedlgr: Use this on a trusted test machine only (fedlgr deploy certs / node-key otherwise).
fedlgr: ############################################################################"""


def certs(args: argparse.Namespace) -> int:
    from fedlgr.shell.deploy.credentials import DEFAULT_HOSTS, make_certificates

    # 127.0.0.1 always: Flower's own processes (SuperExec, the ServerApp) and flwr on the
    # SuperLink's machine reach it there, behind fedlgr's gateway (superlink's --internal-port).
    hosts = tuple(dict.fromkeys([*(args.host or DEFAULT_HOSTS), "127.0.0.1"]))
    paths = make_certificates(args.dir, hosts, days=args.days, force=args.force)
    print(f"wrote {', '.join(map(str, paths.values()))}")
    print(f"server certificate for {', '.join(hosts)}, valid {args.days} days")
    print(f"  {paths['ca.pem']}: to every robot and to whoever runs flwr (--ca)")
    print(f"  {paths['server.pem']}, {paths['server.key']}: stay on the SuperLink's machine")
    print(f"  {paths['ca.key']}: keep offline (it signs certificates)")
    return 0


def node_key(args: argparse.Namespace) -> int:
    from fedlgr.shell.deploy.credentials import make_node_key

    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", args.name):
        raise FedlgrError(f"node-key NAME {args.name!r}: letters, digits, '.', '_', '-' only")
    if len(args.name) > 100:  # NAME.pub must fit a file name (255 bytes at most)
        raise FedlgrError(f"node-key NAME {args.name[:20]}...: at most 100 characters")
    # NAME and NAME.pub share the folder with the deployment's other files: a robot named
    # after one of them (or after another robot's public key) would overwrite it, or lose
    # its private key to it.
    taken = {"roster.yaml", "ca.pem", "ca.key", "server.pem", "server.key"}
    if args.name in taken or args.name.endswith(".pub"):
        raise FedlgrError(
            f"node-key NAME {args.name!r}: the name of a file this folder holds (NAME and "
            f"NAME.pub are written beside {', '.join(sorted(taken))} and other robots' "
            "NAME.pub); choose another"
        )
    roster = None
    if not args.no_roster:
        from fedlgr.shell.deploy.roster import ROSTER_NAME, Roster

        roster = Roster.read_or_empty(args.dir / ROSTER_NAME)
        if args.client is not None and args.client < 0:
            raise FedlgrError(f"--client {args.client}: a client slot is 0 or more")
        taken = [m for m in roster.members if m.client == args.client and m.name != args.name]
        if args.client is not None and taken:
            raise FedlgrError(
                f"--client {args.client}: {taken[0]} holds that slot in {roster.path}"
            )
    elif args.client is not None:
        raise FedlgrError("--client K is the robot's slot on the roster: drop --no-roster")
    private, public = make_node_key(args.dir, args.name, force=args.force)
    print(f"wrote {private} (private: to that robot only) and {public}")
    if roster is not None:
        member = roster.add(args.name, public.read_text(), args.client)
        print(f"added {member} to {roster.write()}")
    print(f"register it with the SuperLink: flwr supernode register {shlex.quote(str(public))}")
    return 0


def app(args: argparse.Namespace) -> int:
    from fedlgr.shell.deploy.flower import APP_DIR

    print(APP_DIR)
    return 0


def connect(args: argparse.Namespace) -> int:
    import tomli_w

    if not re.fullmatch(r"[A-Za-z0-9_-]+", args.name):
        raise FedlgrError(f"connection NAME {args.name!r}: letters, digits, '_', '-' only")
    _address(args.superlink)
    entry = {"address": args.superlink}
    if args.insecure:
        _no_ca(args)
        _warn_insecure()
        entry["insecure"] = True
    else:
        entry["root-certificates"] = str(_certificates(args.ca))
    path, config = _flower_config()
    home = path.parent
    links = config.setdefault("superlink", {})
    links[args.name] = entry
    if args.default or "default" not in links:
        links["default"] = args.name
    home.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".toml.partial")
    partial.write_text(tomli_w.dumps(config))
    partial.replace(path)
    print(f"wrote [superlink.{args.name}] (address {args.superlink}) to {path}")
    if links["default"] != args.name:
        print(
            f"the default stays {links['default']!r}: use --federation {args.name} "
            "(or connect again with --default)"
        )
    return 0


def _flower_config() -> tuple[Path, dict]:
    """The flwr CLI's ``config.toml`` (under ``$FLWR_HOME``, else ``~/.flwr``) and its
    settings ({} while there is none)."""
    import tomllib

    path = Path(os.environ.get("FLWR_HOME") or Path.home() / ".flwr") / "config.toml"
    try:
        return path, tomllib.loads(path.read_text()) if path.is_file() else {}
    except tomllib.TOMLDecodeError as err:
        raise FedlgrError(f"{path}: not valid TOML ({err})") from None
    except OSError as err:
        raise FedlgrError(f"{path}: cannot read it ({err.strerror or err})") from None


def _check_connection(name: str | None) -> None:
    """The SuperLink ``flwr run`` will submit to must be one ``fedlgr deploy connect``
    named: with none, flwr 1.41 writes its own config, whose default ``local`` starts a
    simulation SuperLink and SuperExec of its own in the background - left running after
    the run fails, with the app installed under ``~/.flwr``."""
    path, config = _flower_config()
    links = config.get("superlink", {})
    chosen = name or links.get("default")
    entry = links.get(chosen) if isinstance(chosen, str) else None
    if not isinstance(entry, dict) or entry.get("address", ":local:") == ":local:":
        which = f"--federation {name}" if name else "the default connection"
        raise FedlgrError(
            f"{which}: no SuperLink connection of that name in {path} (flwr would start a "
            "local simulation of its own); add one with fedlgr deploy connect NAME "
            "--superlink HOST:PORT --ca ca.pem"
        )


EXPOSED_CONTROL_WARNING = """\
fedlgr: ####################### WARNING: --expose-control-api #######################
fedlgr: Flower serves ALL its APIs on this port, not only the robots' Fleet API: anyone
fedlgr: who reaches it (ca.pem is public) can register a SuperNode key with flwr
fedlgr: supernode register (then join as a robot) and submit runs with flwr run - code
fedlgr: that runs on this server. Firewall the port to trusted machines, or drop the
fedlgr: option (the default: the Fleet API alone there, the Control API on 127.0.0.1).
fedlgr: ############################################################################"""


def superlink(args: argparse.Namespace) -> int:
    """Flower's SuperLink behind fedlgr's Fleet-only gateway (:mod:`fedlgr.shell.deploy.gateway`)
    on ``--host``/``--port``, bound to 127.0.0.1:``--internal-port`` itself; or, with
    ``--expose-control-api``, Flower alone on ``--host``/``--port`` with all its APIs."""
    from fedlgr.shell.deploy.credentials import is_host

    exe = _flower("flower-superlink")
    if not is_host(args.host):  # the fifth fault sweep, k36: 'bad host' was printed as a URL
        raise FedlgrError(
            f"--host {args.host!r}: not an address to listen on (an IP address such as "
            "0.0.0.0 or 127.0.0.1, or this machine's host name)"
        )
    cmd = [str(exe)]
    tls = None
    if args.insecure:
        cmd.append("--insecure")
    else:
        if args.certs is None:
            raise FedlgrError("--certs DIR is required (fedlgr deploy certs DIR), or --insecure")
        folder = _absolute(args.certs)  # a FIFO was said to hold no ca.pem (a53)
        if why := not_a_folder(folder):
            raise FedlgrError(f"--certs {folder}: {why} (made by fedlgr deploy certs DIR)")
        tls = tuple(
            _existing(args.certs / name, "--certs", "fedlgr deploy certs DIR")
            for name in ("ca.pem", "server.pem", "server.key")
        )
        from fedlgr.shell.deploy.credentials import check_private_mode, warn_if_open

        check_private_mode(tls[2], "--certs")
        # as node-key and the SuperNode say of theirs (the tenth fault sweep, d198)
        warn_if_open(folder, "the certificates or server.key")
        flags = ("--ssl-ca-certfile", "--ssl-certfile", "--ssl-keyfile")
        for flag, path in zip(flags, tls, strict=True):
            cmd += [flag, str(path)]
        cmd.append("--enable-supernode-auth")
    cmd.append("--disable-runtime-dependency-installation")
    if args.expose_control_api:
        if args.internal_port is not None:
            raise FedlgrError("--internal-port is the gateway's: drop it or --expose-control-api")
        print(EXPOSED_CONTROL_WARNING, file=sys.stderr, flush=True)
        cmd += ["--host", args.host, "--port", str(args.port)]
        cmd += _database(args)
        return _exec(cmd, args)
    internal = _internal_port(args)
    cmd += ["--host", "127.0.0.1", "--port", str(internal), *_database(args)]
    executor = None
    if not args.cold_apps:  # its ServerApps forked from a warm process (flower/executor.py)
        cmd += ["--isolation", "process"]
        executor = [sys.executable, "-m", "fedlgr.shell.deploy.flower.executor", "--preload"]
        executor += ["serverapp", "--runtime-api-address", f"127.0.0.1:{internal}"]
        executor += ["--insecure"] if tls is None else ["--root-certificates", str(tls[0])]
    return _gateway(cmd, args, internal, tls, executor)


def _internal_port(args: argparse.Namespace) -> int:
    """Flower's own port on 127.0.0.1 behind the gateway: ``--internal-port``, else --port + 1."""
    internal = args.port + 1 if args.internal_port is None else args.internal_port
    for option, port in (("--port", args.port), ("--internal-port", internal)):
        if not 1 <= port <= 65535:
            raise FedlgrError(f"{option} {port}: a port is 1 to 65535")
    if internal == args.port:
        raise FedlgrError(f"--internal-port {internal}: must differ from --port (the robots')")
    return internal


def _database(args: argparse.Namespace) -> list[str]:
    """``--database FILE`` for Flower, its folder checked first: Flower would end in a
    SQLAlchemy traceback ("unable to open database file")."""
    if args.database is None:
        return []
    path = _absolute(args.database)
    if path.is_dir():
        raise FedlgrError(f"--database {path}: a folder; name the SuperLink's database file")
    if why := not_a_file(path):  # a loop was passed on to Flower (the ninth sweep, c117)
        raise FedlgrError(f"--database {path}: {why}")
    if not path.parent.is_dir():
        raise FedlgrError(f"--database {path}: no folder {path.parent} (make it first)")
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise FedlgrError(f"--database {path}: cannot write in {path.parent}")
    return ["--database", str(path)]


def _gateway(
    cmd: list[str],
    args: argparse.Namespace,
    internal: int,
    tls: tuple[Path, ...] | None,
    executor: list[str] | None,
) -> int:
    """Print what ``superlink`` runs, then run Flower's ``cmd`` behind the gateway."""
    from fedlgr.shell.deploy import gateway

    files = None if tls is None else gateway.Tls(*tls)
    if files is not None and not gateway.covers_loopback(files.cert):
        raise FedlgrError(
            f"--certs: {files.cert} does not name 127.0.0.1, where the gateway and Flower's "
            "own processes reach the SuperLink: make the certificates again with --host "
            "127.0.0.1 besides the robots' names (fedlgr deploy certs DIR --host NAME --host "
            "127.0.0.1)"
        )
    if args.insecure:
        _warn_insecure()
    scheme = "http" if files is None else "https"
    flwr = ["--insecure"] if files is None else ["--ca", str(files.ca)]
    connect = ["fedlgr", "deploy", "connect", "NAME", "--superlink", f"127.0.0.1:{internal}"]
    print(shlex.join(cmd))
    if executor is not None:
        print(shlex.join(executor))
    print(
        f"fedlgr: the robots' port {scheme}://{args.host}:{args.port} is fedlgr's gateway: "
        f"POST /v1/fleet/<name> forwarded to {scheme}://127.0.0.1:{internal}, the rest "
        "refused (403)"
    )
    print(
        "fedlgr: flwr run and flwr supernode register work from this machine only: "
        + shlex.join([*connect, *flwr]),
        flush=True,
    )
    if args.print_command:
        return 0
    from fedlgr.shell.signals import terminate_as_interrupt

    with terminate_as_interrupt():  # SIGTERM (systemd, docker stop) stops Flower too
        env = _env(Path(cmd[0]))
        return gateway.run(cmd, env, args.host, args.port, internal, files, executor)


def supernode(args: argparse.Namespace) -> int:
    from fedlgr.shell.config import MAX_PER_MACHINE
    from fedlgr.shell.deploy.flower.supernode import HEARTBEAT_RANGE, POLL_RANGE

    _flower("flower-supernode")  # Flower is installed here
    _address(args.superlink)
    if args.client is not None and args.client < 0:
        raise FedlgrError(f"--client {args.client}: a client index is 0 or more")
    if args.threads is not None and not 1 <= args.threads <= MAX_PER_MACHINE:
        raise FedlgrError(
            f"--threads {args.threads}: 1 to {MAX_PER_MACHINE} (runtime.threads' bound)"
        )
    data = _absolute(args.data)
    if why := not_a_folder(data):  # was "no such folder" (the ninth sweep, c137-c139)
        raise FedlgrError(f"--data {data}: {why} (the robot's dataset, MANNERS-DB layout)")
    if not data.is_dir():
        raise FedlgrError(f"--data {data}: no such folder (the robot's dataset, MANNERS-DB layout)")
    for option, value, (low, high) in (
        ("--poll-s", args.poll_s, POLL_RANGE),
        ("--heartbeat-s", args.heartbeat_s, HEARTBEAT_RANGE),
    ):
        if not low <= value <= high:  # NaN too
            raise FedlgrError(f"{option} {value}: must be between {low:g} and {high:g} seconds")
    # flower-supernode, its idle poll shortened, its heartbeat as chosen and its ClientApps
    # forked from a warm process (fedlgr/shell/deploy/flower/supernode.py and executor.py say why)
    cmd = [
        sys.executable,
        "-m",
        "fedlgr.shell.deploy.flower.supernode",
        "--poll-s",
        str(args.poll_s),
    ]
    cmd += ["--heartbeat-s", f"{args.heartbeat_s:g}"]
    if not args.cold_apps:
        cmd += ["--warm-apps", f"127.0.0.1:{args.port}"]
    cmd += ["--superlink", args.superlink]
    if args.insecure:
        _no_ca(args)
        cmd.append("--insecure")
    else:
        cmd += ["--root-certificates", str(_certificates(args.ca))]
    if args.insecure and args.key is not None:
        raise FedlgrError(
            "--insecure turns TLS off, and SuperNode authentication needs TLS: drop --key "
            "(or drop --insecure)"
        )
    if not args.insecure:
        from fedlgr.shell.deploy.credentials import check_node_key

        key = _existing(args.key, "--key", "fedlgr deploy node-key DIR NAME")
        check_node_key(key)
        cmd += ["--auth-supernode-private-key", str(key)]
    from fedlgr.shell.data.ratings import read_ratings

    # A broken ratings file is found now, in one line, not when the first run's first
    # message reaches the robot (the images are decoded then, at the run's image size).
    read_ratings(data)
    settings = [f"data-path={_toml_string(str(data))}"]
    if args.client is not None:
        settings.append(f"client={args.client}")
    if args.own_data:
        settings.append("own-data=true")
    for name, folder in (("state-dir", args.state_dir), ("cache-dir", args.cache_dir)):
        if folder is not None:
            own = _own_folder(folder, f"--{name}", make=not args.print_command)
            settings.append(f"{name}={_toml_string(str(own))}")
    if args.weights is not None:
        weights = _absolute(args.weights)
        if why := not_a_file(weights):  # was "no such file" (the eighth sweep, u11-u18, a46-a50)
            raise FedlgrError(f"--weights {weights}: {why}")
        if not weights.is_file():
            raise FedlgrError(
                f"--weights {weights}: no such file (this robot's copy of the root weights "
                "a run's model.weights names)"
            )
        from fedlgr.core.models.scholar import file_state_dict
        from fedlgr.errors import ConfigError

        try:  # its content too (the seventh fault sweep, e17: /etc/shadow was taken)
            file_state_dict(weights)
        except ConfigError as err:
            said = str(err).replace(f"model.weights={weights}", f"--weights {weights}")
            raise FedlgrError(said) from None
        settings.append(f"weights={_toml_string(str(weights))}")
    if args.threads is not None:
        settings.append(f"threads={args.threads}")
    if args.idle_s is not None:
        if not args.idle_s > 0:
            raise FedlgrError(f"--idle-s {args.idle_s}: must be > 0")
        settings.append(f"robot-idle-s={args.idle_s}")
    cmd += ["--node-config", " ".join(settings), "--host", "127.0.0.1", "--port", str(args.port)]
    for option, value in (
        ("--max-retries", args.max_retries),
        ("--max-wait-time", args.max_wait_time),
    ):
        if value is not None and not value >= 0:  # NaN too
            raise FedlgrError(f"{option} {value}: must be 0 or more")
    if args.max_retries is not None:
        cmd += ["--max-retries", str(args.max_retries)]
    if args.max_wait_time is not None:
        cmd += ["--max-wait-time", str(args.max_wait_time)]
    return _exec(cmd, args)


def run(args: argparse.Namespace) -> int:
    import json
    import subprocess
    import time

    from fedlgr.shell.deploy.flower import APP_DIR

    flwr = _flower("flwr")
    config = _absolute(args.config)
    run_config = (
        f"config={_toml_string(str(config))} overrides={_toml_string(shlex.join(args.overrides))}"
    )
    if args.resume:
        run_config += f" resume={_toml_string(args.resume)}"
    link = [args.federation] if args.federation else []
    cmd = [str(flwr), "run", str(APP_DIR), *link, "--stream", "--run-config", run_config]
    _check_connection(args.federation)  # --print-command too (the seventh fault sweep, e21)
    print(shlex.join(cmd), flush=True)
    if args.print_command:
        return 0
    if config.is_file():
        from fedlgr.shell.config import load_config
        from fedlgr.shell.deploy.roster import roster_of

        # Here, in a second, rather than on the server after the run was submitted and
        # its ServerApp started (~40 s): a typo is the commonest mistake. The roster too,
        # as the ServerApp will read it (runs are submitted on the SuperLink's machine).
        roster_of(load_config(config, args.overrides))
    else:
        print(f"fedlgr: {config} is not on this machine: it must be on the SuperLink's", flush=True)
    env = {**_env(flwr), "PYTHONUNBUFFERED": "1"}
    run_id = None
    with subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    ) as proc:
        try:
            for line in proc.stdout:
                print(line, end="", flush=True)
                found = re.search(r"Successfully started run (\d+)", line)
                run_id = run_id or (found and found.group(1))
        except KeyboardInterrupt:
            if run_id:
                stop = shlex.join(["flwr", "stop", run_id, *link])
                print(f"fedlgr: run {run_id} goes on on the SuperLink; {stop} stops it")
            raise
    if proc.returncode != 0 or run_id is None:
        raise FedlgrError(f"flwr run failed (exit {proc.returncode}); its output is above")
    deadline = time.monotonic() + 60  # the log ends as the run does; its status may lag
    while True:
        ls = subprocess.run(
            [str(flwr), "ls", *link, "--run-id", run_id, "--format", "json"],
            capture_output=True,
            text=True,
            env=env,
        )
        try:
            listed = json.loads(ls.stdout[ls.stdout.index("{") :])
            [row] = listed["runs"]
        except (ValueError, KeyError) as err:
            detail = " ".join((ls.stdout + ls.stderr).split())[-300:]
            raise FedlgrError(f"flwr ls --run-id {run_id}: no status ({err}): {detail}") from None
        if row["status"].startswith("finished") or time.monotonic() > deadline:
            break
        time.sleep(1)
    if row["status"] != "finished:completed":
        details = " ".join(str(row.get("status-details") or "no details").split())
        raise FedlgrError(f"Flower run {run_id} ended {row['status']}: {details}")
    print(f"fedlgr: Flower run {run_id} finished:completed")
    return 0


def _flower(name: str) -> Path:
    """Flower's command ``name``: the one next to this Python (the venv), else on PATH."""
    import shutil

    beside = Path(sys.executable).parent / name
    if beside.is_file() and os.access(beside, os.X_OK):
        return beside
    found = shutil.which(name)
    if found is None:
        raise FedlgrError(
            f"{name} not found next to {sys.executable} nor on PATH: Flower is not installed "
            "in this environment (uv sync installs flwr)"
        )
    return Path(found)


def _env(exe: Path) -> dict[str, str]:
    """Flower's processes start flower-superexec (and the apps) from PATH: ``exe``'s folder
    first. Its telemetry and update check are off unless set otherwise."""
    env = {**os.environ, "PATH": f"{exe.parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    env.setdefault("FLWR_TELEMETRY_ENABLED", "0")
    env.setdefault("FLWR_DISABLE_UPDATE_CHECK", "1")  # flwr is pinned (pyproject.toml)
    # How often a SuperExec looks for work (a ServerApp to start on the SuperLink, a
    # ClientApp per message on a robot): Flower's default of 1 s adds up to 1 s per message.
    env.setdefault("FLWR_SUPEREXEC_TASK_POLL_INTERVAL", "0.2")
    return env


def _exec(cmd: list[str], args: argparse.Namespace) -> int:
    if getattr(args, "insecure", False):
        _warn_insecure()
    print(shlex.join(cmd), flush=True)
    if args.print_command:
        return 0
    sys.stderr.flush()
    os.execve(cmd[0], cmd, _env(Path(cmd[0])))
    return 1  # not reached


def _warn_insecure() -> None:
    print(INSECURE_WARNING, file=sys.stderr, flush=True)


def _absolute(path: Path | str) -> Path:
    return Path(os.path.abspath(os.path.expanduser(path)))


def _existing(path: Path | None, option: str, maker: str) -> Path:
    if path is None:
        raise FedlgrError(f"{option} is required (made by {maker}), or --insecure")
    path = _absolute(path)
    if why := not_a_file(path):
        raise FedlgrError(f"{option}: {path} is {why} (made by {maker})")
    if not path.is_file():
        raise FedlgrError(f"{option}: {path} does not exist (made by {maker})")
    return path


def _certificates(path: Path | None) -> Path:
    """``--ca``: an existing file of PEM certificates."""
    from fedlgr.shell.deploy.credentials import check_certificates

    path = _existing(path, "--ca", "fedlgr deploy certs")
    check_certificates(path)
    return path


def _own_folder(folder: Path, option: str, make: bool) -> Path:
    """A folder the robot writes (``--state-dir``, ``--cache-dir``), checked before Flower
    starts rather than when a run's first message arrives (the fifth to seventh fault
    sweeps, k30, k62, e23, e25: ``/proc/x`` and a private key's path were taken): an
    existing folder it can write in, or one it can make - made here, and with
    ``--print-command`` (``make`` False) made and removed again, as only trying tells
    (root may write anywhere by its permissions, yet not in /proc)."""
    path = _absolute(folder)
    if why := not_a_folder(path):  # was "cannot make it (File exists)" (u20, a81)
        raise FedlgrError(f"{option} {path}: {why}")
    if not path.exists():
        above = next(p for p in path.parents if p.exists())
        if not above.is_dir():
            raise FedlgrError(f"{option} {path}: {above} is a file, not a folder")
        made = [p for p in (path, *path.parents) if not p.exists()]  # the deepest first
        try:
            path.mkdir(parents=True)
        except OSError as err:
            raise FedlgrError(f"{option} {path}: cannot make it ({err.strerror})") from None
        if not make:
            for part in made:
                part.rmdir()
            path = above  # what must be writable
    if not os.access(path, os.W_OK | os.X_OK):
        raise FedlgrError(f"{option} {_absolute(folder)}: cannot write in {path}")
    return _absolute(folder)


def _no_ca(args: argparse.Namespace) -> None:
    if args.ca is not None:
        raise FedlgrError("--insecure turns TLS off: drop --ca (or drop --insecure)")


def _address(address: str) -> None:
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise FedlgrError(f"--superlink {address!r}: expected HOST:PORT, e.g. 10.0.0.5:9092")
    if not 1 <= int(port) <= 65535:
        raise FedlgrError(f"--superlink {address!r}: a port is 1 to 65535")


def _toml_string(value: str) -> str:
    """``value`` as a TOML string for Flower's ``key=value`` settings (``--node-config``,
    ``--run-config``). Flower finds each value with the pattern ``"[^"]*"`` before reading it
    as TOML, so a ``"`` inside is written as the escape ``\\u0022``, never ``\\"``."""
    out = []
    for char in value:
        if char == "\\":
            out.append("\\\\")
        elif char == '"' or ord(char) < 0x20 or ord(char) == 0x7F:
            out.append(f"\\u{ord(char):04x}")
        else:
            out.append(char)
    return '"' + "".join(out) + '"'
