"""The container files, tested the only way this machine can (no container engine):
their commands run outside a container, and what they name exists and agrees."""

from __future__ import annotations

import json
import os
import shlex
import socket
import subprocess
import sys
from pathlib import Path

import yaml

from vastray.server.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
DOCKERFILE = ROOT / "deploy" / "Dockerfile"
COMPOSE = ROOT / "docker-compose.yml"


def stages() -> list[list[tuple[str, str]]]:
    """(INSTRUCTION, arguments) of each stage, continuation lines joined."""
    text = DOCKERFILE.read_text().replace("\\\n", " ")
    stages: list[list[tuple[str, str]]] = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        word, _, rest = line.partition(" ")
        if word.upper() == "FROM":
            stages.append([])
        stages[-1].append((word.upper(), rest.strip()))
    assert len(stages) == 2, "a build stage and a runtime stage"
    return stages


def instructions() -> list[tuple[str, str]]:
    """The runtime stage's instructions."""
    return stages()[1]


def apt_packages(stage: list[tuple[str, str]]) -> set[str]:
    words = [w for word, rest in stage if word == "RUN" for w in shlex.split(rest)]
    return {w for w in words if w[0].isalpha() and w not in {"apt-get", "install", "update", "rm", "pip"}}


def env_of(runtime: list[tuple[str, str]]) -> dict[str, str]:
    env: dict[str, str] = {}
    for word, rest in runtime:
        if word == "ENV":
            for item in shlex.split(rest):
                key, _, value = item.partition("=")
                env[key] = value
    return env


def exec_form(rest: str) -> list[str]:
    if rest.startswith("CMD "):
        rest = rest[4:]
    return json.loads(rest)


def test_the_runtime_stage_has_every_library_the_native_module_links() -> None:
    """The shared libraries the installed native module needs (ldd) beyond the C and C++
    runtimes come from Debian packages the runtime stage installs, and their -dev
    packages are in the build stage."""
    import vastray.native

    ldd = subprocess.run(["ldd", vastray.native.__file__], capture_output=True, text=True, check=True).stdout
    paths = {line.split()[0]: line.split()[2] for line in ldd.splitlines() if "=>" in line}
    base = ("libc.so", "libm.so", "libstdc++", "libgcc_s", "libpthread", "ld-linux", "libdl", "linux-vdso")
    extra = {lib: path for lib, path in paths.items() if not lib.startswith(base)}
    build, runtime = (apt_packages(stage) for stage in stages())
    for lib, path in extra.items():
        dpkg = subprocess.run(["dpkg", "-S", os.path.realpath(path)], capture_output=True, text=True)
        owner = dpkg.stdout.split(":")[0]
        assert owner in runtime, f"{lib} is Debian's {owner}, which the runtime stage lacks"
        stem = owner.rstrip("0123456789.").removesuffix("-")
        assert f"{stem}-dev" in build, f"no {stem}-dev in the build stage"
    assert {"liblz4-1", "libdeflate0"} <= runtime and extra, "the codecs are linked from the distribution"


def test_what_the_build_stage_copies_exists() -> None:
    text = DOCKERFILE.read_text()
    for line in text.splitlines():
        if line.startswith("COPY") and "--from" not in line:
            *sources, _ = line.split()[1:]
            for source in sources:
                assert (ROOT / source).exists(), source
    for package in ("vastray", "server", "client"):
        assert f"COPY {package} ./{package}" in text, package


def test_the_data_volume_belongs_to_the_runtime_user() -> None:
    runtime = instructions()
    words = [w for w, _ in runtime]
    run = " ".join(rest for w, rest in runtime if w == "RUN")
    assert "mkdir -p /data" in run and "chown vastray:vastray /data" in run
    assert words.index("USER") < words.index("VOLUME")
    assert dict(runtime)["USER"] == "vastray"
    assert env_of(runtime)["VASTRAY_DATA_DIR"] == "/data"
    for key in env_of(runtime):
        if key.startswith("VASTRAY_"):
            assert key[8:].lower() in Settings.model_fields, key


def test_the_image_command_and_healthcheck_run_outside_a_container(tmp_path: Path) -> None:
    runtime = instructions()
    cmd = exec_form(dict(runtime)["CMD"])
    health = exec_form(dict(runtime)["HEALTHCHECK"].split(" CMD ", 1)[1])
    assert cmd == ["vastray", "serve"]
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {
        **os.environ,
        **env_of(runtime),
        "VASTRAY_DATA_DIR": str(tmp_path / "data"),
        "VASTRAY_PORT": str(port),
    }
    env["PATH"] = f"{Path(sys.executable).parent}:{env['PATH']}"
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("vastray serving ") and f":{port}/?key=" in line, line
        probe = [sys.executable if health[0] == "python" else health[0], *health[1:]]
        probe[-1] = probe[-1].replace("8000", str(port))
        for _ in range(100):
            if subprocess.run(probe, capture_output=True, timeout=10).returncode == 0:
                break
        else:
            raise AssertionError("the healthcheck never passed")
        assert (tmp_path / "data" / "registry.sqlite3").exists()
    finally:
        proc.terminate()
        assert proc.wait(30) == 0, "docker stop (SIGTERM) must shut down cleanly"


def test_compose_file_agrees_with_the_image() -> None:
    compose = yaml.safe_load(COMPOSE.read_text())
    service = compose["services"]["vastray"]
    assert service["build"]["dockerfile"] == "deploy/Dockerfile"
    assert (ROOT / service["build"]["context"] / service["build"]["dockerfile"]).is_file()
    assert any(v.split(":")[1] == "/data" for v in service["volumes"])
    assert set(compose["volumes"]) == {v.split(":")[0] for v in service["volumes"]}
    for key in service["environment"]:
        assert key.startswith("VASTRAY_") and key[8:].lower() in Settings.model_fields, key
    image_health = dict(instructions())["HEALTHCHECK"].split(" CMD ", 1)[1]
    assert service["healthcheck"]["test"][1:] == exec_form(image_health)
    assert service["ports"] == ["127.0.0.1:8000:8000"]
