"""Deployment files, checked without a Docker engine: hadolint, the compose specification,
``depends_on`` targets, and the Zenoh configs parsed by Zenoh itself."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh
from ruamel.yaml import YAML

REPO = Path(__file__).resolve().parents[2]
DOCKER = REPO / "docker"
DOCKERFILES = sorted(DOCKER.glob("*.Dockerfile"))
COMPOSE = [DOCKER / "compose.yaml", *sorted((DOCKER / "multihost").glob("*.yaml"))]
ZENOH_CONFIGS = sorted((DOCKER / "zenoh").glob("*.json5"))
BIN = Path(sys.executable).parent


def _tool(name: str) -> str:
    path = BIN / name
    if path.exists():
        return str(path)
    found = shutil.which(name)
    assert found, f"{name} is not installed (it comes with the dev extra)"
    return found


@pytest.mark.parametrize("dockerfile", DOCKERFILES, ids=lambda p: p.name)
def test_dockerfiles_pass_hadolint(dockerfile: Path) -> None:
    result = subprocess.run([_tool("hadolint"), str(dockerfile)], capture_output=True, text=True,
                            check=False)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize("dockerfile", DOCKERFILES, ids=lambda p: p.name)
def test_images_run_as_non_root(dockerfile: Path) -> None:
    users = [line.split()[1] for line in dockerfile.read_text().splitlines()
             if line.startswith("USER ")]
    assert users and users[-1] not in ("root", "0")


@pytest.mark.parametrize("compose", COMPOSE, ids=lambda p: p.name)
def test_compose_files_follow_the_specification(compose: Path) -> None:
    result = subprocess.run([_tool("check-jsonschema"), "--builtin-schema",
                             "vendor.compose-spec", str(compose)], capture_output=True,
                            text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize("compose", COMPOSE, ids=lambda p: p.name)
def test_depends_on_names_defined_services(compose: Path) -> None:
    doc = YAML(typ="safe").load(compose.read_text())
    services = doc["services"]
    for name, service in services.items():
        deps = service.get("depends_on", [])
        for dep in deps if isinstance(deps, list) else list(deps):
            assert dep in services, f"{compose.name}: {name} depends on undefined {dep}"


@pytest.mark.parametrize("config", ZENOH_CONFIGS, ids=lambda p: p.name)
def test_zenoh_configs_parse(config: Path) -> None:
    conf = zenoh.Config.from_file(str(config))
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("transport/link/tx/lease")) == 2000
