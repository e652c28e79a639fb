"""The committed locks match pyproject.toml, each other, and what is installed.

``make install`` installs ``requirements/dev.lock`` with ``--no-deps``, so nothing checks at
install time that the lock still covers pyproject's requirements: these tests do. The images'
locks (``requirements/cpu.lock``, ``gpu.lock``) must agree with the venv's lock on every package
they share, so the services run in the images on the versions the suite ran on.
"""

from __future__ import annotations

import os
import re
import sys
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import pytest
from packaging.markers import Marker
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]
LOCKS = REPO / "requirements"
# The images' Python (docker/*.Dockerfile) and platform, for evaluating the venv lock's markers.
IMAGE_ENV = {"python_version": "3.11", "python_full_version": "3.11.10", "sys_platform": "linux",
             "platform_system": "Linux", "platform_machine": "x86_64",
             "implementation_name": "cpython", "platform_python_implementation": "CPython",
             "os_name": "posix"}


@dataclass(frozen=True)
class Pin:
    name: str
    version: str
    marker: Marker | None
    hashes: int


def read_lock(path: Path) -> list[Pin]:
    """The pins of a ``uv pip compile --generate-hashes`` file (continuation lines joined)."""
    text = re.sub(r"\\\n\s*", " ", path.read_text())
    pins = []
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line or line.startswith("-"):
            continue
        hashes = line.count("--hash=")
        requirement = line.split("--hash=", 1)[0]
        spec, _, marker = requirement.partition(";")
        name, _, version = spec.strip().partition("==")
        pins.append(Pin(canonicalize_name(name.split("[")[0]), version.strip(),
                        Marker(marker.strip()) if marker.strip() else None, hashes))
    return pins


def pins_for(pins: list[Pin], env: dict[str, str] | None = None) -> dict[str, str]:
    """``name -> version`` of the pins whose markers hold in ``env`` (this interpreter if None)."""
    chosen: dict[str, str] = {}
    for pin in pins:
        if pin.marker is None or pin.marker.evaluate(env):
            assert pin.name not in chosen, f"{pin.name} pinned twice for one environment"
            chosen[pin.name] = pin.version
    return chosen


def makefile_extras() -> list[str]:
    match = re.search(r"^EXTRAS \?= (\S+)$", (REPO / "Makefile").read_text(), re.MULTILINE)
    assert match, "Makefile has no `EXTRAS ?= ...` line"
    return match.group(1).split(",")


def project_requirements(extras: list[str]) -> list[Requirement]:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    reqs = [Requirement(r) for r in project["dependencies"]]
    for extra in extras:
        reqs += [Requirement(r) for r in project["optional-dependencies"][extra]]
    return reqs


def test_every_lock_line_is_pinned_with_hashes() -> None:
    for lock in sorted(LOCKS.glob("*.lock")):
        pins = read_lock(lock)
        assert pins, f"{lock.name} is empty"
        for pin in pins:
            assert pin.version, f"{lock.name}: {pin.name} is not pinned with =="
            assert pin.hashes > 0, f"{lock.name}: {pin.name} has no hash"


def test_dev_lock_covers_pyproject_for_this_python() -> None:
    locked = pins_for(read_lock(LOCKS / "dev.lock"))
    for req in project_requirements(makefile_extras()):
        if req.marker is not None and not req.marker.evaluate():
            continue
        name = canonicalize_name(req.name)
        assert name in locked, f"{req} is in pyproject.toml but not in dev.lock: run `make lock`"
        assert req.specifier.contains(locked[name], prereleases=True), (
            f"dev.lock pins {name}=={locked[name]}, pyproject asks {req}: run `make lock`")


@pytest.mark.parametrize("image", ["cpu", "gpu"])
def test_image_locks_agree_with_the_venv_lock(image: str) -> None:
    venv = pins_for(read_lock(LOCKS / "dev.lock"), IMAGE_ENV)
    for name, version in pins_for(read_lock(LOCKS / f"{image}.lock"), IMAGE_ENV).items():
        if name in venv:
            assert version == venv[name], f"{image}.lock pins {name}=={version}, dev.lock {venv[name]}"


@pytest.mark.skipif(os.environ.get("HANDKSE_DEPENDENCIES") == "latest",
                    reason="make test-latest runs against the newest releases, not the lock")
def test_installed_versions_are_the_locked_ones() -> None:
    locked = pins_for(read_lock(LOCKS / "dev.lock"))
    wrong = {}
    for name, version in locked.items():
        try:
            installed = metadata.version(name)
        except metadata.PackageNotFoundError:
            installed = None
        if installed != version:
            wrong[name] = (installed, version)
    assert not wrong, f"installed (have, locked) differ from dev.lock: {wrong}; run `make install`"
