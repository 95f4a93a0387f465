"""The federation's roster (``deploy.roster``): which robot (name, client slot) holds which public
key, and the most scenes it may claim; the ServerApp sends work only to its nodes, in its slots."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import yaml
from cryptography.exceptions import UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization

from fedlgr.errors import FedlgrError, first_line

ROSTER_NAME = "roster.yaml"
FIELDS = frozenset({"name", "client", "key", "scenes"})  # a robot's entry
HEADER = (
    "# fedlgr's roster: the robots of this federation, their client slots and public keys.\n"
    "# fedlgr deploy node-key adds to it; a Flower run names it with deploy.roster=PATH.\n"
)


def key_der(key: bytes | str) -> bytes:
    """A public key (OpenSSH, as in ``NAME.pub``, or PEM, as Flower keeps it) as DER
    SubjectPublicKeyInfo: one spelling to compare."""
    data = key.encode() if isinstance(key, str) else bytes(key)
    if data.lstrip().startswith(b"-----BEGIN"):
        public = serialization.load_pem_public_key(data)
    else:
        public = serialization.load_ssh_public_key(data.strip())
    return public.public_bytes(
        serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    )


def fingerprint(key: bytes | str) -> str:
    """Short and stable: the first 16 hex digits of the key's SHA-256."""
    return hashlib.sha256(key_der(key)).hexdigest()[:16]


@dataclass(frozen=True)
class Member:
    name: str
    client: int
    key: str  # the OpenSSH public key line
    scenes: int | None = None  # the most training scenes it holds (None: not bounded)

    def __str__(self) -> str:
        return f"{self.name} (client {self.client})"


class Roster:
    def __init__(self, members: list[Member], path: Path | None = None):
        self.members, self.path = list(members), path

    @classmethod
    def read(cls, path: Path | str) -> Roster:
        path = Path(path)
        if not path.is_file():
            raise FedlgrError(
                f"roster {path}: no such file (fedlgr deploy node-key DIR NAME writes "
                f"DIR/{ROSTER_NAME})"
            )
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except (yaml.YAMLError, UnicodeDecodeError) as err:
            first = first_line(err)
            raise FedlgrError(f"roster {path}: not valid YAML ({first})") from None
        except RecursionError:  # thousands of nested levels: no roster fedlgr writes
            raise FedlgrError(f"roster {path}: nested too deeply to be a roster") from None
        entries = data.get("robots") if isinstance(data, dict) else None
        if not isinstance(entries, list):
            raise FedlgrError(f"roster {path}: expected 'robots:' and a list of robots")
        members = [_member(path, i, entry) for i, entry in enumerate(entries)]
        _check_unique(path, members)
        return cls(members, path)

    @classmethod
    def read_or_empty(cls, path: Path) -> Roster:
        return cls.read(path) if path.exists() else cls([], path)

    def write(self, path: Path | None = None) -> Path:
        """All of it, replacing the file at once (a reader never sees half a roster)."""
        path = Path(path or self.path)
        rows = [
            {"name": m.name, "client": m.client, "key": m.key}
            | ({} if m.scenes is None else {"scenes": m.scenes})
            for m in self.members
        ]
        text = HEADER + yaml.safe_dump({"robots": rows}, sort_keys=False, width=1000)
        partial = path.with_name(f".{path.name}.partial")
        partial.unlink(missing_ok=True)
        fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
        with os.fdopen(fd, "w") as f:
            f.write(text)
        partial.replace(path)
        return path

    def add(self, name: str, key: str, client: int | None = None) -> Member:
        """A new robot (a name already there is replaced: a new key for that robot keeps
        its slot unless ``client`` says otherwise); ``client`` None: the lowest free slot."""
        old = next((m for m in self.members if m.name == name), None)
        others = [m for m in self.members if m.name != name]
        if client is None:
            client = old.client if old is not None else _lowest_free(others)
        taken = next((m for m in others if m.client == client), None)
        if taken is not None:
            raise FedlgrError(f"--client {client}: {taken} holds that slot in {self.path}")
        member = Member(name, client, key.strip(), old.scenes if old is not None else None)
        self.members = sorted([*others, member], key=lambda m: m.client)
        return member

    def member(self, public_key: bytes | str) -> Member | None:
        """The robot that holds ``public_key`` (None: not on the roster, or not a key)."""
        if not public_key:
            return None
        try:
            der = key_der(public_key)
        except (ValueError, TypeError, UnsupportedAlgorithm):
            return None
        return next((m for m in self.members if key_der(m.key) == der), None)

    @property
    def capacity(self) -> dict[int, int]:
        """client -> the most training scenes its robot holds, where the roster says."""
        return {m.client: m.scenes for m in self.members if m.scenes is not None}


def _member(path: Path, index: int, entry) -> Member:
    where = f"roster {path}: robot {index + 1}"
    if not isinstance(entry, dict) or not {"name", "client", "key"} <= set(entry) <= FIELDS:
        raise FedlgrError(f"{where}: expected name, client and key (and scenes, optional)")
    name, client, key = entry["name"], entry["client"], entry["key"]
    if not isinstance(name, str) or not name:
        raise FedlgrError(f"{where}: name must be a non-empty string")
    if isinstance(client, bool) or not isinstance(client, int) or client < 0:
        raise FedlgrError(f"{where} ({name}): client must be an integer >= 0, not {client!r}")
    scenes = entry.get("scenes")
    if scenes is not None and (
        isinstance(scenes, bool) or not isinstance(scenes, int) or scenes < 1
    ):
        raise FedlgrError(f"{where} ({name}): scenes must be an integer >= 1, not {scenes!r}")
    try:
        key_der(str(key))
    except (ValueError, TypeError, UnsupportedAlgorithm) as err:
        raise FedlgrError(f"{where} ({name}): key is not a public key ({err})") from None
    return Member(name, client, str(key).strip(), scenes)


def _check_unique(path: Path, members: list[Member]) -> None:
    for clash, value in (
        ("share a name", lambda m: m.name),
        ("share a client", lambda m: m.client),
        ("hold the same key", lambda m: key_der(m.key)),
    ):
        seen: dict = {}
        for m in members:
            if value(m) in seen:
                raise FedlgrError(f"roster {path}: {seen[value(m)]} and {m} {clash}")
            seen[value(m)] = m


def _lowest_free(members: list[Member]) -> int:
    held = {m.client for m in members}
    return next(c for c in range(len(held) + 1) if c not in held)


def roster_of(config) -> Roster | None:
    """A Flower run's roster (``deploy.roster``), checked against ``data.clients``; None for
    ``none`` (any node that joins takes part, as the client its SuperNode names)."""
    path = config.deploy.roster
    if path is None:
        raise FedlgrError(
            "deploy.roster is not set: a Flower run takes part only the robots of a roster "
            "(fedlgr deploy node-key DIR NAME writes DIR/roster.yaml; deploy.roster=PATH), "
            "or deploy.roster=none on a test machine without SuperNode authentication"
        )
    if path == "none":
        return None
    roster, clients = Roster.read(path), config.data.clients
    held = {m.client for m in roster.members}
    if missing := [c for c in range(clients) if c not in held]:  # every client has a robot
        raise FedlgrError(
            f"roster {roster.path}: no robot for client {', '.join(map(str, missing))} of "
            f"data.clients={clients} (fedlgr deploy node-key DIR NAME --client K adds one)"
        )
    return roster
