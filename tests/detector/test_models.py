"""Model preparation: provenance, conversion accuracy against the originals, the cache contract."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from services.common.progress import Progress
from services.detector import models
from services.detector.config import DetectorConfig
from services.detector.models import (
    MAX_ABS_DIFF,
    MODELS,
    WHEEL,
    ModelsMissing,
    PrepareError,
    compare_with_tflite,
    model_path,
    prepare,
    replace_prelu,
    sha256_of,
)
from services.detector.pipeline import HandPipeline
from services.detector.runtime import CPU, CUDA, TENSORRT, DeviceUnavailable, provider_names


def test_manifest_records_source_licence_and_hashes(models_dir: Path) -> None:
    manifest = json.loads((models_dir / "manifest.json").read_text())
    assert manifest["source"]["wheel"] == WHEEL.filename
    assert manifest["source"]["sha256"] == WHEEL.sha256
    assert manifest["licence"] == "Apache-2.0"
    assert "Apache License" in (models_dir / manifest["licence_file"]).read_text()
    assert set(manifest["models"]) == set(MODELS)
    for name, entry in manifest["models"].items():
        path = models_dir / entry["file"]
        assert sha256_of(path) == entry["sha256"], name
        assert entry["source_sha256"] == MODELS[name].sha256
        size = MODELS[name].input_size
        assert entry["inputs"] == {"input_1": [1, 3, size, size]}
        ops = {node.op_type for node in onnx.load(str(path)).graph.node}
        assert "PRelu" not in ops, name  # replaced by Relu/Min/Mul/Add
    assert manifest["models"]["palm_full"]["prelu_replaced"] > 0


def test_converted_models_match_the_originals(models_dir: Path) -> None:
    """ONNX Runtime on the conversion vs LiteRT on the shipped .tflite, same random inputs."""
    worst = {}
    for name in MODELS:
        diffs = compare_with_tflite(models_dir / "tflite" / f"{name}.tflite",
                                    model_path(name, models_dir))
        assert set(diffs) >= {"Identity", "Identity_1"}
        worst[name] = max(diffs.values())
    print("max abs diff converted vs original:", worst)
    assert max(worst.values()) < MAX_ABS_DIFF


def test_prelu_rewrite_is_exact() -> None:
    rng = np.random.default_rng(0)
    slope = rng.normal(size=(4, 1, 1)).astype(np.float32)
    graph = helper.make_graph(
        [helper.make_node("PRelu", ["x", "a"], ["y"], name="p")], "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4, 5, 5])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4, 5, 5])],
        [numpy_helper.from_array(slope, "a")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 11)])
    model.ir_version = 6
    x = rng.normal(size=(1, 4, 5, 5)).astype(np.float32)
    before = ort.InferenceSession(model.SerializeToString(), providers=[CPU]).run(None, {"x": x})
    assert replace_prelu(model) == 1
    onnx.checker.check_model(model)
    assert [n.op_type for n in model.graph.node] == ["Relu", "Min", "Mul", "Add"]
    after = ort.InferenceSession(model.SerializeToString(), providers=[CPU]).run(None, {"x": x})
    np.testing.assert_array_equal(after[0], before[0])
    np.testing.assert_array_equal(before[0], np.where(x > 0, x, x * slope))


def test_missing_models_tell_the_user_to_run_prepare(tmp_path: Path) -> None:
    with pytest.raises(ModelsMissing, match="handkse models prepare"):
        model_path("palm_full", tmp_path)
    with pytest.raises(ModelsMissing, match="handkse models prepare"):
        HandPipeline.from_config(DetectorConfig(models_dir=str(tmp_path), device="cpu"))


def test_prepare_is_idempotent_and_needs_no_network_when_cached(
        models_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def no_network(*_args: object) -> Path:
        raise AssertionError("prepare went to PyPI although the cache is complete")

    monkeypatch.setattr(models, "_download_wheel", no_network)
    monkeypatch.setattr(models, "convert", no_network)
    manifest = prepare(models_dir)  # no conversion and no download: checked by the patches
    assert set(manifest["models"]) == set(MODELS)


def test_prepare_reconverts_offline_from_the_kept_originals(
        models_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def no_network(*_args: object) -> Path:
        raise AssertionError("prepare went to PyPI although the originals are cached")

    monkeypatch.setattr(models, "_download_wheel", no_network)
    shutil.copytree(models_dir / "tflite", tmp_path / "tflite")
    shutil.copy(models_dir / "LICENSE.mediapipe", tmp_path / "LICENSE.mediapipe")
    log = io.StringIO()
    manifest = prepare(tmp_path, check=False, progress=Progress(1, stream=log, tty=False))
    assert manifest["source"]["sha256"] == WHEEL.sha256
    for name in MODELS:
        assert model_path(name, tmp_path).stat().st_size > 1_000_000
    # one plain line per step, counting down what is left (no fetch: the originals are there)
    lines = log.getvalue().splitlines()
    assert [line.split(" (")[0] for line in lines[:-1]] == [
        f"[{i}/{len(MODELS)}] converting {name}" for i, name in enumerate(MODELS, 1)]
    assert lines[-1].startswith(f"hand models ready in {tmp_path}")


def test_a_wrong_wheel_is_refused(tmp_path: Path) -> None:
    fake = tmp_path / WHEEL.filename
    fake.write_bytes(b"not the mediapipe wheel")
    with pytest.raises(PrepareError, match="sha256"):
        prepare(tmp_path / "cache", wheel=fake, check=False)


def test_provider_selection() -> None:
    gpu = [TENSORRT, CUDA, CPU]
    assert provider_names("auto", gpu) == [TENSORRT, CUDA, CPU]
    assert provider_names("auto", [CUDA, CPU]) == [CUDA, CPU]
    assert provider_names("auto", [CPU]) == [CPU]
    assert provider_names("cpu", gpu) == [CPU]
    assert provider_names("cuda", gpu) == [CUDA, CPU]
    assert provider_names("tensorrt", gpu) == [TENSORRT, CUDA, CPU]
    with pytest.raises(DeviceUnavailable, match="onnxruntime-gpu"):
        provider_names("cuda", [CPU])
    with pytest.raises(ValueError, match="device"):
        provider_names("tpu", [CPU])


def test_the_cpu_path_runs_on_the_cpu_provider(cpu_config: DetectorConfig) -> None:
    pipeline = HandPipeline.from_config(cpu_config)
    assert pipeline.providers == [CPU]
    auto = HandPipeline.from_config(DetectorConfig(models_dir=cpu_config.models_dir))
    assert auto.providers[-1] == CPU  # auto picks a GPU only where onnxruntime offers one
    assert auto.providers[0] in provider_names("auto", ort.get_available_providers())
