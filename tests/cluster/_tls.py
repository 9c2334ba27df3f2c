"""A certificate authority of a test's own, made with the openssl command line: its certificate
(what clients trust), and server certificates it signs for the names and addresses a test's
servers answer on (HAProxy's edge, PostgreSQL, S3)."""

from __future__ import annotations

import subprocess
from collections.abc import Sequence
from dataclasses import dataclass
from ipaddress import ip_address
from pathlib import Path

from _cluster import tool


@dataclass(frozen=True)
class ServerCertificate:
    cert: Path  # PEM, the leaf
    key: Path  # PEM, unencrypted, mode 0600
    pem: Path  # the leaf, then its key: what HAProxy's `crt` takes


@dataclass(frozen=True)
class Authority:
    """A CA: `ca` is its certificate (PEM), the file clients are told to trust."""

    folder: Path
    ca: Path
    key: Path

    @classmethod
    def make(cls, folder: Path, *, name: str = "jitdyn test CA") -> Authority:
        folder.mkdir(parents=True, exist_ok=True)
        ca, key = folder / "ca.crt", folder / "ca.key"
        _openssl(
            "req", "-x509", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
            "-keyout", str(key), "-out", str(ca), "-days", "2", "-subj", f"/CN={name}",
            "-addext", "basicConstraints=critical,CA:TRUE",
            "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        )  # fmt: skip
        return cls(folder, ca, key)

    def issue(self, name: str, *, hosts: Sequence[str]) -> ServerCertificate:
        """A server certificate for `hosts` (DNS names or IP addresses, in its subjectAltName)."""
        cert, key, request = (self.folder / f"{name}{ext}" for ext in (".crt", ".key", ".csr"))
        names = ",".join(f"IP:{h}" if _is_ip(h) else f"DNS:{h}" for h in hosts)
        extensions = self.folder / f"{name}.ext"
        extensions.write_text(
            f"subjectAltName={names}\nbasicConstraints=CA:FALSE\n"
            "keyUsage=critical,digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth\n"
        )
        _openssl(
            "req", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
            "-keyout", str(key), "-out", str(request), "-subj", f"/CN={hosts[0]}",
        )  # fmt: skip
        _openssl(
            "x509", "-req", "-in", str(request), "-CA", str(self.ca), "-CAkey", str(self.key),
            "-CAcreateserial", "-out", str(cert), "-days", "2", "-extfile", str(extensions),
        )  # fmt: skip
        key.chmod(0o600)
        pem = self.folder / f"{name}.pem"
        pem.write_bytes(cert.read_bytes() + key.read_bytes())
        pem.chmod(0o600)
        return ServerCertificate(cert, key, pem)


def _is_ip(host: str) -> bool:
    try:
        ip_address(host)
    except ValueError:
        return False
    return True


def _openssl(*args: str) -> None:
    done = subprocess.run([tool("openssl"), *args], check=False, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"openssl {args[0]} failed:\n{done.stderr}")
