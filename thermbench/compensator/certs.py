"""``thermbench certs OUT_DIR``: self-signed application certificates for OPC UA
``Basic256Sha256`` sign-and-encrypt (OPC 10000-6 §6.2.2), made with asyncua's
certificate generator: ``server_cert.der`` / ``server_key.pem`` for ``sim-cnc`` (or to
trust on a real controller) and ``client_cert.der`` / ``client_key.pem`` for the
compensator. Each names its application URI and this host (name, localhost, 127.0.0.1).
Existing files are never overwritten; every file is written atomically.
"""

from __future__ import annotations

import ipaddress
import socket
from pathlib import Path

from ..outputs import check_output_file, output_file
from .opcua import CLIENT_APP_URI
from .simcnc import SERVER_APP_URI

FILES = {"server": ("server_cert.der", "server_key.pem", SERVER_APP_URI),
         "client": ("client_cert.der", "client_key.pem", CLIENT_APP_URI)}  # fmt: skip


def make_certificates(out_dir: str | Path, days: int = 365, host: str | None = None) -> dict[str, Path]:
    from asyncua.crypto.cert_gen import dump_private_key_as_pem, generate_private_key, generate_self_signed_app_certificate
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding
    from cryptography.x509.oid import ExtendedKeyUsageOID

    out = Path(out_dir)
    taken = [str(out / f) for pair in FILES.values() for f in pair[:2] if (out / f).exists()]
    if taken:
        raise FileExistsError(f"{out}: {taken} exist already; certificates are never overwritten (remove them or pick another directory)")
    for pair in FILES.values():  # a dataset or another output there is refused before any key is made
        for f in pair[:2]:
            check_output_file(out / f, "certificate")
    out.mkdir(parents=True, exist_ok=True)
    host = host or socket.gethostname()
    written = {}
    for role, (cert_name, key_name, uri) in FILES.items():
        key = generate_private_key()
        sans = [x509.UniformResourceIdentifier(uri), x509.DNSName(host), x509.DNSName("localhost"),
                x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]  # fmt: skip
        use = [ExtendedKeyUsageOID.SERVER_AUTH] if role == "server" else [ExtendedKeyUsageOID.CLIENT_AUTH]
        cert = generate_self_signed_app_certificate(key, f"thermbench {role}", {"organizationName": "thermbench"}, sans, use,
                                                    days=days)  # fmt: skip
        with output_file(out / key_name, "private-key", mode=0o600) as tmp:  # private from the start
            tmp.write_bytes(dump_private_key_as_pem(key))
        with output_file(out / cert_name, "certificate") as tmp:
            tmp.write_bytes(cert.public_bytes(Encoding.DER))
        written[f"{role}_certificate"], written[f"{role}_private_key"] = out / cert_name, out / key_name
    return written
