"""Peer renderers for ``bokehray bench``: every one gets the same pinned inputs.

What each peer receives (see docs/benchmarks.md, "What the peers get"):

* the **same scene-linear float32 RGB** image (no gamma on the way in or out; the peers
  blur radiance like bokehray does), and
* the **same per-pixel CoC radius** ``r = K |d - d_f|`` in pixels, computed here once from the
  sample's ``K`` and ``d_f``, so focus and aperture size are identical by construction;
* a **disc** aperture (the benchmark data are disc apertures).

Peers:

* :class:`NaiveScatter`: O(r^2) per pixel scatter in the style of BokehMe's classical renderer
  (Peng et al., CVPR 2022, sec. 3.1), written here in numpy from the paper's description: each
  pixel spreads its colour over the pixels within its CoC with the soft-edged weight
  ``w = (0.5 + 0.5 tanh(4 (r - dist))) / (r^2 + 0.2)``, and the output is
  ``sum(w I) / sum(w)``. No depth ordering: this is the baseline that bleeds a sharp subject
  into the blurred background and shows no partial occlusion.
* :class:`GeglLensBlur`: GEGL's ``gegl:lens-blur`` (Debian ``gegl`` + ``gir1.2-gegl-0.4`` +
  ``python3-gi``), with its aux input as the radius map (``linear-mask``, radius = max CoC),
  run in a persistent worker under the system Python.
* :class:`BlenderDefocus`: Blender's compositor Defocus node (PyPI ``bpy``), with the Z input
  as the radius map (``use_zbuffer`` off, ``z_scale`` = max CoC, ``blur_max`` above it, no
  gamma correction, no threshold), run in a persistent worker under a Python that has
  ``bpy`` (it pins numpy < 2, so usually a separate virtualenv: ``BOKEHRAY_BPY_PYTHON``).

Both external peers run out of process, so a crash or a missing library there cannot take the
benchmark down; their render time is measured around the request (including a few ms to pass
the arrays through files), their peak memory is the worker's own ``VmHWM``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

__all__ = ["BlenderDefocus", "GeglLensBlur", "NaiveScatter", "coc_radius_map"]

_HERE = Path(__file__).resolve().parent


def coc_radius_map(disparity: np.ndarray, k_px: float, focus_disparity: float) -> np.ndarray:
    """The pinned CoC radius map in pixels that every peer gets: ``K |d - d_f|`` (float32)."""
    return (np.float32(k_px) * np.abs(np.asarray(disparity, np.float32) - np.float32(focus_disparity))).astype(
        np.float32)


# --------------------------------------------------------------------------- naive O(r^2) scatter


class NaiveScatter:
    """BokehMe-style classical scatter, O(r^2) per pixel, numpy (see the module docstring)."""

    name = "naive-scatter"

    @staticmethod
    def unavailable() -> str | None:
        return None

    def __call__(self, image: np.ndarray, disparity: np.ndarray, k_px: float, focus_disparity: float) -> np.ndarray:
        r = coc_radius_map(disparity, k_px, focus_disparity).astype(np.float64)
        img = np.asarray(image[..., :3], np.float64)
        h, w = r.shape
        reach = np.floor(r).astype(np.int64) + 1  # a source reaches offsets |dx|, |dy| <= floor(r) + 1
        n = int(reach.max())
        acc = np.zeros((h, w, 3))
        wsum = np.zeros((h, w))
        inv_area = 1.0 / (r * r + 0.2)
        for dy in range(-n, n + 1):
            ys, yd = slice(max(0, -dy), min(h, h - dy)), slice(max(0, dy), min(h, h + dy))
            for dx in range(-n, n + 1):
                xs, xd = slice(max(0, -dx), min(w, w - dx)), slice(max(0, dx), min(w, w + dx))
                rr = r[ys, xs]
                dist = np.hypot(dy, dx)
                wt = (0.5 + 0.5 * np.tanh(4.0 * (rr - dist))) * inv_area[ys, xs]
                wt *= (reach[ys, xs] >= max(abs(dy), abs(dx)))
                wsum[yd, xd] += wt
                acc[yd, xd] += wt[..., None] * img[ys, xs]
        return (acc / np.maximum(wsum, 1e-12)[..., None]).astype(np.float32)


# --------------------------------------------------------------------------- out-of-process workers


class _Worker:
    """A persistent child process answering one JSON request per line (``REPLY {...}`` lines)."""

    def __init__(self, argv: list[str], ready_timeout: float = 120.0):
        self.tmp = Path(tempfile.mkdtemp(prefix="bokehray-peer-"))
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, bufsize=1, cwd=self.tmp)
        self.log: list[str] = []
        hello = self._read_reply(ready_timeout)
        if not hello.get("ok"):
            self.close()
            raise RuntimeError(hello.get("error", "worker did not start"))
        self.info = hello

    def _read_reply(self, timeout: float) -> dict:
        out: dict = {}

        def read() -> None:
            assert self.proc.stdout is not None
            for line in self.proc.stdout:
                if line.startswith("REPLY "):
                    out.update(json.loads(line[6:]))
                    return
                self.log.append(line.rstrip())
                del self.log[:-20]

        t = threading.Thread(target=read, daemon=True)
        t.start()
        t.join(timeout)
        if not out:
            tail = " | ".join(self.log[-3:]) or "no output"
            return {"ok": False, "error": f"no reply (exit code {self.proc.poll()}): {tail}"}
        return out

    def request(self, req: dict, timeout: float = 600.0) -> dict:
        if self.proc.poll() is not None:
            raise RuntimeError(f"worker exited with code {self.proc.returncode}")
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(req) + "\n")
        self.proc.stdin.flush()
        rep = self._read_reply(timeout)
        if not rep.get("ok"):
            raise RuntimeError(rep.get("error", "worker failed"))
        return rep

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                assert self.proc.stdin is not None
                self.proc.stdin.close()
                self.proc.wait(10)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()
        shutil.rmtree(self.tmp, ignore_errors=True)


class _ExternalPeer:
    """Common part of the GEGL and Blender adapters: raw float32 files in, raw float32 out.

    The request holds the linear RGB image and the CoC radius map divided by its maximum
    ``rmax`` (the form both peers take, so the workers do no per-pixel work of their own).
    """

    name = "external"
    script = ""

    def __init__(self) -> None:
        self._worker: _Worker | None = None
        self.last_peak_mb: float | None = None
        self.last_inner_seconds: float | None = None

    def argv(self) -> list[str] | None:  # pragma: no cover - overridden
        raise NotImplementedError

    def start(self) -> None:
        if self._worker is None:
            argv = self.argv()
            if argv is None:
                raise RuntimeError(self.unavailable() or "not available")
            self._worker = _Worker(argv)

    def __call__(self, image: np.ndarray, disparity: np.ndarray, k_px: float, focus_disparity: float) -> np.ndarray:
        self.start()
        assert self._worker is not None
        h, w = disparity.shape
        r = coc_radius_map(disparity, k_px, focus_disparity)
        rmax = float(r.max())
        tmp = self._worker.tmp
        np.ascontiguousarray(image[..., :3], np.float32).tofile(tmp / "image.f32")
        # both peers take the radius map normalised to [0, 1] and scaled by rmax inside
        (r / np.float32(rmax) if rmax > 0 else np.zeros_like(r)).astype(np.float32).tofile(tmp / "radius.f32")
        rep = self._worker.request({"width": w, "height": h, "image": str(tmp / "image.f32"),
                                    "radius": str(tmp / "radius.f32"), "out": str(tmp / "out.f32"),
                                    "rmax": rmax})
        peak = rep.get("peak_kb")
        self.last_peak_mb = peak / 1024 if peak is not None else None
        self.last_inner_seconds = rep.get("seconds")
        return np.fromfile(tmp / "out.f32", np.float32).reshape(h, w, 3).copy()

    def close(self) -> None:
        if self._worker is not None:
            self._worker.close()
            self._worker = None


class GeglLensBlur(_ExternalPeer):
    """GEGL ``gegl:lens-blur`` with the CoC radius map as its aux mask (linear), disc only."""

    name = "gegl-lens-blur"
    script = "_gegl_worker.py"

    @staticmethod
    def _python() -> str | None:
        return os.environ.get("BOKEHRAY_GEGL_PYTHON") or shutil.which("python3", path="/usr/bin:/bin") or None

    @classmethod
    def unavailable(cls) -> str | None:
        py = cls._python()
        if py is None:
            return "no system python3 with GObject introspection found (set BOKEHRAY_GEGL_PYTHON)"
        p = subprocess.run([py, "-c", "import gi; gi.require_version('Gegl', '0.4'); from gi.repository import Gegl"],
                           capture_output=True, text=True)
        if p.returncode != 0:
            return "GEGL bindings missing (apt-get install gegl gir1.2-gegl-0.4 python3-gi)"
        return None

    def argv(self) -> list[str] | None:
        py = self._python()
        return None if py is None else [py, str(_HERE / self.script)]


class BlenderDefocus(_ExternalPeer):
    """Blender's compositor Defocus node, Z input as the radius map (``use_zbuffer`` off), disc."""

    name = "blender-defocus"
    script = "_blender_worker.py"

    @staticmethod
    def _python() -> str | None:
        env = os.environ.get("BOKEHRAY_BPY_PYTHON")
        if env:
            return env
        for cand in (Path.cwd() / ".venv-bpy" / "bin" / "python", Path(sys.prefix).parent / ".venv-bpy" / "bin" / "python"):
            if cand.is_file():
                return str(cand)
        return sys.executable

    @classmethod
    def unavailable(cls) -> str | None:
        py = cls._python()
        p = subprocess.run([py, "-c", "import bpy"], capture_output=True, text=True, timeout=120)
        if p.returncode != 0:
            return f"no 'bpy' module for {py} (pip install bpy in a Python 3.11 venv; set BOKEHRAY_BPY_PYTHON)"
        return None

    def argv(self) -> list[str] | None:
        return [self._python(), str(_HERE / self.script)]
