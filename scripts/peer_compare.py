"""`posefuse serve` against its Python peer (scripts/python_peer/server.py: FastAPI + uvicorn,
OpenCV, NumPy, ONNX Runtime) on the same bundle, the same request fixtures and the same load
client (BENCHMARKS.md, "Against a Python peer").

    python scripts/peer_compare.py --bin target/release/posefuse --data data/street300_s2 \
        --peer-python /path/to/venv/bin/python --clients 1,16,64 --duration 10

The peer's packages are not the project's: install scripts/python_peer/requirements.txt into a
virtual environment of its own and pass its python. Each server runs alone (the other stopped);
per server and client count it prints frames/s, persons/s, p50/p99 and peak RSS, then how far
the two servers' keypoints are apart and each one's MPJPE against the fixtures' ground truth
(every labelled keypoint, Waymo's convention), so a faster peer that answers wrongly shows.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from load_check import (  # noqa: E402
    HOST,
    KeepAlive,
    Server,
    free_port,
    percentile,
    raise_fd_limit,
    request,
    wait_ready,
    watch_peak,
)


class Peer(Server):
    """The Python peer under uvicorn with `workers` processes; RSS and CPU are the whole tree's."""

    def __init__(self, python: str, model_dir: str, workers: int, log: Path) -> None:
        self.port = free_port()
        self.log = log
        here = Path(__file__).parent / "python_peer"
        self.proc = subprocess.Popen(
            [python, "-m", "uvicorn", "--app-dir", str(here), "server:app", "--host", HOST,
             "--port", str(self.port), "--workers", str(workers), "--log-level", "warning"],
            env={**os.environ, "MODEL_DIR": model_dir},
            stdout=subprocess.DEVNULL,
            stderr=log.open("w"),
            start_new_session=True,
        )
        wait_ready(self.proc, self.port, log, "peer")

    def proc_status(self) -> dict[str, int]:
        """VmRSS (kB) summed over uvicorn and its worker processes."""
        total = {"VmRSS": 0, "Threads": 0}
        for pid in tree(self.proc.pid):
            try:
                for line in Path(f"/proc/{pid}/status").read_text().splitlines():
                    key, _, value = line.partition(":")
                    if key in total:
                        total[key] += int(value.split()[0])
            except OSError:
                pass
        return total

    def stop(self) -> int:
        os.killpg(self.proc.pid, 15)
        try:
            return self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, 9)
            return -9


def tree(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            todo += [int(c) for c in Path(f"/proc/{p}/task/{p}/children").read_text().split()]
        except OSError:
            pass
    return out


async def load(server: Server, frames: list[bytes], persons: list[int], clients: int, duration: float) -> dict:
    """`clients` keep-alive clients, each sending the fixtures in turn for `duration` seconds and
    honouring Retry-After on a 429; `clients_answered` counts those that had any answer."""
    done = {"frames": 0, "persons": 0, "refused": 0, "failed": 0}
    answered: set[int] = set()
    latency: list[float] = []
    peak = {"VmRSS": 0}
    stop_at = time.time() + duration

    async def client(i: int) -> None:
        conn, k = KeepAlive(server.port), i
        while time.time() < stop_at:
            t = time.perf_counter()
            try:
                status = await conn.post("/v1/poses", frames[k % len(frames)])
            except (TimeoutError, OSError, asyncio.IncompleteReadError):
                status = 0
            if status == 200:
                latency.append(time.perf_counter() - t)
                done["frames"] += 1
                done["persons"] += persons[k % len(frames)]
                answered.add(i)
                k += clients
            elif status == 429:
                done["refused"] += 1
                await asyncio.sleep(min(conn.retry_after or 0.0, max(stop_at - time.time(), 0.0)))
            else:
                done["failed"] += 1
                # a dead or refusing server must not turn the client into a busy loop on the
                # cores the next server will be measured on
                await asyncio.sleep(0.05)
        conn.close()

    t0 = time.time()
    await asyncio.gather(watch_peak(server, stop_at, peak), *(client(i) for i in range(clients)))
    took = time.time() - t0
    return {
        "clients": clients,
        "clients_answered": len(answered),
        "frames_per_s": round(done["frames"] / took, 1),
        "persons_per_s": round(done["persons"] / took, 1),
        "p50_ms": round(percentile(latency, 0.5) * 1e3, 2),
        "p99_ms": round(percentile(latency, 0.99) * 1e3, 2),
        "refused": done["refused"],
        "failed": done["failed"],
        "peak_rss_mb": round(peak["VmRSS"] / 1024),
    }


async def answers(server: Server, frames: list[bytes]) -> list[dict]:
    out = []
    for body in frames:
        status, text = await request(server.port, "POST", "/v1/poses", body, timeout=60)
        out.append(json.loads(text) if status == 200 else {"persons": []})
    return out


def keypoints(person: dict) -> np.ndarray | None:
    if person.get("keypoints_3d") is not None:  # the peer's answer
        return np.asarray(person["keypoints_3d"], dtype=np.float64)
    if person.get("keypoints"):  # the server's
        return np.asarray([k["xyz"] for k in person["keypoints"]], dtype=np.float64)
    return None


def accuracy(fixtures: list[dict], served: list[dict], peer: list[dict]) -> dict:
    """Over the persons both servers answer with the fusion network (matched by id): the mean
    keypoint distance between the two, split by whether the box holds more points than the
    networks take (then the two choose different points), and each one's MPJPE."""
    apart: dict[str, list[float]] = {"all_points_taken": [], "points_chosen": []}
    err: dict[str, list[float]] = {"posefuse": [], "peer": []}
    for fx, a, b in zip(fixtures, served, peer, strict=True):
        ours = {p.get("id"): p for p in a["persons"]}
        theirs = {p.get("id"): p for p in b["persons"]}
        for p in fx["persons"]:
            pa, pb = ours.get(p["id"]), theirs.get(p["id"])
            if pa is None or pb is None or "fusion" != pa.get("mode") or "fusion" != pb.get("mode"):
                continue
            ka, kb = keypoints(pa), keypoints(pb)
            if ka is None or kb is None:
                continue
            gt = p["ground_truth"]["keypoints_3d"]
            xyz = np.asarray(gt["xyz"], dtype=np.float64)
            labelled = np.asarray(gt["visible"]) | np.asarray(gt.get("occluded", [False] * len(xyz)))
            key = "points_chosen" if int(pa.get("num_points", 0)) > 256 else "all_points_taken"
            apart[key].append(float(np.linalg.norm(ka - kb, axis=1).mean()))
            err["posefuse"] += np.linalg.norm(ka - xyz, axis=1)[labelled].tolist()
            err["peer"] += np.linalg.norm(kb - xyz, axis=1)[labelled].tolist()
    return {
        "fusion_persons": {k: len(v) for k, v in apart.items()},
        "apart_cm": {k: round(float(np.mean(v)) * 100, 2) if v else None for k, v in apart.items()},
        "mpjpe_cm": {k: round(float(np.mean(v)) * 100, 2) for k, v in err.items()},
    }


async def main_async(a: argparse.Namespace) -> dict:
    raise_fd_limit()
    files = sorted((a.data / "requests").glob("*.json"))
    fixtures = [json.loads(f.read_text()) for f in files]
    frames = [f.read_bytes() for f in files]
    persons = [len(fx["persons"]) for fx in fixtures]
    counts = [int(c) for c in a.clients.split(",")]
    result: dict = {"frames": len(frames), "persons_per_frame": round(sum(persons) / len(persons), 3)}
    served = {}
    for name in ("posefuse", "peer"):
        if name == "posefuse":
            server: Server = Server(a.bin, a.model_dir, {}, a.logs / "posefuse.log")
        else:
            server = Peer(a.peer_python, a.model_dir, a.workers, a.logs / "peer.log")
        try:
            served[name] = await answers(server, frames)
            await load(server, frames, persons, max(counts), 2.0)  # warm-up
            result[name] = [await load(server, frames, persons, c, a.duration) for c in counts]
        finally:
            server.stop()
        print(json.dumps({name: result[name]}), flush=True)
    result["ratio_persons_per_s"] = {
        str(c): round(p["persons_per_s"] / max(q["persons_per_s"], 1e-9), 2)
        for c, p, q in zip(counts, result["posefuse"], result["peer"], strict=True)
    }
    result["agreement"] = accuracy(fixtures, served["posefuse"], served["peer"])
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bin", default="target/release/posefuse")
    ap.add_argument("--model-dir", default="models/default")
    ap.add_argument("--data", type=Path, required=True, help="simulator output with requests/*.json")
    ap.add_argument("--peer-python", required=True, help="python of a venv with the peer's requirements")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 2, help="uvicorn worker processes")
    ap.add_argument("--clients", default="1,16,64")
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--logs", type=Path, default=Path("/tmp"))
    a = ap.parse_args()
    print(json.dumps(asyncio.run(main_async(a)), indent=1))


if __name__ == "__main__":
    main()
