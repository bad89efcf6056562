"""How live a panel stays while its long step runs out of Slicer's process (issue 80): a
`breastbiomech simulate` of a block compressed by two plates, run by the panels' worker
(BreastBiomech/BreastBiomechCommon/worker.py) and followed as a panel follows it, by polling.

Prints one JSON line: the seconds from the start to the first event and to the first progress
event (the child's interpreter, the library and warp starting), the progress events' interval
while the solver runs (median and largest, s), and the seconds from Cancel to a stopped process.

    python benchmarks/worker_latency.py [--watch-s 10] [--divisions 16] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.append(str(Path(__file__).resolve().parents[1] / "BreastBiomech"))

from BreastBiomechCommon.worker import CommandWorker  # noqa: E402
from BreastBiomechLib.io.meshes import write_vtu  # noqa: E402
from BreastBiomechLib.mesh.primitives import box_mesh  # noqa: E402

SIDE = 40.0  # mm


def block_case(folder: Path, divisions: int, device: str) -> Path:
    """A block compressed 10 % by a plate on each side, in physical time long enough to outlast
    the watch (a case file, docs/solver.md)."""
    write_vtu(folder / "block.vtu", box_mesh((SIDE, SIDE, SIDE), (divisions,) * 3))
    case = {"mesh": "block.vtu", "materials": {"default": {"E": 10e3, "nu": 0.45}},
            "constraints": [{"nodes": "face_xlo", "components": "x"}, {"nodes": "face_ylo", "components": "y"}],
            "plates": [{"name": "base", "point": [0, 0, 0], "normal": [0, 0, 1], "slaves": "face_zlo"},
                       {"name": "top", "point": [0, 0, SIDE], "normal": [0, 0, -1],
                        "displacement": [0, 0, -0.1 * SIDE], "slaves": "face_zhi"}],
            "total_time": 1000.0, "settle_time": 0.0, "damping": 200.0,
            "solver": {"method": "physical", "device": device}}
    path = folder / "case.json"
    path.write_text(json.dumps(case))
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--watch-s", type=float, default=10.0, help="how long progress is watched (s)")
    parser.add_argument("--divisions", type=int, default=16, help="block divisions per side (6 tets a cube)")
    parser.add_argument("--device", default="cpu", help="warp device of the solve")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        case = block_case(Path(folder), args.divisions, args.device)
        started = time.perf_counter()
        worker = CommandWorker(["simulate", str(case), "--out", str(Path(folder) / "out")]).start()
        arrivals, first_event = [], None
        while worker.running and (not arrivals or time.perf_counter() - arrivals[0] < args.watch_s):
            new = worker.poll()
            now = time.perf_counter()
            if new and first_event is None:
                first_event = now - started
            arrivals += [now for e in new if e["event"] == "progress" and e.get("fraction")]
            time.sleep(0.005)
        if not worker.running:
            raise SystemExit(f"the solve ended before the watch did: {worker.error}")
        intervals = np.diff(arrivals)
        cancel_s = worker.cancel()
    print(json.dumps({"tets": 6 * args.divisions ** 3, "device": args.device,
                      "first_event_s": round(first_event, 3), "first_progress_s": round(arrivals[0] - started, 3),
                      "progress_interval_median_s": round(float(np.median(intervals)), 4),
                      "progress_interval_max_s": round(float(intervals.max()), 4),
                      "progress_events": len(arrivals), "cancel_to_stopped_s": round(cancel_s, 4)}))


if __name__ == "__main__":
    main()
