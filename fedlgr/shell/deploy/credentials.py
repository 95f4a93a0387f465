"""What a deployment needs before it starts: TLS certificates for the SuperLink and an ECDSA key
pair per robot (``fedlgr deploy certs`` / ``node-key``). Every file is created new (``O_EXCL |
O_NOFOLLOW``: never through a symbolic link), private keys 0600 from their first byte."""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import re
import stat
import sys
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import UnsupportedAlgorithm
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from fedlgr.errors import FedlgrError, first_line
from fedlgr.shell.checks.paths import not_a_folder

DEFAULT_HOSTS = ("localhost", "127.0.0.1", "::1")


def check_free(paths, force: bool, replacing: str) -> None:
    """Refuse, before anything is written, a symbolic link at any of ``paths`` (even with ``force``:
    credentials are never written through a link), something there that is not a regular file, and
    an existing file unless ``force`` (``replacing`` says what replacing it does)."""
    for path in paths:
        if path.is_symlink():
            raise FedlgrError(
                f"{path} is a symbolic link: credentials are written as new files only, "
                "never through a link (remove it)"
            )
        if path.exists() and not path.is_file():
            raise FedlgrError(f"{path} exists and is not a regular file (remove it)")
        if path.exists() and not force:
            raise FedlgrError(f"{path} exists: {replacing} (--force replaces it)")


def _write(path: Path, data: bytes, private: bool, force: bool = False) -> None:
    """``data`` as a new file at ``path`` (``O_EXCL | O_NOFOLLOW``: an existing file or a link is
    refused), a private one 0600 from its first byte. ``force`` first removes a regular file there:
    a new inode, so a hard link to the old one keeps the old bytes."""
    if force and path.is_file() and not path.is_symlink():
        path.unlink()
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(path, flags, 0o600 if private else 0o644)
    except FileExistsError:
        raise FedlgrError(
            f"{path} appeared (a file or a symbolic link) while credentials were written: "
            "nothing written to it"
        ) from None
    except OSError as err:
        raise FedlgrError(f"{path}: cannot create it ({err.strerror})") from None
    try:
        with os.fdopen(fd, "wb") as out:
            if private:
                os.fchmod(fd, 0o600)  # exactly 0600 under any umask (it never had more)
            out.write(data)
    except OSError as err:  # a full disk: no half a key left behind
        path.unlink(missing_ok=True)
        raise FedlgrError(f"{path}: cannot write it ({err.strerror})") from None


def _private_bytes(key, encoding) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, encoding, serialization.NoEncryption())


def _folder(folder: Path) -> None:
    """The credentials folder, made 0700: it holds private keys and the roster, which nobody else
    may replace."""
    if why := not_a_folder(folder):  # named as what it is: mkdir would say "File exists"
        raise FedlgrError(f"{folder}: {why}")
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as err:
        raise FedlgrError(f"{folder}: cannot create the folder ({err.strerror})") from None
    # an existing folder's mode is its owner's choice: an open one is warned of, not changed
    warn_if_open(folder, "a public key, the roster or ca.pem")


def warn_if_open(folder: Path, what: str) -> None:
    """A warning when every user can write in ``folder`` - and so replace ``what`` in it -
    unless its sticky bit (as /tmp's) keeps others from replacing files they do not own."""
    mode = folder.stat().st_mode
    if mode & stat.S_IWOTH and not mode & stat.S_ISVTX:
        print(
            f"fedlgr: warning: {folder} can be written by every user (mode "
            f"{stat.S_IMODE(mode):04o}): anyone could replace {what} in it; chmod 700 {folder}",
            file=sys.stderr,
        )


def _names(hosts) -> list[x509.GeneralName]:
    out: list[x509.GeneralName] = []
    for host in hosts:
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            out.append(x509.DNSName(host))
    return out


MAX_DAYS = 3650  # ten years: longer outlives any key and overflows no date
_LABEL = re.compile(r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)")


def is_host(host: str, wildcard: bool = False) -> bool:
    """An IP address, or a DNS name of letters, digits and hyphens (with ``wildcard``, a
    leading ``*.`` allowed), at most 253 long."""
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        pass
    name = host.removeprefix("*.") if wildcard else host
    labels = name.split(".")
    return bool(
        name
        and len(host) <= 253
        and all(_LABEL.fullmatch(p) for p in labels)
        and not labels[-1].isdigit()  # a mistyped address (999.1.1.1), not a name
    )


def check_node_key(path: Path, option: str = "--key") -> None:
    """``path`` holds a robot's private node key (OpenSSH), not its ``.pub`` half or another file,
    which Flower would refuse only in a traceback as the SuperNode starts."""
    try:
        serialization.load_ssh_private_key(path.read_bytes(), password=None)
    except (ValueError, TypeError, UnsupportedAlgorithm) as err:
        half = " (the public half: give NAME, not NAME.pub)" if path.suffix == ".pub" else ""
        raise FedlgrError(
            f"{option} {path}: not a private node key{half}; fedlgr deploy node-key DIR NAME "
            f"writes one ({first_line(err)})"
        ) from None
    except OSError as err:
        raise FedlgrError(f"{option} {path}: cannot read it ({err.strerror})") from None
    check_private_mode(path, option)
    warn_if_open(path.parent, "the key")  # as node-key warns of the folder it writes in
    if path.resolve().parent != path.parent.resolve():  # a link: the key's own folder too
        warn_if_open(path.resolve().parent, "the key")


def check_private_mode(path: Path, option: str) -> None:
    """A private key that others can read or write (a robot's --key, the SuperLink's
    server.key) is refused, as ssh refuses one."""
    mode = stat.S_IMODE(path.stat().st_mode)
    if mode & 0o077:
        raise FedlgrError(
            f"{option} {path}: a private key others can read or write (mode {mode:04o}); "
            f"chmod 600 {path}"
        )


def check_certificates(path: Path, option: str = "--ca") -> None:
    """``path`` holds PEM certificates (a ``ca.pem``), not a key or another file: said in
    one line before Flower starts, not in its traceback."""
    try:
        x509.load_pem_x509_certificates(path.read_bytes())
    except ValueError:
        raise FedlgrError(
            f"{option} {path}: not a PEM certificate (the deployment's ca.pem, made by "
            "fedlgr deploy certs DIR)"
        ) from None
    except OSError as err:
        raise FedlgrError(f"{option} {path}: cannot read it ({err.strerror})") from None


def make_certificates(
    folder: Path, hosts=DEFAULT_HOSTS, days: int = 365, force: bool = False
) -> dict[str, Path]:
    """``ca.pem``, ``ca.key``, ``server.pem``, ``server.key`` in ``folder`` for ``hosts``
    (``force``: replace those files; a symbolic link is refused all the same)."""
    if not 1 <= days <= MAX_DAYS:
        raise FedlgrError(
            f"--days {days}: certificates must be valid for 1 to {MAX_DAYS} days (ten years)"
        )
    for host in hosts:  # a host name or address a TLS client can match (wildcards too)
        if not is_host(host, wildcard=True):
            raise FedlgrError(
                f"--host {host!r}: not an IP address or a DNS name (letters, digits, hyphens and "
                "dots, no trailing dot, labels of at most 63, at most 253 in all; a leading *. "
                "for a wildcard); robots could never match it"
            )
    paths = {name: folder / name for name in ("ca.pem", "ca.key", "server.pem", "server.key")}
    check_free(
        paths.values(), force, "new certificates lock out every robot holding the old ca.pem"
    )
    _folder(folder)
    now = dt.datetime.now(dt.UTC)
    start, end = now - dt.timedelta(minutes=5), now + dt.timedelta(days=days)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "fedlgr deployment CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_cert_sign=True,
                crl_sign=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), False)
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    server = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, hosts[0])]))
        .issuer_name(ca_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.SubjectAlternativeName(_names(hosts)), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), False
        )
        .sign(ca_key, hashes.SHA256())
    )
    pkcs8 = serialization.PrivateFormat.PKCS8
    _write(paths["ca.pem"], ca.public_bytes(serialization.Encoding.PEM), False, force)
    _write(paths["ca.key"], _private_bytes(ca_key, pkcs8), True, force)
    _write(paths["server.pem"], server.public_bytes(serialization.Encoding.PEM), False, force)
    _write(paths["server.key"], _private_bytes(key, pkcs8), True, force)
    return paths


def make_node_key(folder: Path, name: str, force: bool = False) -> tuple[Path, Path]:
    """``folder/name`` (private, OpenSSH) and ``folder/name.pub`` (to register);
    ``force``: replace them (a symbolic link is refused all the same)."""
    private, public = folder / name, folder / f"{name}.pub"
    check_free((private, public), force, "a new key locks that robot out until it is registered")
    _folder(folder)
    key = ec.generate_private_key(ec.SECP384R1())
    _write(private, _private_bytes(key, serialization.PrivateFormat.OpenSSH), True, force)
    openssh = key.public_key().public_bytes(
        serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH
    )
    _write(public, openssh + b"\n", False, force)
    return private, public
