"""Certificates and zenoh security configs for a fleet: mutual TLS and access control.

A small certificate authority for a site (one CA, one certificate per router and per fleet
member; the certificate's common name is who the member is for zenoh's access control)::

    python -m stack.comm.tls ca   certs/                       # certs/ca.pem, certs/ca.key
    python -m stack.comm.tls issue certs/ router-a --cn router.site-a --ip 192.0.2.1 --dns router-a.local
    python -m stack.comm.tls issue certs/ robot-3 --cn fleet-a.robot-3

and the zenoh json5 blocks that use them (:func:`tls_block`, :func:`acl_block`,
:func:`write_config`), the same shape as ``deploy/*.json5``. ``cryptography`` is imported only
here, only when certificates are made (``pip install 'formation-stack[test]'`` or
``pip install cryptography``); openssl makes equivalent files (``docs/deploy.md``).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import ipaddress
import json
import sys
from pathlib import Path

#: every message type zenoh 1.x access control knows (rules list the ones they allow)
ACL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
                "liveliness_token", "declare_liveliness_subscriber", "liveliness_query")


def _crypto():
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    except ImportError:  # pragma: no cover - depends on the install
        raise SystemExit("stack.comm.tls: needs the 'cryptography' package (pip install cryptography)") from None
    return x509, hashes, serialization, ec, NameOID, ExtendedKeyUsageOID


def _write(path: Path, data: bytes, private: bool = False) -> None:
    path.write_bytes(data)
    if private:
        path.chmod(0o600)


def make_ca(folder: str | Path, common_name: str = "formation-stack site CA", days: int = 3650) -> tuple[Path, Path]:
    """A self-signed CA: ``folder/ca.pem`` and ``folder/ca.key``; returns both paths."""
    x509, hashes, serialization, ec, NameOID, _ = _crypto()
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    now = _dt.datetime.now(_dt.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - _dt.timedelta(minutes=5)).not_valid_after(now + _dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                                         key_encipherment=False, data_encipherment=False, key_agreement=False,
                                         encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    _write(folder / "ca.pem", cert.public_bytes(serialization.Encoding.PEM))
    _write(folder / "ca.key", key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                serialization.NoEncryption()), private=True)
    return folder / "ca.pem", folder / "ca.key"


def issue(folder: str | Path, name: str, common_name: str, ips: tuple[str, ...] | list[str] = (),
          dns: tuple[str, ...] | list[str] = (), days: int = 825) -> tuple[Path, Path]:
    """A certificate signed by ``folder/ca.{pem,key}``: ``folder/<name>.pem`` and ``.key``.

    Usable as a server (routers: listen) and a client (agents, routers meshing: connect);
    ``ips``/``dns`` become subject alternative names, which a connecting side checks against
    the endpoint's host (``verify_name_on_connect``). Loopback is always included.
    """
    x509, hashes, serialization, ec, NameOID, EKU = _crypto()
    folder = Path(folder)
    ca_cert = x509.load_pem_x509_certificate((folder / "ca.pem").read_bytes())
    ca_key = serialization.load_pem_private_key((folder / "ca.key").read_bytes(), password=None)
    key = ec.generate_private_key(ec.SECP256R1())
    now = _dt.datetime.now(_dt.timezone.utc)
    sans = [x509.DNSName("localhost")] + [x509.DNSName(d) for d in dns]
    sans += [x509.IPAddress(ipaddress.ip_address(i)) for i in dict.fromkeys(["127.0.0.1", *ips])]
    cert = (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
            .issuer_name(ca_cert.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - _dt.timedelta(minutes=5)).not_valid_after(now + _dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(x509.ExtendedKeyUsage([EKU.SERVER_AUTH, EKU.CLIENT_AUTH]), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))
    pem, keyfile = folder / f"{name}.pem", folder / f"{name}.key"
    _write(pem, cert.public_bytes(serialization.Encoding.PEM))
    _write(keyfile, key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                      serialization.NoEncryption()), private=True)
    return pem, keyfile


def tls_block(ca: str | Path, cert: str | Path, key: str | Path, verify_name: bool = True) -> dict:
    """``transport.link.tls`` for mutual TLS: the same certificate to listen (routers) and to connect."""
    return {"root_ca_certificate": str(ca),
            "listen_private_key": str(key), "listen_certificate": str(cert),
            "connect_private_key": str(key), "connect_certificate": str(cert),
            "enable_mtls": True, "verify_name_on_connect": verify_name}


def acl_block(fleets: dict[str, list[str]], routers: list[str]) -> dict:
    """Access control for a site router: deny by default.

    Each fleet's members (certificate common names) may do anything under ``stack/<fleet>/**``
    and nothing else, so one fleet can neither publish into another (``cmd_vel``, ``state``, ...)
    nor subscribe to it; the site's routers (their common names) may exchange everything with
    each other (the mesh carries every fleet).
    """
    rules = [{"id": "router-mesh", "messages": list(ACL_MESSAGES), "flows": ["ingress", "egress"],
              "permission": "allow", "key_exprs": ["**"]}]
    subjects = [{"id": "routers", "cert_common_names": list(routers)}] if routers else []
    policies = [{"id": "routers", "rules": ["router-mesh"], "subjects": ["routers"]}] if routers else []
    for fleet, members in fleets.items():
        rules.append({"id": f"fleet-{fleet}", "messages": list(ACL_MESSAGES), "flows": ["ingress", "egress"],
                      "permission": "allow", "key_exprs": [f"stack/{fleet}/**"]})
        subjects.append({"id": f"fleet-{fleet}", "cert_common_names": list(members)})
        policies.append({"id": f"fleet-{fleet}", "rules": [f"fleet-{fleet}"], "subjects": [f"fleet-{fleet}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def write_config(path: str | Path, tls: dict | None = None, acl: dict | None = None) -> Path:
    """A zenoh json5 file (plain JSON is json5) with these blocks, for ``--zenoh-config`` / ``--config``."""
    conf: dict = {}
    if tls is not None:
        conf["transport"] = {"link": {"tls": tls}}
    if acl is not None:
        conf["access_control"] = acl
    path = Path(path)
    path.write_text(json.dumps(conf, indent=2) + "\n")
    return path


def cli(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m stack.comm.tls", description="A site CA and its certificates (mutual TLS).")
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("ca", help="make FOLDER/ca.pem and FOLDER/ca.key")
    c.add_argument("folder")
    c.add_argument("--cn", default="formation-stack site CA")
    i = sub.add_parser("issue", help="make FOLDER/NAME.pem and FOLDER/NAME.key, signed by FOLDER/ca.*")
    i.add_argument("folder")
    i.add_argument("name")
    i.add_argument("--cn", required=True, help="common name: who this is for access control (e.g. fleet-a.robot-3)")
    i.add_argument("--ip", action="append", default=[], help="an address the holder listens on (routers; repeatable)")
    i.add_argument("--dns", action="append", default=[], help="a host name the holder listens on (repeatable)")
    a = ap.parse_args(argv)
    try:
        if a.cmd == "ca":
            if (Path(a.folder) / "ca.key").exists():
                print(f"{ap.prog}: {Path(a.folder) / 'ca.key'} exists; not overwriting a CA", file=sys.stderr)
                return 2
            for p in make_ca(a.folder, a.cn):
                print(p)
        else:
            for p in issue(a.folder, a.name, a.cn, a.ip, a.dns):
                print(p)
    except (OSError, ValueError) as e:
        print(f"{ap.prog}: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(cli())
