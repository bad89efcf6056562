"""How busy each GPU was while a benchmark ran: ``nvidia-smi`` sampled in the background.

A local Dask cluster pins worker i to GPU i (round robin), so on a machine with as many workers as
GPUs each GPU's figures are its worker's. Utilisation is nvidia-smi's "utilization.gpu": the
percentage of the sample period in which a kernel ran on the GPU (not how much of the GPU it
filled). Where nvidia-smi is absent (a machine without an NVIDIA driver) nothing is sampled.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile

QUERY = "index,utilization.gpu,memory.used"


def summarise_samples(text: str) -> dict[str, dict]:
    """nvidia-smi's ``--query-gpu=index,utilization.gpu,memory.used --format=csv,noheader,nounits``
    lines -> {GPU index: {"samples", "mean_utilisation_percent", "peak_utilisation_percent",
    "busy_fraction" (share of samples with any kernel running), "peak_memory_mib"}}. Lines that
    are not three numbers (a driver's "[N/A]", a line cut off when sampling stopped) are skipped."""
    per_gpu: dict[str, list[tuple[float, float]]] = {}
    for line in text.splitlines():
        fields = [f.strip() for f in line.split(",")]
        if len(fields) != 3:
            continue
        try:
            utilisation, memory = float(fields[1]), float(fields[2])
        except ValueError:
            continue
        per_gpu.setdefault(fields[0], []).append((utilisation, memory))
    return {gpu: {"samples": len(samples),
                  "mean_utilisation_percent": round(sum(u for u, _ in samples) / len(samples), 1),
                  "peak_utilisation_percent": max(u for u, _ in samples),
                  "busy_fraction": round(sum(u > 0 for u, _ in samples) / len(samples), 3),
                  "peak_memory_mib": max(m for _, m in samples)}
            for gpu, samples in sorted(per_gpu.items())}


class GpuUsage:
    """``with GpuUsage() as usage: ...`` samples every GPU every ``period_ms`` while the block
    runs; afterwards ``usage.summary`` is :func:`summarise_samples`'s dict, or None where the
    machine has no nvidia-smi."""

    def __init__(self, period_ms: int = 500):
        self.period_ms = period_ms
        self.summary: dict[str, dict] | None = None
        self._process = None
        self._log = None

    def __enter__(self) -> GpuUsage:
        executable = shutil.which("nvidia-smi")
        if executable is not None:
            self._log = tempfile.TemporaryFile(mode="w+")
            self._process = subprocess.Popen([executable, f"--query-gpu={QUERY}", "--format=csv,noheader,nounits",
                                              "-lms", str(self.period_ms)], stdout=self._log,
                                             stderr=subprocess.DEVNULL)
        return self

    def __exit__(self, *exc) -> None:
        if self._process is None:
            return
        self._process.terminate()
        self._process.wait(timeout=10)
        self._log.seek(0)
        self.summary = summarise_samples(self._log.read())
        self._log.close()
