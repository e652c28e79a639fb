"""Easy mistakes end in one line naming the thing and the fix, exit status 2, no traceback
(``python -m services`` as a real subprocess, as a user runs it)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from services.common.keys import Keys
from services.common.processes import REPO, child_env, handkse_cmd
from services.common.recording import write_recording
from services.synthetic.objects import OBJECTS
from tests.common import samples


def _run(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess[str]:
    return subprocess.run(handkse_cmd(*args), capture_output=True, text=True, env=child_env(),
                          cwd=cwd, timeout=60, check=False)


def one_line_error(result: subprocess.CompletedProcess[str]) -> str:
    """The single non-empty stderr line of a command that failed with status 2."""
    assert result.returncode == 2, (result.returncode, result.stdout, result.stderr)
    assert "Traceback" not in result.stderr, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    return lines[0]


@pytest.fixture
def files(tmp_path: Path) -> dict[str, Path]:
    good = tmp_path / "good.mcap"
    keys = Keys("a")
    write_recording(good, [(keys.hand_landmarks, samples.hand_landmarks(i).to_msgpack(),
                            1_000 + i) for i in range(50)])
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"this is a text file, not a recording\n" * 20)
    two_rigs = tmp_path / "two_rigs.mcap"
    write_recording(two_rigs, [(Keys(r).hand_landmarks, samples.hand_landmarks().to_msgpack(),
                                1_000 + i) for i, r in enumerate(("a", "b"))])
    return {"good": good, "truncated": truncated, "garbage": garbage, "two_rigs": two_rigs,
            "missing": tmp_path / "missing.mcap", "tmp": tmp_path}


# (arguments, pieces the one line must contain); {name} is replaced by the path in `files`
CASES: list[tuple[list[str], list[str]]] = [
    (["replay", "--synthetic", "kee"],
     ["handkse replay: --synthetic: unknown object 'kee'; known: ", ", ".join(OBJECTS)]),
    (["demo", "--object", "kee"], ["handkse demo: --object: unknown object 'kee'"]),
    (["replay", "{missing}"], ["recording {missing} does not exist"]),
    (["replay", "{garbage}"], ["{garbage} is not an MCAP recording", "handkse record"]),
    (["replay", "{truncated}"], ["recording {truncated} is damaged or incomplete"]),
    (["replay", "{tmp}"], ["recording {tmp} is a folder"]),
    (["record", "{tmp}/no/such/folder/x.mcap", "--duration", "1"],
     ["cannot write the recording", "the folder {tmp}/no/such/folder does not exist"]),
    (["get", "model", "-c", "{tmp}/zenoh.json5"],
     ["handkse get: zenoh config file {tmp}/zenoh.json5 does not exist"]),
    (["stats", "--cfg", "transport/no_such_key:1"],
     ["--cfg 'transport/no_such_key:1'", "no config key 'transport/no_such_key'"]),
    (["stats", "--cfg", "mode:\"bogus\""], ["--cfg 'mode:\"bogus\"': bad value for mode"]),
    (["stats", "--cfg", "no-colon"], ["--cfg 'no-colon' must look like KEY:VALUE"]),
    (["replay", "--synthetic", "key", "--rig", "a/b"],
     ["handkse replay: --rig: 'a/b' is not a rig name", "letters, digits",
      "(see handkse replay --help)"]),
    (["replay", "--synthetic", "key", "--participant", "99"],
     ["handkse replay: --participant: must be 1..7, got 99 (see handkse replay --help)"]),
    (["replay", "--synthetic", "key", "--participant", "0"], ["--participant: must be 1..7"]),
    (["replay", "--synthetic", "key", "--rate", "-1"], ["--rate: must be >= 0, got -1"]),
    (["replay", "--synthetic", "key", "--seed", "-1"], ["--seed: must be >= 0, got -1"]),
    (["replay", "--synthetic", "key", "--wait-timeout", "0"], ["--wait-timeout: must be > 0"]),
    (["get", "model", "--timeout", "0"], ["handkse get: --timeout: must be > 0, got 0"]),
    (["stats", "--timeout", "nan"], ["--timeout: expected a finite number, got 'nan'"]),
    (["record", "x.mcap", "--count", "0"], ["--count: must be > 0, got 0"]),
    (["stats", "trackr"], ["unknown service 'trackr'; known: camera, detector, tracker"]),
    (["replay", "--synthetic", "key", "--wait-for", "kinematic"],
     ["--wait-for: unknown service 'kinematic'"]),
    (["replay"], ["replay needs a recording FILE or --synthetic OBJECT"]),
    (["replay", "{good}", "--topics", "hand/bdy"],
     ["--topics: hand/bdy not in {good}; it has: hand/landmarks"]),
    (["replay", "{good}", "--save", "{tmp}/copy.mcap"], ["--save works with --synthetic only"]),
    (["replay", "{two_rigs}", "--rig", "c"],
     ["{two_rigs} holds the rigs a, b: --rig c would merge them"]),
    (["replay", "--synthetic", "key", "--topics", "camera/rgbd"],
     ["--topics: camera/rgbd not in the synthetic key demonstration"]),
    (["frobnicate"], ["handkse: COMMAND: invalid choice: 'frobnicate'"]),
    (["articulate", "--amount", "0"],
     ["handkse articulate: --amount: must be a finite, non-zero number, got 0"]),
    (["articulate", "--duration", "-2"], ["handkse articulate: --duration: must be > 0"]),
    (["articulate", "--model-file", "{missing}"],
     ["handkse articulate: --model-file {missing} does not exist"]),
    (["articulate", "--model-file", "{garbage}"],
     ["handkse articulate: --model-file {garbage} is not a KinematicModel"]),
    (["robot-bridge", "--sim-object", "synthetic:kee"],
     ["handkse robot-bridge: --sim-object: sim_object 'synthetic:kee': unknown object 'kee'"]),
    (["robot-bridge", "--sim-object", "{tmp}/lab/key.toml"],
     ["handkse robot-bridge: object calibration file {tmp}/lab/key.toml does not exist"]),
    # a service that does not answer: `stats SERVICE` fails, so scripts can rely on it
    (["stats", "tracker", "--timeout", "1", "--no-multicast-scouting"],
     ["handkse stats: get 'handkse/default/tracker/stats': nothing answers"]),
    (["articulate", "--amount", "1", "--duration", "2", "--no-multicast-scouting"],
     ["handkse articulate: no robot bridge answers on handkse/default/robot/articulate",
      "is handkse robot-bridge running"]),
    (["articulate", "--dry-run", "--no-multicast-scouting"],
     ["handkse articulate: cannot read the model for the default amount or duration",
      "give --amount and --duration"]),
]


@pytest.mark.parametrize(("args", "pieces"), CASES, ids=lambda v: " ".join(v)[:40])
def test_mistake_ends_in_one_line(args: list[str], pieces: list[str],
                                  files: dict[str, Path]) -> None:
    names = {k: str(v) for k, v in files.items()}
    line = one_line_error(_run(*(a.format(**names) for a in args)))
    for piece in pieces:
        assert piece.format(**names) in line, line


def test_debug_log_level_adds_the_traceback(files: dict[str, Path]) -> None:
    result = _run("replay", str(files["missing"]), "--log-level", "DEBUG")
    assert result.returncode == 2
    assert "Traceback" in result.stderr
    last = [line for line in result.stderr.splitlines() if line.strip()][-1]
    assert last == f"handkse replay: recording {files['missing']} does not exist"


def test_remap_rig_is_accepted_and_says_it_is_not_needed(files: dict[str, Path]) -> None:
    out = files["tmp"] / "out.mcap"
    result = _run("replay", "--synthetic", "bolt", "--remap-rig", "--rig", "lab",
                  "--save", str(out))
    assert result.returncode == 0, result.stderr
    assert "--remap-rig is not needed any more" in result.stderr
