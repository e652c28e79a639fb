"""Deployment files, checked without a Docker engine: hadolint, the compose specification,
``depends_on`` targets, the Zenoh configs parsed by Zenoh itself, and the one-host compose file:
a health check on every service, dependencies that wait for health, the router on loopback, a
default that needs no hardware, and the commands parsed by the real ``handkse`` parser."""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh
from ruamel.yaml import YAML

from services.cli import build_parser
from services.robot_bridge.config import sim_object_source

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


# --- the one-host compose file: starts anywhere, health-gated ---

ONE_HOST = DOCKER / "compose.yaml"
HARDWARE_PROFILES = {"kinect", "realsense", "gpu"}
# the liveliness token each handkse command declares (what its health check must ask for)
TOKEN_OF = {"router": "router", "tracker": "tracker", "kinematics": "kinematics",
            "robot-bridge": "robot_bridge", "replay": "replay", "camera": "camera",
            "detector": "detector"}


def _one_host_services() -> dict[str, dict]:
    services: dict[str, dict] = YAML(typ="safe").load(ONE_HOST.read_text())["services"]
    return services


def _parse(argv: list[str]) -> argparse.Namespace:
    """``argv`` parsed by the real ``handkse`` parser (a typo fails here, not in a container)."""
    return build_parser(argv).parse_args(argv)


def test_every_service_has_a_health_check_on_its_own_token() -> None:
    for name, service in _one_host_services().items():
        assert service["image"].startswith("handkse-"), name
        test = service["healthcheck"]["test"]
        assert test[:3] == ["CMD", "handkse", "health"], name
        assert _parse(test[2:]).service == [TOKEN_OF[service["command"][0]]], name
        assert service["healthcheck"]["retries"] >= 1


def test_every_dependency_waits_until_healthy() -> None:
    services = _one_host_services()
    for name, service in services.items():
        deps = service.get("depends_on", {})
        assert isinstance(deps, dict), f"{name}: depends_on needs conditions"
        for dep, how in deps.items():
            assert how == {"condition": "service_healthy"}, (name, dep)
            assert not set(services[dep].get("profiles", [])), f"{name} waits for optional {dep}"
        if name != "zenoh-router":
            assert "zenoh-router" in deps or all(
                "zenoh-router" in services[d].get("depends_on", {}) for d in deps), name


def test_only_the_router_is_published_and_only_on_loopback() -> None:
    services = _one_host_services()
    assert services["zenoh-router"]["ports"] == ["127.0.0.1:7447:7447"]
    assert [n for n, s in services.items() if s.get("ports") and n != "zenoh-router"] == []


def test_without_a_profile_the_pipeline_needs_no_hardware() -> None:
    services = _one_host_services()
    default = {n: s for n, s in services.items() if not s.get("profiles")}
    assert {s["command"][0] for s in default.values()} == {
        "router", "replay", "tracker", "kinematics", "robot-bridge"}
    for name, service in default.items():
        assert "devices" not in service and "deploy" not in service, name
        _parse(service["command"])
    replay = _parse(services["replay"]["command"])
    assert replay.synthetic == "key" and replay.loop and not replay.keep_stamps
    assert replay.standby_while == ["camera"]  # a live camera silences the demonstration
    assert set(replay.reset) == {"tracker", "kinematics"}
    bridge = _parse(services["robot-bridge"]["command"])
    assert bridge.backend == "mujoco"
    # the simulated Panda holds the very object the replay demonstrates
    held = sim_object_source(bridge.sim_object)
    assert (held.kind, held.name, held.participant, held.seed) == (
        "synthetic", replay.synthetic, replay.participant, replay.seed)


def test_each_hardware_profile_has_one_camera_and_one_detector() -> None:
    services = _one_host_services()
    used = {p for s in services.values() for p in s.get("profiles", [])}
    assert used == HARDWARE_PROFILES
    for profile in HARDWARE_PROFILES:
        on = [s for s in services.values() if profile in s.get("profiles", [])]
        assert sorted(s["command"][0] for s in on) == ["camera", "detector"], profile
    gpu = [s for s in services.values() if "gpu" in s.get("profiles", [])
           and s["command"][0] == "detector"]
    assert gpu[0]["image"] == "handkse-gpu:latest"
    assert gpu[0]["deploy"]["resources"]["reservations"]["devices"][0]["driver"] == "nvidia"
    for s in services.values():
        if s["command"][0] == "detector" and "gpu" not in s.get("profiles", []):
            assert _parse(s["command"]).device == "cpu"
