"""Config: TOML sections into dataclasses, command-line overrides, clear errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.common.bus import ZenohOptions
from services.common.config import ConfigError, load_section, parse_override, to_toml


def test_defaults_without_file() -> None:
    assert load_section("zenoh") == ZenohOptions()


def test_file_and_override(tmp_path: Path) -> None:
    f = tmp_path / "c.toml"
    f.write_text('[zenoh]\nmode = "client"\nconnect = ["tcp/10.0.0.1:7447"]\nlease_ms = 2000\n')
    o = load_section("zenoh", f, ["zenoh.lease_ms=1500"])
    assert o.mode == "client" and o.connect == ("tcp/10.0.0.1:7447",) and o.lease_ms == 1500


@pytest.mark.parametrize(("text", "message"), [
    ("[zenoh]\nmood = 1\n", "unknown keys"),
    ("[zenoh]\nlease_ms = 'x'\n", "lease_ms"),
    ("[nosuch]\na = 1\n", "unknown config section"),
    ("[zenoh]\nmode = 'bus'\n", "mode"),
    ("not toml = = 1", "not valid TOML"),
])
def test_errors_name_the_problem(tmp_path: Path, text: str, message: str) -> None:
    f = tmp_path / "c.toml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_section("zenoh", f)


def test_override_parsing() -> None:
    assert parse_override("tracker.m=0.25") == ("tracker", "m", 0.25)
    assert parse_override("zenoh.mode=client") == ("zenoh", "mode", "client")
    with pytest.raises(ConfigError):
        parse_override("nodot=1")


def test_to_toml_round_trips(tmp_path: Path) -> None:
    o = ZenohOptions(mode="client", connect=("a/b",), lease_ms=5)
    f = tmp_path / "c.toml"
    f.write_text(to_toml({"zenoh": o}))
    assert load_section("zenoh", f) == o
