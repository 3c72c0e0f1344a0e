"""A system D-Bus with polkit and RealtimeKit of its own, and an unprivileged user, for the
tests and benchmarks of real time without root (issue 35 item 1).

This machine has no init system running D-Bus (no systemd, no logind), so
:class:`RtkitBus` starts, as root, each as its own process:

- ``dbus-daemon`` with Debian's system bus configuration (``/usr/share/dbus-1/
  system.conf``: the same policies, RealtimeKit's and polkit's included) listening on a
  socket in a temporary folder instead of ``/run/dbus``; every process given
  ``DBUS_SYSTEM_BUS_ADDRESS`` (:meth:`RtkitBus.env`) uses it as its system bus;
- ``polkitd`` on it, with the project's rule ``configs/rtkit/50-simserver-realtime.rules``
  installed in ``/etc/polkit-1/rules.d`` for the time of the test (removed afterwards if
  it was not there): without a desktop session polkit grants RealtimeKit's
  ``acquire-real-time`` to nobody, the rule grants it to the group ``simserver-rt``;
- Debian's ``rtkit-daemon`` (``--stderr``), with its defaults (maximum priority 20,
  ``RLIMIT_RTTIME`` at most 200 ms).

:func:`unprivileged_user` makes a system user in that group (``useradd``), and
:func:`user_kernel_cache` a ``NUMBA_CACHE_DIR`` it owns, filled with this tree's compiled
kernels (it cannot write the tree's ``__pycache__``, and a cold compile takes minutes).
"""

from __future__ import annotations

import grp
import os
import pwd
import shutil
import subprocess
import sys
import time
from pathlib import Path

from simserver.testing import CONFIGS, REPO, OutputProcess

DBUS_DAEMON = "/usr/bin/dbus-daemon"
POLKITD = "/usr/lib/polkit-1/polkitd"
RTKIT_DAEMON = "/usr/libexec/rtkit-daemon"
SYSTEM_CONF = Path("/usr/share/dbus-1/system.conf")
POLKIT_RULES_DIR = Path("/etc/polkit-1/rules.d")
RULE = CONFIGS / "rtkit" / "50-simserver-realtime.rules"
GROUP = "simserver-rt"
USER = "simserver-rt"


def missing() -> str | None:
    """Why an RtkitBus cannot run here (None if it can)."""
    if os.geteuid() != 0:
        return "needs root (to start a system bus, polkitd and rtkit-daemon)"
    for path in (DBUS_DAEMON, POLKITD, RTKIT_DAEMON, SYSTEM_CONF):
        if not Path(path).exists():
            return f"{path} is not installed (apt-get install dbus polkitd rtkit)"
    for tool in ("useradd", "groupadd", "setpriv"):
        if shutil.which(tool) is None:
            return f"{tool} is not installed"
    return None


def _bus_config(socket_path: Path) -> str:
    """Debian's system bus configuration, listening at ``socket_path``, in the
    foreground, without activation, syslog, a pid file or a change of user."""
    text = SYSTEM_CONF.read_text(encoding="utf-8")
    for drop in ("<fork/>", "<syslog/>", "<user>messagebus</user>",
                 "<standard_system_servicedirs/>",
                 "<servicehelper>/usr/lib/dbus-1.0/dbus-daemon-launch-helper</servicehelper>",
                 "<pidfile>/run/dbus/pid</pidfile>"):
        text = text.replace(drop, "")
    text = text.replace("<listen>unix:path=/run/dbus/system_bus_socket</listen>",
                        f"<listen>unix:path={socket_path}</listen>")
    # relative to the file's own folder in Debian's; ours is elsewhere
    return text.replace("<includedir>system.d</includedir>",
                        "<includedir>/usr/share/dbus-1/system.d</includedir>")


def _name_owned(address: str, name: str) -> bool:
    from jeepney.bus_messages import message_bus
    from jeepney.io.blocking import open_dbus_connection
    from jeepney.wrappers import unwrap_msg

    try:
        conn = open_dbus_connection(bus=address)
    except OSError:
        return False
    try:
        reply = unwrap_msg(conn.send_and_get_reply(message_bus.NameHasOwner(name),
                                                   timeout=2.0))
        return bool(reply[0])
    finally:
        conn.close()


class RtkitBus:
    """The system bus, polkitd and rtkit-daemon of a test (a context manager).

    The bus socket and configuration live in a folder of their own under ``/tmp``
    (removed at exit): polkitd and the unprivileged user connect to the socket, so every
    folder above it must be open to them (pytest's ``tmp_path`` is not).

    Parameters
    ----------
    rtkit_args : sequence of str
        More ``rtkit-daemon`` options.
    """

    def __init__(self, rtkit_args: tuple[str, ...] = ()) -> None:
        import tempfile

        self.rtkit_args = rtkit_args
        self.procs: list[OutputProcess] = []
        self.rule_installed: Path | None = None
        self.folder = folder = Path(tempfile.mkdtemp(prefix="simserver-bus-", dir="/tmp"))
        folder.chmod(0o755)
        self.socket = folder / "system_bus_socket"
        self.address = f"unix:path={self.socket}"

    def env(self) -> dict[str, str]:
        """The variables that make a process use this bus as its system bus."""
        return {"DBUS_SYSTEM_BUS_ADDRESS": self.address}

    def _wait(self, name: str, proc: OutputProcess, timeout_s: float = 30.0) -> None:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if _name_owned(self.address, name):
                return
            if not proc.alive():
                break
            time.sleep(0.1)
        raise RuntimeError(f"{name} did not appear on the bus:\n{proc.text()[-3000:]}")

    def __enter__(self) -> RtkitBus:
        try:
            conf = self.folder / "system.conf"
            conf.write_text(_bus_config(self.socket), encoding="utf-8")
            env = dict(os.environ, **self.env())
            bus = OutputProcess([DBUS_DAEMON, f"--config-file={conf}", "--nofork",
                                 "--nopidfile"], env=env, cwd=REPO)
            self.procs.append(bus)
            end = time.monotonic() + 30.0
            while not self.socket.exists():
                if not bus.alive() or time.monotonic() > end:
                    raise RuntimeError(f"dbus-daemon did not start:\n{bus.text()}")
                time.sleep(0.05)
            target = POLKIT_RULES_DIR / RULE.name
            if not target.exists():
                POLKIT_RULES_DIR.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(RULE, target)
                target.chmod(0o644)
                self.rule_installed = target
            polkit = OutputProcess([POLKITD, "--no-debug"], env=env, cwd=REPO)
            self.procs.append(polkit)
            self._wait("org.freedesktop.PolicyKit1", polkit)
            rtkit = OutputProcess([RTKIT_DAEMON, "--stderr", *self.rtkit_args], env=env,
                                  cwd=REPO)
            self.procs.append(rtkit)
            self._wait("org.freedesktop.RealtimeKit1", rtkit)
            self.rtkit = rtkit
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        for proc in reversed(self.procs):
            proc.stop(timeout_s=10.0)
        self.procs.clear()
        if self.rule_installed is not None:
            self.rule_installed.unlink(missing_ok=True)
            self.rule_installed = None
        shutil.rmtree(self.folder, ignore_errors=True)


def unprivileged_user(name: str = USER, group: str = GROUP) -> pwd.struct_passwd:
    """A system user ``name`` without a home or a login shell, in ``group`` (both made
    if missing)."""
    try:
        grp.getgrnam(group)
    except KeyError:
        subprocess.run(["groupadd", "--system", group], check=True, timeout=30)
    try:
        return pwd.getpwnam(name)
    except KeyError:
        subprocess.run(["useradd", "--system", "--no-create-home", "--shell",
                        "/usr/sbin/nologin", "--gid", group, name], check=True, timeout=30)
        return pwd.getpwnam(name)


def user_kernel_cache(root: Path, user: pwd.struct_passwd) -> Path:
    """A ``NUMBA_CACHE_DIR`` owned by ``user``, holding a copy of this tree's kernel
    caches where numba looks for them under that variable
    (``simserver.core.kernel_cache_dirs``)."""
    from simserver.core import kernel_cache_dirs

    old = os.environ.get("NUMBA_CACHE_DIR")
    os.environ["NUMBA_CACHE_DIR"] = str(root)
    try:
        for package in ("core", "adapters"):
            source, target = kernel_cache_dirs(REPO / "simserver" / package)
            target.mkdir(parents=True, exist_ok=True)
            for f in source.iterdir():
                if f.suffix in (".nbi", ".nbc") or f.name.endswith(".sha256"):
                    shutil.copy2(f, target / f.name)
    finally:
        if old is None:
            del os.environ["NUMBA_CACHE_DIR"]
        else:
            os.environ["NUMBA_CACHE_DIR"] = old
    for dirpath, _, files in os.walk(root):
        os.chown(dirpath, user.pw_uid, user.pw_gid)
        for f in files:
            os.chown(os.path.join(dirpath, f), user.pw_uid, user.pw_gid)
    root.chmod(0o700)
    return root


def as_user(user: pwd.struct_passwd, argv: list[str], cap: str | None = None) -> list[str]:
    """``argv`` run as ``user`` (its groups, no capabilities, rtprio limit 0: SCHED_FIFO
    refused, as for an ordinary login); with ``cap`` (e.g. ``"sys_nice"``, what ``docker
    run --cap-add SYS_NICE`` gives) that one capability, ambient, and no other.

    This machine's Python lives under ``/root`` (mode 0700), where another user cannot
    reach it: the command then runs in a mount namespace of its own (``unshare``) in
    which ``/root`` is an empty folder open to all holding only the Python installation,
    bound from the real one. Nothing outside that namespace changes.
    """
    caps = ["--inh-caps=-all", "--bounding-set=-all"] if cap is None else \
        [f"--inh-caps=-all,+{cap}", f"--ambient-caps=-all,+{cap}",
         f"--bounding-set=-all,+{cap}"]
    drop = ["setpriv", f"--reuid={user.pw_uid}", f"--regid={user.pw_gid}", "--init-groups",
            *caps, "prlimit", "--rtprio=0", "--"]
    # a virtual environment elsewhere (CI's) still runs the interpreter it links to
    under_root = [p for p in (Path(sys.prefix).resolve(), Path(sys.base_prefix).resolve(),
                              Path(sys.executable).resolve()) if p.is_relative_to("/root")]
    if not under_root:
        return [*drop, *argv]
    top = Path("/root") / under_root[0].relative_to("/root").parts[0]
    script = ('set -e; t=$(mktemp -d); mount --bind "$0" "$t"; '
              'mount -t tmpfs -o mode=755 tmpfs /root; mkdir -p "$0"; '
              'mount --bind "$t" "$0"; exec "$@"')
    return ["unshare", "--mount", "--propagation", "private", "sh", "-c", script, str(top),
            *drop, *argv]
