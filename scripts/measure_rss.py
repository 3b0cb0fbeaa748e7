"""Measures the RSS of `posefuse serve` (target/debug/posefuse, or POSEFUSE_BIN): idle after warm-up,
then under N concurrent clients posting examples/frame.json for T seconds (loopback only).
Usage: python3 scripts/measure_rss.py N T   (docs/DEPLOY.md records the results)."""

import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "clients" / "python" / "tests"))

import live_server  # noqa: E402


def main() -> None:
    clients, seconds = int(sys.argv[1]), float(sys.argv[2])
    server = live_server.start(Path(tempfile.mkdtemp()))

    def status() -> dict[str, str]:
        lines = Path(f"/proc/{server.process.pid}/status").read_text().splitlines()
        fields = dict(line.split(":", 1) for line in lines)
        return {k: fields[k].strip() for k in ("VmRSS", "VmHWM", "Threads")}

    try:
        time.sleep(2)
        print("idle:", status())
        body = (ROOT / "examples" / "frame.json").read_bytes()
        stop = time.monotonic() + seconds
        counts = [0] * clients

        def worker(i: int) -> None:
            while time.monotonic() < stop:
                request = urllib.request.Request(
                    server.http_url + "/v1/poses", data=body, headers={"content-type": "application/json"}
                )
                with urllib.request.urlopen(request, timeout=30) as response:
                    response.read()
                counts[i] += 1

        threads = [threading.Thread(target=worker, args=(i,)) for i in range(clients)]
        for t in threads:
            t.start()
        peak = 0
        while any(t.is_alive() for t in threads):
            peak = max(peak, int(status()["VmRSS"].split()[0]))
            time.sleep(0.1)
        print(f"load: {clients} clients for {seconds} s, {sum(counts)} frames; peak VmRSS {peak} kB;", status())
    finally:
        live_server.stop(server)


if __name__ == "__main__":
    main()
