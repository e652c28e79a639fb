"""ONNX Runtime sessions: execution providers chosen from what is installed, tuned for latency.

``device="auto"`` takes TensorRT, then CUDA, then the CPU, among the providers the installed
``onnxruntime`` package offers (``onnxruntime-gpu`` brings CUDA and TensorRT; the plain package
only the CPU). ``cpu``, ``cuda`` and ``tensorrt`` ask for one; a GPU provider that is not
installed is an error naming the package to install. If a GPU provider is listed but fails to
start (missing CUDA/TensorRT libraries), the session falls back to the next one and logs why.

Latency settings: full graph optimisation, sequential execution, ``threads`` intra-op threads
(one frame at a time, batch 1), spinning threads kept (they cut the wake-up latency between the
three small models of a frame). TensorRT caches its engines next to the models
(``<models_dir>/trt``) so only the first start pays the build.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from services.detector.config import DEVICES

log = logging.getLogger(__name__)

TENSORRT = "TensorrtExecutionProvider"
CUDA = "CUDAExecutionProvider"
CPU = "CPUExecutionProvider"
_WANTED = {"auto": (TENSORRT, CUDA, CPU), "tensorrt": (TENSORRT, CUDA, CPU),
           "cuda": (CUDA, CPU), "cpu": (CPU,)}


class DeviceUnavailable(RuntimeError):
    """The requested device has no provider in the installed onnxruntime."""


def provider_names(device: str, available: list[str] | tuple[str, ...]) -> list[str]:
    """Providers to try, best first, for ``device`` given the ``available`` ones.

    Pure function (tested without a GPU): ``auto`` keeps what is available of TensorRT > CUDA >
    CPU; an explicit GPU device must have its provider available.
    """
    if device not in DEVICES:
        raise ValueError(f"device must be one of {list(DEVICES)}, got {device!r}")
    wanted = _WANTED[device]
    if device in ("cuda", "tensorrt") and wanted[0] not in available:
        raise DeviceUnavailable(
            f"device {device!r} needs {wanted[0]}, but onnxruntime offers only {list(available)}: "
            "install onnxruntime-gpu (with CUDA 12 / TensorRT libraries) instead of onnxruntime")
    names = [p for p in wanted if p in available]
    return names or [CPU]


def _provider_options(name: str, cache_dir: Path | None) -> dict[str, Any]:
    if name == TENSORRT:
        options: dict[str, Any] = {"trt_fp16_enable": False, "trt_engine_cache_enable": True}
        if cache_dir is not None:
            (cache_dir / "trt").mkdir(parents=True, exist_ok=True)
            options["trt_engine_cache_path"] = str(cache_dir / "trt")
            options["trt_timing_cache_enable"] = True
            options["trt_timing_cache_path"] = str(cache_dir / "trt")
        return options
    if name == CUDA:
        return {"cudnn_conv_algo_search": "HEURISTIC", "do_copy_in_default_stream": True}
    return {}


def session_options(threads: int) -> Any:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    return options


def create_session(path: str | Path, device: str = "auto", threads: int = 2,
                   cache_dir: Path | None = None) -> Any:
    """An ``onnxruntime.InferenceSession`` on the best provider for ``device``.

    Tries the candidate providers in order and falls back (with a warning) when one fails to
    initialise. ``session.get_providers()[0]`` is the provider that runs it.
    """
    import onnxruntime as ort

    names = provider_names(device, ort.get_available_providers())
    options = session_options(threads)
    errors = []
    for i in range(len(names)):
        chain = names[i:]
        providers = [(n, _provider_options(n, cache_dir)) for n in chain]
        try:
            session = ort.InferenceSession(str(path), sess_options=options, providers=providers)
        except Exception as exc:  # a GPU provider whose libraries are missing raises here
            errors.append(f"{chain[0]}: {exc}")
            log.warning("%s: %s failed to start (%s); trying %s", Path(path).name, chain[0],
                        exc, chain[1:] or "nothing")
            continue
        if device in ("cuda", "tensorrt") and session.get_providers()[0] == CPU:
            log.warning("%s: asked for %s but runs on the CPU", Path(path).name, device)
        return session
    raise DeviceUnavailable(f"no execution provider could run {path}: {'; '.join(errors)}")


__all__ = ["CPU", "CUDA", "TENSORRT", "DeviceUnavailable", "create_session", "provider_names"]
