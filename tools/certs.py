"""Development PKI and credentials for secured Zenoh links (`aero certs`).

Writes a CA, a server certificate for the router and one client certificate per role (CN = role
name, which the router's access_control matches as `cert_common_names`), a user/password
dictionary for Zenoh's usrpwd authentication, and ready-to-use Zenoh configs made from the
templates in tools/secure/ (deploy/secure/ in a checkout) with absolute paths and the generated
passwords filled in. For development and tests: a production CA keeps its key offline and
issues certificates per host (docs/deploy.md, "Secured links").
"""
from __future__ import annotations

import datetime as dt
import ipaddress
import os
import secrets
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

TEMPLATES = Path(__file__).resolve().with_name("secure")
ROLES = ("vehicle", "ground")          # client identities: certificate CN == usrpwd user name
CERTS_PLACEHOLDER = "/etc/aero/certs"  # the templates' certificate folder, replaced by --out
PASSWORD_PLACEHOLDER = "CHANGE-ME-{role}"
VALID_DAYS = 365


@dataclass
class Issued:
    out: Path
    files: list[Path]
    passwords: dict[str, str]


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "AeroPerception dev"),
                      x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _builder(subject: str, issuer: x509.Name, public_key, days: int) -> x509.CertificateBuilder:
    now = dt.datetime.now(dt.timezone.utc)
    return (x509.CertificateBuilder().subject_name(_name(subject)).issuer_name(issuer)
            .public_key(public_key).serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days)))


def make_ca(days: int = VALID_DAYS) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    key = _key()
    cert = (_builder("AeroPerception dev CA", _name("AeroPerception dev CA"), key.public_key(), days)
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False,
                                         encipher_only=False, decipher_only=False), critical=True)
            .sign(key, hashes.SHA256()))
    return key, cert


def issue(ca_key, ca_cert: x509.Certificate, cn: str, hosts: list[str] = (), server: bool = False,
          days: int = VALID_DAYS) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A leaf certificate: CN `cn`, SANs `hosts` (DNS names or IP addresses) for a server."""
    key = _key()
    b = (_builder(cn, ca_cert.subject, key.public_key(), days)
         .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
         .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH if server
                                               else ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False))
    sans: list[x509.GeneralName] = []
    for h in hosts:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            sans.append(x509.DNSName(h))
    if not sans:  # rustls (Zenoh) wants a SAN on every end-entity certificate
        sans.append(x509.DNSName(cn))
    b = b.add_extension(x509.SubjectAlternativeName(sans), critical=False)
    return key, b.sign(ca_key, hashes.SHA256())


def _write(path: Path, data: bytes, private: bool = False) -> Path:
    path.write_bytes(data)
    if private:
        os.chmod(path, 0o600)
    return path


def _pem_key(key) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _pem_cert(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def render_config(template: str, out: Path, passwords: dict[str, str]) -> str:
    """A template from tools/secure/ with the certificate folder and passwords filled in."""
    text = template.replace(CERTS_PLACEHOLDER, str(out))
    for role, pw in passwords.items():
        text = text.replace(PASSWORD_PLACEHOLDER.format(role=role), pw)
    return text


def create(out: Path, hosts: list[str], days: int = VALID_DAYS, force: bool = False) -> Issued:
    """Write the CA, router and role certificates, users.txt and the three Zenoh configs to `out`."""
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    if (out / "ca.pem").exists() and not force:
        raise FileExistsError(f"{out / 'ca.pem'} exists")
    files: list[Path] = []
    ca_key, ca_cert = make_ca(days)
    files += [_write(out / "ca.pem", _pem_cert(ca_cert)), _write(out / "ca.key", _pem_key(ca_key), True)]
    r_key, r_cert = issue(ca_key, ca_cert, "router", hosts=hosts, server=True, days=days)
    files += [_write(out / "router.pem", _pem_cert(r_cert)), _write(out / "router.key", _pem_key(r_key), True)]
    for role in ROLES:
        k, c = issue(ca_key, ca_cert, role, days=days)
        files += [_write(out / f"{role}.pem", _pem_cert(c)), _write(out / f"{role}.key", _pem_key(k), True)]
    passwords = {role: secrets.token_urlsafe(18) for role in ROLES}
    files.append(_write(out / "users.txt", "".join(f"{r}:{p}\n" for r, p in passwords.items()).encode(), True))
    for template in sorted(TEMPLATES.glob("*.json5")):
        files.append(_write(out / template.name, render_config(template.read_text(), out, passwords).encode(),
                            private=True))
    return Issued(out, files, passwords)
