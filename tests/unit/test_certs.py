"""`aero certs` output (tools/certs.py): a CA that signs the router and role certificates with
the names the router's access control and the clients' name check rely on."""
import ipaddress

import zenoh
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from aeroperception.tools import certs


def _cert(path):
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_certs_are_signed_by_the_ca_with_role_names_and_router_hosts(tmp_path):
    issued = certs.create(tmp_path, ["localhost", "10.77.0.2"])
    ca = _cert(tmp_path / "ca.pem")
    for name in ("router", *certs.ROLES):
        c = _cert(tmp_path / f"{name}.pem")
        ca.public_key().verify(c.signature, c.tbs_certificate_bytes, ec.ECDSA(c.signature_hash_algorithm))
        assert c.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == name
    sans = _cert(tmp_path / "router.pem").extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert sans.get_values_for_type(x509.DNSName) == ["localhost"]
    assert sans.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("10.77.0.2")]
    users = dict(line.split(":", 1) for line in (tmp_path / "users.txt").read_text().split())
    assert users == issued.passwords and len(set(users.values())) == 2
    assert (tmp_path / "ca.key").stat().st_mode & 0o077 == 0


def test_rendered_configs_are_valid_zenoh_configs_with_nothing_left_to_fill(tmp_path):
    issued = certs.create(tmp_path, ["localhost"])
    for name in ("router", *certs.ROLES):
        text = (tmp_path / f"{name}.json5").read_text()
        assert certs.CERTS_PLACEHOLDER not in text and "CHANGE-ME" not in text
        zenoh.Config.from_file(str(tmp_path / f"{name}.json5"))
    assert issued.passwords["ground"] in (tmp_path / "ground.json5").read_text()
    assert issued.passwords["vehicle"] not in (tmp_path / "ground.json5").read_text()
