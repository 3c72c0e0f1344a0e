"""Throwaway certificates for the secured zenoh configurations (tests, benchmarks).

``make_pki(root)`` runs the ``openssl`` commands of docs/security.md step 1 with 2-day
certificates and the server's ``subjectAltName`` ``IP:127.0.0.1,DNS:localhost``; nothing
it makes is ever committed (callers put it in a temporary folder). ``materialize`` fills
the placeholders of an example of ``configs/zenoh``.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

from simserver.testing import CONFIGS

ZENOH_EXAMPLES = CONFIGS / "zenoh"
PLACEHOLDER_DIR = "/etc/simserver/"


def _openssl(*args: str, cwd: Path) -> None:
    proc = subprocess.run(["openssl", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=60)
    if proc.returncode != 0:
        raise RuntimeError(f"openssl {' '.join(args)} failed:\n{proc.stderr}")


def _issue(tls: Path, name: str, cn: str, ca: str, ext: str) -> None:
    """Key and certificate ``name.key``/``name.pem`` for ``cn``, signed by ``ca``."""
    _openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key", "-out",
             f"{name}.csr", "-subj", f"/CN={cn}", cwd=tls)
    (tls / f"{name}.ext").write_text(ext, encoding="ascii")
    _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key",
             "-CAcreateserial", "-out", f"{name}.pem", "-days", "2", "-extfile",
             f"{name}.ext", cwd=tls)


def make_pki(root: Path) -> Path:
    """A throwaway CA, a server certificate for 127.0.0.1/localhost, client certificates.

    Layout (as the example configs expect under ``/etc/simserver/``): ``tls/ca.pem``,
    ``tls/server.{key,pem}``, ``tls/driver.{key,pem}`` (CN driver), ``tls/viewer.{key,pem}``
    (CN viewer), and ``tls/rogue.{key,pem}`` (CN driver, signed by another CA).
    """
    tls = root / "tls"
    tls.mkdir(parents=True)
    for ca, cn in (("ca", "simserver test CA"), ("rogue_ca", "someone else's CA")):
        _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{ca}.key",
                 "-out", f"{ca}.pem", "-days", "2", "-subj", f"/CN={cn}",
                 "-addext", "basicConstraints=critical,CA:TRUE",
                 "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=tls)
    server_ext = ("subjectAltName=IP:127.0.0.1,DNS:localhost\nbasicConstraints=CA:FALSE\n"
                  "keyUsage=digitalSignature,keyEncipherment\n"
                  "extendedKeyUsage=serverAuth,clientAuth\n")
    client_ext = ("basicConstraints=CA:FALSE\nkeyUsage=digitalSignature,keyEncipherment\n"
                  "extendedKeyUsage=clientAuth\n")
    _issue(tls, "server", "simserver", "ca", server_ext)
    _issue(tls, "driver", "driver", "ca", client_ext)
    _issue(tls, "viewer", "viewer", "ca", client_ext)
    _issue(tls, "rogue", "driver", "rogue_ca", client_ext)
    for key in tls.glob("*.key"):
        key.chmod(0o600)
    return root


def materialize(example: str, pki_root: Path, out_name: str | None = None,
                replace: dict[str, str] | None = None) -> Path:
    """An example config of ``configs/zenoh`` with its placeholders filled in."""
    text = (ZENOH_EXAMPLES / example).read_text(encoding="utf-8")
    for old, new in (replace or {}).items():
        assert old in text, f"{example} has no placeholder {old!r}"
        text = text.replace(old, new)
    text = text.replace(PLACEHOLDER_DIR, f"{pki_root}/")
    path = pki_root / (out_name or example)
    path.write_text(text, encoding="utf-8")
    path.chmod(0o600)
    return path
