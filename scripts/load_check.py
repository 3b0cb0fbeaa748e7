"""Fault-and-load checks against a `posefuse serve` process on loopback (BENCHMARKS.md, targets of
docs/OPERATIONS.md). Standard library only; every count and duration is bounded.

  python scripts/load_check.py drain    --bin target/release/posefuse
  python scripts/load_check.py idle     --bin target/release/posefuse --idle 19500
  python scripts/load_check.py overload --bin target/release/posefuse --frames DIR/requests
  python scripts/load_check.py cancel   --bin target/release/posefuse --frames DIR/requests

Each prints one JSON line of measurements and exits 1 when a target is missed.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import resource
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

HOST = "127.0.0.1"


def free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return s.getsockname()[1]


def ready(port: int) -> bool:
    """GET /readyz with a blocking socket: True on 200."""
    with socket.create_connection((HOST, port), timeout=2) as c:
        c.sendall(b"GET /readyz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        return c.recv(64).startswith(b"HTTP/1.1 200")


def wait_ready(proc: subprocess.Popen, port: int, log: Path, what: str) -> None:
    """Until /readyz answers 200; exits with the log's tail if the process dies first."""
    deadline = time.time() + 120
    while time.time() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"{what} exited: {log.read_text()[-2000:]}")
        try:
            if ready(port):
                return
        except OSError:
            pass
        time.sleep(0.1)
    raise SystemExit(f"{what} not ready in 120 s")


class Server:
    """A `posefuse serve` child process with its log in a file."""

    def __init__(
        self, binary: str, model_dir: str, env: dict[str, str], log: Path
    ) -> None:
        self.port = free_port()
        full_env = {**os.environ, **env}
        self.log = log
        self.proc = subprocess.Popen(
            [
                binary,
                "serve",
                "--addr",
                f"{HOST}:{self.port}",
                "--model-dir",
                model_dir,
            ],
            env=full_env,
            stdout=subprocess.DEVNULL,
            stderr=log.open("w"),
        )
        wait_ready(self.proc, self.port, log, "server")

    def proc_status(self) -> dict[str, int]:
        """VmRSS (kB) and Threads of the server."""
        out = {}
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in ("VmRSS", "Threads"):
                out[key] = int(value.split()[0])
        return out

    def cpu_seconds(self) -> float:
        fields = (
            Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        )
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return -9


async def read_response_with_headers(
    reader: asyncio.StreamReader,
) -> tuple[int, dict[str, str], bytes]:
    head = await reader.readuntil(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    status = int(lines[0].split()[1])
    headers = {}
    for line in lines[1:]:
        if ":" in line:
            name, value = line.split(":", 1)
            headers[name.strip().lower()] = value.strip()
    length = int(headers.get("content-length", "0"))
    body = await reader.readexactly(length) if length else b""
    return status, headers, body


async def read_response(reader: asyncio.StreamReader) -> tuple[int, bytes]:
    status, _, body = await read_response_with_headers(reader)
    return status, body


async def request(
    port: int, method: str, path: str, body: bytes, timeout: float = 30
) -> tuple[int, bytes]:
    reader, writer = await asyncio.wait_for(
        asyncio.open_connection(HOST, port), timeout
    )
    try:
        head = (
            f"{method} {path} HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
        )
        head += f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
        writer.write(head.encode() + body)
        await writer.drain()
        return await asyncio.wait_for(read_response(reader), timeout)
    finally:
        writer.close()


class KeepAlive:
    """One client connection reused for its requests."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.conn: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
        # The last refusal's Retry-After (seconds), when it gave one.
        self.retry_after: float | None = None

    async def post(self, path: str, body: bytes, timeout: float = 60) -> int:
        for attempt in range(2):
            if self.conn is None:
                self.conn = await asyncio.open_connection(HOST, self.port)
            reader, writer = self.conn
            head = (
                f"POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                f"Content-Length: {len(body)}\r\n\r\n"
            )
            try:
                # The answer may come before the body is read (429 at admission): wait for it,
                # not for the body to be sent.
                writer.write(head.encode() + body)
                status, headers, _ = await asyncio.wait_for(
                    read_response_with_headers(reader), timeout
                )
                if status == 429:
                    self.retry_after = float(headers.get("retry-after", "1"))
                if headers.get("connection", "").lower() == "close":
                    writer.close()
                    self.conn = None
                else:
                    # The body may still be on its way (an early 429): finish sending it
                    # before the next request on this connection.
                    await asyncio.wait_for(writer.drain(), timeout)
                return status
            except (OSError, asyncio.IncompleteReadError):
                writer.close()
                self.conn = None
                if attempt == 1:
                    raise
        return 0

    def close(self) -> None:
        if self.conn:
            self.conn[1].close()


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


def raise_fd_limit() -> int:
    _soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    return hard


def load_frames(directory: str | None, limit: int = 64) -> list[bytes]:
    if directory is None:
        raise SystemExit("--frames DIR (simulator request fixtures) is needed")
    files = sorted(Path(directory).glob("*.json"))[:limit]
    if not files:
        raise SystemExit(f"no *.json in {directory}")
    return [f.read_bytes() for f in files]


# ---------------------------------------------------------------- drain


async def drain_check(a: argparse.Namespace) -> dict:
    server = Server(
        a.bin, a.model_dir, {"POSEFUSE_DRAIN_TIMEOUT": str(a.drain_timeout)}, a.log
    )
    port = server.port
    half = []
    for i in range(50):
        _, w = await asyncio.open_connection(HOST, port)
        if i % 2:
            w.write(b"POST /v1/poses HTTP/1.1\r\nHost: x\r\n")
        else:
            w.write(
                b"POST /v1/poses HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 999\r\n\r\n{"
            )
        await w.drain()
        half.append(w)
    # A running NDJSON stream: a frame, then the body kept open.
    frame = (a.frames and load_frames(a.frames, 1)[0]) or None
    reader, writer = await asyncio.open_connection(HOST, port)
    writer.write(
        b"POST /v1/poses:batch HTTP/1.1\r\nHost: x\r\nContent-Type: application/x-ndjson\r\n"
        b"Transfer-Encoding: chunked\r\n\r\n"
    )
    line = (frame or b'{"bad": 1}') + b"\n"
    writer.write(f"{len(line):x}\r\n".encode() + line + b"\r\n")
    await writer.drain()
    await asyncio.sleep(1.0)
    t0 = time.time()
    server.proc.send_signal(signal.SIGTERM)
    stream_out = b""
    try:
        stream_out = await asyncio.wait_for(reader.read(), 5)
    except (TimeoutError, OSError):
        pass
    code = await asyncio.to_thread(server.proc.wait, a.drain_timeout + 30)
    took = time.time() - t0
    log = a.log.read_text()
    result = {
        "check": "drain",
        "exit_code": code,
        "exit_s": round(took, 2),
        "drain_timeout_s": a.drain_timeout,
        "stream_told_to_end": b"unavailable" in stream_out,
        "cut_logged": "drain deadline passed" in log,
    }
    result["ok"] = (
        code == 0 and took < a.drain_timeout + 2 and result["stream_told_to_end"]
    )
    return result


# ---------------------------------------------------------------- idle flood


async def idle_check(a: argparse.Namespace) -> dict:
    raise_fd_limit()
    server = Server(a.bin, a.model_dir, {}, a.log)
    port = server.port
    frame = load_frames(a.frames, 1)[0] if a.frames else None
    idle = []
    opened_at = time.time()
    for _ in range(a.idle):
        try:
            _, w = await asyncio.open_connection(HOST, port)
            idle.append(w)
        except OSError:
            break
    open_s = time.time() - opened_at
    latencies: list[float] = []
    failures = 0
    stop_at = time.time() + a.duration

    async def client() -> None:
        nonlocal failures
        while time.time() < stop_at:
            t = time.perf_counter()
            try:
                if frame is None:
                    status, _ = await request(port, "GET", "/healthz", b"", timeout=5)
                else:
                    status, _ = await request(
                        port, "POST", "/v1/poses", frame, timeout=5
                    )
                if status != 200:
                    failures += 1
            except (TimeoutError, OSError, asyncio.IncompleteReadError):
                failures += 1
            latencies.append(time.perf_counter() - t)

    await asyncio.gather(*(client() for _ in range(4)))
    status = server.proc_status()
    for w in idle:
        w.close()
    code = server.stop()
    log = a.log.read_text()
    result = {
        "check": "idle",
        "idle_opened": len(idle),
        "open_s": round(open_s, 1),
        "requests": len(latencies),
        "failures": failures,
        "p50_ms": round(percentile(latencies, 0.5) * 1e3, 1),
        "p99_ms": round(percentile(latencies, 0.99) * 1e3, 1),
        "server_rss_mb": round(status.get("VmRSS", 0) / 1024),
        "server_threads": status.get("Threads"),
        "accept_errors_logged": log.count("accept failed"),
        "exit_code": code,
    }
    result["ok"] = failures == 0 and percentile(latencies, 0.99) < 1.0
    return result


# ---------------------------------------------------------------- overload


async def watch_peak(server: Server, stop_at: float, peak: dict[str, int]) -> None:
    """Until stop_at, keeps in `peak` the largest of each of its keys in the server's status."""
    while time.time() < stop_at:
        s = server.proc_status()
        for k, v in peak.items():
            peak[k] = max(v, s.get(k, 0))
        await asyncio.sleep(0.1)


async def run_clients(
    server: Server, frames: list[bytes], clients: int, duration: float, backoff: str
) -> dict:
    statuses: dict[int, int] = {}
    ok_latency: list[float] = []
    refused_latency: list[float] = []
    peak = {"VmRSS": 0, "Threads": 0}
    stop_at = time.time() + duration

    async def client(i: int) -> None:
        conn = KeepAlive(server.port)
        k = i
        while time.time() < stop_at:
            body = frames[k % len(frames)]
            k += clients
            t = time.perf_counter()
            try:
                status = await conn.post("/v1/poses", body)
            except (TimeoutError, OSError, asyncio.IncompleteReadError):
                status = 0
            dt = time.perf_counter() - t
            statuses[status] = statuses.get(status, 0) + 1
            if status == 200:
                ok_latency.append(dt)
            elif status == 429:
                refused_latency.append(dt)
                wait = conn.retry_after if backoff == "retry-after" else float(backoff)
                await asyncio.sleep(min(wait or 0.0, max(stop_at - time.time(), 0.0)))
        conn.close()

    t0 = time.time()
    await asyncio.gather(watch_peak(server, stop_at, peak), *(client(i) for i in range(clients)))
    took = time.time() - t0
    return {
        "clients": clients,
        "ok_per_s": round(statuses.get(200, 0) / took, 1),
        "statuses": {str(k): v for k, v in sorted(statuses.items())},
        "ok_p50_ms": round(percentile(ok_latency, 0.5) * 1e3, 1),
        "ok_p99_ms": round(percentile(ok_latency, 0.99) * 1e3, 1),
        "p50_429_ms": round(percentile(refused_latency, 0.5) * 1e3, 1),
        "p99_429_ms": round(percentile(refused_latency, 0.99) * 1e3, 1),
        "max_429_ms": round(max(refused_latency, default=0.0) * 1e3, 1),
        "peak_rss_mb": round(peak["VmRSS"] / 1024),
        "peak_threads": peak["Threads"],
    }


async def overload_check(a: argparse.Namespace) -> dict:
    raise_fd_limit()
    frames = load_frames(a.frames)
    # The server's waiting line: a 429 comes at once (the line full or off) or when a frame's wait
    # in it is over, never later.
    server = Server(a.bin, a.model_dir, {"POSEFUSE_ADMISSION_WAIT_MS": str(a.admission_wait_ms)}, a.log)
    refusal_bound_ms = a.admission_wait_ms + 50
    base = await run_clients(server, frames, 16, a.duration, a.backoff)
    high = await run_clients(server, frames, a.clients, a.duration, a.backoff)
    await asyncio.sleep(30)
    after = server.proc_status().get("VmRSS", 0) / 1024
    code = server.stop()
    result = {
        "check": "overload",
        "backoff": a.backoff,
        "base": base,
        "high": high,
        "throughput_ratio": round(high["ok_per_s"] / max(base["ok_per_s"], 1e-9), 3),
        "admission_wait_ms": a.admission_wait_ms,
        "refusal_bound_ms": refusal_bound_ms,
        "rss_30s_after_mb": round(after),
        "exit_code": code,
    }
    result["ok"] = (
        result["throughput_ratio"] >= 0.9
        and high["max_429_ms"] <= refusal_bound_ms
        and high["peak_rss_mb"] <= 1024
        and after < 400
        and "0" not in high["statuses"]
    )
    return result


# ---------------------------------------------------------------- cancellation


async def cancel_check(a: argparse.Namespace) -> dict:
    frames = load_frames(a.frames, 1)
    # A heavy frame: every person of the fixture repeated up to 256.
    frame = json.loads(frames[0])
    persons = frame["persons"]
    frame["persons"] = [dict(persons[i % len(persons)], id=f"p{i}") for i in range(256)]
    body = json.dumps(frame).encode()
    server = Server(a.bin, a.model_dir, {"POSEFUSE_REQUEST_TIMEOUT_MS": "50"}, a.log)
    out = {"check": "cancel"}
    status, _ = await request(server.port, "POST", "/v1/poses", body, timeout=60)
    out["status_after_deadline"] = status
    await asyncio.sleep(0.2)
    c0 = server.cpu_seconds()
    await asyncio.sleep(2.0)
    out["cpu_s_in_2s_after_504"] = round(server.cpu_seconds() - c0, 3)
    # Hang up 50 ms into a request with a generous deadline.
    server.stop()
    server = Server(a.bin, a.model_dir, {}, a.log)
    t = time.perf_counter()
    c_start = server.cpu_seconds()
    status, _ = await request(server.port, "POST", "/v1/poses", body, timeout=120)
    out["full_frame_s"] = round(time.perf_counter() - t, 2)
    out["full_frame_cpu_s"] = round(server.cpu_seconds() - c_start, 2)
    _, w = await asyncio.open_connection(HOST, server.port)
    w.write(
        (
            f"POST /v1/poses HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            f"Content-Length: {len(body)}\r\n\r\n"
        ).encode()
        + body
    )
    await w.drain()
    await asyncio.sleep(0.05)
    w.close()
    await asyncio.sleep(0.2)
    c0 = server.cpu_seconds()
    await asyncio.sleep(2.0)
    out["cpu_s_in_2s_after_hang_up"] = round(server.cpu_seconds() - c0, 3)
    server.stop()
    out["ok"] = (
        out["status_after_deadline"] == 504
        and max(out["cpu_s_in_2s_after_504"], out["cpu_s_in_2s_after_hang_up"]) < 0.1
    )
    return out


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("check", choices=["drain", "idle", "overload", "cancel"])
    p.add_argument("--bin", default="target/release/posefuse")
    p.add_argument("--model-dir", default="models/default")
    p.add_argument(
        "--frames",
        help="directory of request fixtures (posefuse simulate --requests N)",
    )
    p.add_argument("--idle", type=int, default=19_500, help="idle connections to open")
    p.add_argument("--clients", type=int, default=256)
    p.add_argument(
        "--duration", type=float, default=15.0, help="seconds per load phase"
    )
    p.add_argument(
        "--backoff",
        default="0.05",
        help="seconds a refused overload client waits before its next request, or "
        "'retry-after' for the server's Retry-After",
    )
    p.add_argument(
        "--admission-wait-ms",
        type=int,
        default=2000,
        help="the server's --admission-wait-ms for the overload check (2000: its default; "
        "0: no waiting line, every 429 at once)",
    )
    p.add_argument("--drain-timeout", type=int, default=5)
    p.add_argument("--log", type=Path, default=Path("/tmp/posefuse-load-check.log"))
    a = p.parse_args()
    if not Path(a.bin).exists():
        print(f"skipped: {a.bin} is missing (cargo build --release)")
        return
    check = {
        "drain": drain_check,
        "idle": idle_check,
        "overload": overload_check,
        "cancel": cancel_check,
    }[a.check]
    result = asyncio.run(check(a))
    print(json.dumps(result))
    sys.exit(0 if result.get("ok") else 1)


if __name__ == "__main__":
    main()
