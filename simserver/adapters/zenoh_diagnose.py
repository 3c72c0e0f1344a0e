"""Why a zenoh session did not reach its server: what the server wants that this client
lacks (issue 35 item 3).

zenoh 1.10 says the same "Unable to connect to any of [...]" whether nothing listens,
the server speaks TLS and the client plain TCP, the client does not trust the server's
CA, the server wants a client certificate, or it refused the client's credentials; and a
peer-mode client (``simserver view``) opens its session anyway and then waits for a
server it cannot reach. :func:`explain` finds out which, after the failure, from the
client's own config and a few probes of its connect endpoints:

1. a TCP connect: refused (nothing listens) or no answer;
2. a TLS handshake that checks nothing (Python's ``ssl``): the server speaks TLS or not,
   against the endpoint's protocol (``tcp/`` to a TLS server: "it speaks TLS");
3. for ``tls/``: the same handshake checked against the client's CA file
   (``transport/link/tls/root_ca_certificate``, or the system's roots when it names
   none, as zenoh does) and its name check; then whether the server asks for a client
   certificate (it ends the link with a ``certificate required`` alert);
4. the TLS link fine: the server refused the zenoh session itself, so credentials
   (``transport/auth/usrpwd``): none in the client's config; or, when it has some, a
   session opened with the same config without them tells "the server wants none" from
   "it refused these".

Each probe completes or fails one handshake, as the client's own attempt did: nothing
here is sent that a client would not send (no credentials but the client's own).
"""

from __future__ import annotations

import contextlib
import json
import socket
import ssl
from typing import Any

PROBE_TIMEOUT_S = 2.0
"""A probe's connect and handshake each wait at most this long."""
ALERT_WAIT_S = 0.5
"""After a TLS 1.3 handshake the server's verdict on a client certificate arrives as an
alert on the first read; no data within this long means no alert (a zenoh listener waits
for the client's first message)."""
MAX_ENDPOINTS = 3
"""At most this many connect endpoints are probed (one line each)."""

EXAMPLES = "configs/zenoh"


def _get(cfg: Any, key: str) -> Any:
    try:
        return json.loads(cfg.get_json(key))
    except Exception:  # noqa: BLE001 - a key this zenoh does not know: unset
        return None


def _split(endpoint: str) -> tuple[str, str, int] | None:
    """``proto/host:port[?...][#...]`` -> (proto, host, port), or None if not tcp/tls."""
    proto, _, rest = endpoint.partition("/")
    rest = rest.split("?", 1)[0].split("#", 1)[0]
    host, sep, port = rest.rpartition(":")
    if proto not in ("tcp", "tls") or not sep or not port.isdigit():
        return None
    return proto, host.strip("[]"), int(port)


def _tls_probe(host: str, port: int, context: ssl.SSLContext,
               wait_alert: bool = False) -> tuple[str, str]:
    """One TLS handshake: ("ok", ""), ("refused"/"timeout", why), ("not_tls", why),
    ("verify", why), ("alert", why: the server's alert after the handshake)."""
    try:
        raw = socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S)
    except ConnectionRefusedError:
        return "refused", "connection refused"
    except TimeoutError:
        return "timeout", "no answer"
    except OSError as exc:
        return "refused", exc.strerror or str(exc)
    with raw:
        try:
            # an address as the name: ssl sends no SNI for it and matches it against
            # the certificate's IP entries, as zenoh does
            with context.wrap_socket(raw, server_hostname=host) as tls:
                if wait_alert:
                    tls.settimeout(ALERT_WAIT_S)
                    try:
                        tls.recv(1)
                    except TimeoutError:
                        pass  # nothing to say: no alert
                    except ssl.SSLError as exc:
                        return "alert", exc.reason or str(exc)
                    except OSError:
                        pass
                return "ok", ""
        except ssl.SSLCertVerificationError as exc:
            return "verify", exc.verify_message or exc.reason or str(exc)
        except ssl.SSLError as exc:
            return "not_tls", exc.reason or str(exc)
        except TimeoutError:
            return "not_tls", "no TLS answer"
        except OSError as exc:
            return "not_tls", exc.strerror or str(exc)


def _unchecked() -> ssl.SSLContext:
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE
    return ctx


def _checked(ca_file: str | None, check_name: bool,
             cert: tuple[str, str] | None = None) -> ssl.SSLContext:
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    if ca_file:
        ctx.load_verify_locations(cafile=ca_file)
    else:
        ctx.load_default_certs()
    ctx.check_hostname = check_name
    if cert is not None:
        ctx.load_cert_chain(certfile=cert[0], keyfile=cert[1])
    return ctx


def _without_credentials_opens(cfg: Any, endpoint: str) -> bool:
    """Whether a client session with ``cfg`` minus its user/password opens at
    ``endpoint`` (client mode fails to open when refused)."""
    import zenoh

    try:
        trial = zenoh.Config.from_json5(str(cfg))
        trial.insert_json5("transport/auth/usrpwd", json.dumps({"user": None,
                                                               "password": None}))
        trial.insert_json5("mode", '"client"')
        trial.insert_json5("connect/endpoints", json.dumps([endpoint]))
        trial.insert_json5("listen/endpoints", "[]")
        with zenoh.open(trial):
            return True
    except Exception:  # noqa: BLE001 - refused, or a config this cannot copy
        return False


def explain_endpoint(cfg: Any, endpoint: str, session_tried: bool = True) -> str | None:
    """What the server at ``endpoint`` wants that the client config ``cfg`` lacks; None
    when the probes find nothing wrong (or the endpoint is not tcp/tls).

    Parameters
    ----------
    cfg : zenoh.Config
        The client's config (its TLS and credentials settings are read).
    endpoint : str
        One of its connect endpoints.
    session_tried : bool
        True when a client-mode session with ``cfg`` failed to open (then a TLS link that
        is fine points at the credentials); False for a peer that opened but reached no
        server (its links are not known to have failed).
    """
    parts = _split(endpoint)
    if parts is None:
        return None
    proto, host, port = parts
    where = f"{host}:{port}"
    kind, why = _tls_probe(host, port, _unchecked())
    if kind == "refused":
        return f"nothing accepts connections at {where} ({why}): no server listens there"
    if kind == "timeout":
        return (f"no answer from {where} within {PROBE_TIMEOUT_S:g} s (a wrong address, "
                "or a firewall dropping the connection)")
    speaks_tls = kind == "ok"
    if proto == "tcp":
        if speaks_tls:
            return (f"the server at {where} speaks TLS and this client plain TCP: connect "
                    f"to tls/{where} with a client config that trusts the server's CA "
                    "(transport.link.tls.root_ca_certificate: the CA file, and "
                    f"protocols [\"tls\"]; {EXAMPLES}/client_tls.json5)")
        return _credentials(cfg, endpoint, where, session_tried)
    if not speaks_tls:
        return (f"the server at {where} does not speak TLS ({why}): it is a plain "
                f"listener, connect to tcp/{where} instead")
    tls = "transport/link/tls/"
    ca_file = _get(cfg, tls + "root_ca_certificate")
    check_name = _get(cfg, tls + "verify_name_on_connect") is not False
    try:
        checked = _checked(ca_file, check_name)
    except (OSError, ssl.SSLError) as exc:
        return (f"this client's CA file {ca_file} (transport.link.tls.root_ca_certificate) "
                f"cannot be read: {getattr(exc, 'strerror', None) or exc}")
    kind, why = _tls_probe(host, port, checked, wait_alert=True)
    if kind == "verify":
        if "match" in why.lower() or "hostname" in why.lower():
            return (f"the server's TLS certificate at {where} does not name {host!r} "
                    f"({why}): connect by a name or address in its subjectAltName, or "
                    "issue it one that names this one")
        if not ca_file:
            return (f"the server at {where} speaks TLS but this client does not trust its "
                    f"certificate ({why}): the client config names no CA file "
                    "(transport.link.tls.root_ca_certificate), so only the system's public "
                    "roots are trusted; set it to the CA that signed the server's "
                    f"certificate ({EXAMPLES}/client_tls.json5)")
        return (f"the server's TLS certificate at {where} is not signed by the CA in "
                f"{ca_file} ({why}): set transport.link.tls.root_ca_certificate to the CA "
                "that signed it")
    if kind == "alert" and "certificate" in why.lower():
        cert = (_get(cfg, tls + "connect_certificate"), _get(cfg, tls + "connect_private_key"))
        if not (cert[0] and cert[1]) or _get(cfg, tls + "enable_mtls") is not True:
            return (f"the server at {where} requires a client certificate (mutual TLS; "
                    f"{why}): set transport.link.tls.enable_mtls true, connect_certificate "
                    "and connect_private_key to a certificate its CA signed "
                    f"({EXAMPLES}/client_mtls.json5)")
        with contextlib.suppress(OSError, ssl.SSLError):
            kind, why = _tls_probe(host, port, _checked(ca_file, check_name, cert),
                                   wait_alert=True)
            if kind in ("alert", "not_tls", "verify"):
                return (f"the server at {where} refused this client's certificate "
                        f"{cert[0]} ({why}): it wants one signed by its own CA")
    if kind not in ("ok", "alert"):
        return None
    return _credentials(cfg, endpoint, where, session_tried)


def _credentials(cfg: Any, endpoint: str, where: str, session_tried: bool) -> str | None:
    """The link is fine: the server refused the zenoh session, so its credentials."""
    if not session_tried:
        return None
    user = _get(cfg, "transport/auth/usrpwd/user")
    if not user:
        return (f"the link to {where} works but the server refused the zenoh session: it "
                "requires credentials (transport.auth.usrpwd.user and password; "
                f"{EXAMPLES}/client_driver.json5, client_viewer.json5), or its access "
                "rules do not admit this client")
    if _without_credentials_opens(cfg, endpoint):
        return (f"the server at {where} does not ask for credentials, and zenoh refuses a "
                f"client that sends some (user {user!r}): remove transport.auth.usrpwd "
                "from this client config")
    return (f"the link to {where} works but the server refused the credentials of user "
            f"{user!r} (a wrong password or an unknown user: transport.auth.usrpwd)")


def explain(cfg: Any, session_tried: bool = True) -> str:
    """:func:`explain_endpoint` for each connect endpoint of ``cfg``, joined; "" when it
    finds nothing (never raises: a diagnosis must not hide the error it explains)."""
    try:
        endpoints = _get(cfg, "connect/endpoints") or []
        if isinstance(endpoints, dict):
            mode = _get(cfg, "mode") or "peer"
            endpoints = endpoints.get(mode, [])
        found = []
        for ep in list(endpoints)[:MAX_ENDPOINTS]:
            text = explain_endpoint(cfg, str(ep), session_tried)
            if text:
                found.append(text if len(endpoints) == 1 else f"{ep}: {text}")
        return "; ".join(found)
    except Exception:  # noqa: BLE001
        return ""


def explain_unreached(cfg: Any) -> str:
    """Why a session that opened (a peer) reaches no server: a client-mode session with
    the same config tried at its connect endpoints; if that fails too, :func:`explain`
    of it. "" when it opens (the link is fine: the server is not there, or under another
    vehicle id or prefix) or nothing is found."""
    import zenoh

    try:
        trial = zenoh.Config.from_json5(str(cfg))
        trial.insert_json5("mode", '"client"')
        trial.insert_json5("listen/endpoints", "[]")
        try:
            with zenoh.open(trial):
                return ""
        except zenoh.ZError:
            return explain(trial)
    except Exception:  # noqa: BLE001 - a diagnosis never raises
        return ""
