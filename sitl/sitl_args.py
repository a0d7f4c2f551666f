"""`fcemu sitl`'s MAVLink arguments checked before anything starts: every peer an address the
vehicle can send to, a signing key wherever a peer is marked :signed, and every file the flight
reads or writes (signing key, tlog, parameter file) opened here, in the parent, so that a bad one
is one `fcemu: error:` line instead of a MAVLink process that dies after the flight has started."""

from __future__ import annotations

import ipaddress
import os
import re
import socket
import sys
import tempfile
from pathlib import Path

from fcemu.firmware.errors import UserError
from fcemu.firmware.mavlink.bridge import PeerConfig, parse_peer

_DOTTED_NUMBERS = re.compile(r"^[0-9.]+$")


def resolve_host(host: str) -> str:
    """The IPv4 address of `host` (an IPv4 address or a name that resolves to one); ValueError if none."""
    if _DOTTED_NUMBERS.match(host):
        try:
            return str(ipaddress.IPv4Address(host))
        except ValueError:
            raise ValueError(f"{host} is not an IPv4 address") from None
    try:
        infos = socket.getaddrinfo(host, None, socket.AF_INET, socket.SOCK_DGRAM)
    except (socket.gaierror, UnicodeError) as exc:
        reason = exc.strerror if isinstance(exc, socket.gaierror) and exc.strerror else str(exc)
        raise ValueError(f"host {host} does not resolve to an IPv4 address ({reason.lower()})") from None
    return str(infos[0][4][0])


def checked_peer(spec: str, name: str) -> PeerConfig:
    """parse_peer, with the host resolved once here (the MAVLink process sends to the address)."""
    try:
        peer = parse_peer(spec, name)
    except ValueError:
        port = spec.removesuffix(":signed").rpartition(":")[2]
        if port.isdigit() and not 0 < int(port) < 65536:
            raise ValueError(f"bad peer {spec!r}: port {port} is not in 1..65535") from None
        raise
    try:
        peer.host = resolve_host(peer.host)
    except ValueError as exc:
        raise ValueError(f"bad peer {spec!r}: {exc}") from None
    return peer


def _reason(exc: OSError) -> str:
    return (exc.strerror or type(exc).__name__).lower()


def check_signing_key(path: str) -> None:
    from fcemu.firmware.mavlink.endpoint import load_signing_key

    where = Path(path)
    try:
        if where.exists() and not where.is_file():
            raise UserError(f"--signing-key {path}: not a regular file")
        load_signing_key(where)
    except OSError as exc:
        raise UserError(f"--signing-key {path}: cannot read it ({_reason(exc)})") from None
    except (UnicodeDecodeError, ValueError):
        raise UserError(f"--signing-key {path}: not a signing key (32 bytes, 64 hex digits or a "
                        "passphrase)") from None


def check_writable(option: str, path: str) -> None:
    """The file (and its folder) can be created where asked; one made only to find out is removed
    again, so nothing is left behind should something else fail before the flight writes it."""
    existed = os.path.lexists(path)
    try:
        if Path(path).is_dir():
            raise IsADirectoryError(21, "Is a directory")
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC, 0o644))
        if not existed:
            os.unlink(path)
    except OSError as exc:
        raise UserError(f"{option} {path}: cannot write it ({_reason(exc)})") from None


def check_tlog(path: str) -> None:
    """The tlog: the flight opens it for the MAVLink process (bridge.open_for_mavlink)."""
    check_writable("--tlog", path)


def check_ulog(path: str) -> None:
    """The ULog: written when the flight ends, too late to say it cannot be."""
    check_writable("--ulog", path)


def check_params_file(path: str) -> None:
    """The parameter file is saved by writing a file beside it and renaming it over: that must work."""
    where = Path(path)
    try:
        if where.is_dir():
            raise IsADirectoryError(21, "Is a directory")
        where.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(prefix=f".{where.name}.", dir=where.parent):
            pass
    except OSError as exc:
        raise UserError(f"--params {path}: cannot save parameters there ({_reason(exc)}); "
                        "'--params \"\"' flies without a parameter file") from None


def check_mavlink_files(args, params_file: str | None) -> None:
    """The files the flight reads or writes. A default parameter file that cannot be saved only warns."""
    if args.signing_key:
        check_signing_key(args.signing_key)
    if args.tlog:
        check_tlog(args.tlog)
    if params_file:
        try:
            check_params_file(params_file)
        except UserError as exc:
            if args.params is not None:
                raise
            print(f"fcemu: warning: {str(exc).removeprefix('--params ').split(';')[0]}; parameter "
                  "changes will not persist", file=sys.stderr)


def check_signed_peers(options: list[tuple[str, str]], peers: list[PeerConfig], signing_key: str | None
                       ) -> None:
    """A peer marked :signed is refused unsigned traffic only with a key to sign with."""
    if signing_key:
        return
    for (option, spec), peer in zip(options, peers, strict=True):
        if peer.signed:
            raise UserError(f"{option} {spec}: a :signed peer needs --signing-key")


MAVLINK_OPTIONS = ("gcs", "offboard", "peer", "sysid", "tlog", "signing_key", "params")


def refuse_mavlink_options(args) -> None:
    """--no-mavlink flies without the MAVLink process: an option for it would be silently ignored."""
    given = [f"--{name.replace('_', '-')}" for name in MAVLINK_OPTIONS
             if getattr(args, name, None) is not None]
    if given:
        verb = "sets" if len(given) == 1 else "set"
        raise UserError(f"{' and '.join(given)} {verb} up MAVLink, which --no-mavlink turns off")
