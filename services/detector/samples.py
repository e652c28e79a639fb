"""Real test photographs for the detector's tests and benchmark (fetched, never shipped).

``basketball1.png`` and ``basketball2.png`` (640x480, two consecutive frames of a man catching a
ball, a second person raising a hand; OpenCV sample data, Apache-2.0 / BSD-3-Clause according to
Debian's ``copyright`` file, which is extracted alongside) come from the Debian package
``opencv-doc``: ``apt-get download`` (no install, no root needed) and ``dpkg-deb
--fsys-tarfile``, cached under ``$XDG_CACHE_HOME/handkse/test-data/opencv-doc``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tarfile
import tempfile
from pathlib import Path

DATA_MEMBER = "./usr/share/doc/opencv-doc/examples/data/"
IMAGES = ("basketball1.png", "basketball2.png")
COPYRIGHT = "./usr/share/doc/opencv-doc/copyright"


class AptUnavailable(RuntimeError):
    """``apt-get`` or ``dpkg-deb`` is not installed (not a Debian-like system)."""


def default_cache() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "handkse" / "test-data" / "opencv-doc"


def opencv_doc_images(dest: Path | None = None) -> Path:
    """Folder holding basketball1/2.png (and ``copyright``); downloads opencv-doc when needed.

    Raises :class:`AptUnavailable` without apt, ``RuntimeError`` when the download fails.
    """
    dest = dest or default_cache()
    if all((dest / name).is_file() for name in IMAGES):
        return dest
    if shutil.which("apt-get") is None or shutil.which("dpkg-deb") is None:
        raise AptUnavailable("apt-get/dpkg-deb unavailable: cannot fetch the opencv-doc test "
                             "images (Debian package opencv-doc, basketball1/2.png)")
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        done = subprocess.run(["apt-get", "download", "opencv-doc"], cwd=tmp,
                              capture_output=True, text=True, check=False, timeout=900)
        debs = list(Path(tmp).glob("opencv-doc_*.deb"))
        if done.returncode != 0 or not debs:
            raise RuntimeError(f"apt-get download opencv-doc failed: "
                               f"{done.stderr.strip()[-500:]} (run `apt-get update` first?)")
        wanted = {DATA_MEMBER + name: name for name in IMAGES}
        wanted[COPYRIGHT] = "copyright"
        with subprocess.Popen(["dpkg-deb", "--fsys-tarfile", str(debs[0])],
                              stdout=subprocess.PIPE) as proc:
            assert proc.stdout is not None
            with tarfile.open(fileobj=proc.stdout, mode="r|*") as tar:
                for member in tar:
                    if member.name in wanted and member.isfile():
                        f = tar.extractfile(member)
                        assert f is not None
                        part = dest / (wanted[member.name] + ".part")
                        part.write_bytes(f.read())
                        part.replace(dest / wanted[member.name])
            with open(os.devnull, "wb") as sink:
                shutil.copyfileobj(proc.stdout, sink)  # drain, so dpkg-deb exits cleanly
    missing = [n for n in IMAGES if not (dest / n).is_file()]
    if missing:
        raise RuntimeError(f"opencv-doc did not contain {missing}")
    return dest


__all__ = ["IMAGES", "AptUnavailable", "default_cache", "opencv_doc_images"]
