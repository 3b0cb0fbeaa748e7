"""The batch Indexed Job (deploy/batch/): posefuse's own `waymo score --shard i/k` per pod.

Offline: the Job's command line parses against the scorer's flags (src/cli/waymo.rs), every
$(VAR) it uses is declared, the shard count matches `completions` and `parallelism`, each index
writes its own folder, and the paths lie on the shipped `posefuse-data` claim. With a built binary
(target/debug/posefuse) the Job's command lines run as its pods would, on a small simulated dataset.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
from pathlib import Path

import live_server
import pytest
import yaml
from test_manifests import cli_flags, dockerfile, parse_flags, quantity

ROOT = Path(__file__).resolve().parents[2]
BATCH = ROOT / "deploy" / "batch"
INDEX = "$(JOB_COMPLETION_INDEX)"


def docs() -> dict[str, dict]:
    """The kustomization's resources by kind, and the kustomization itself."""
    kustomization = yaml.safe_load(BATCH.joinpath("kustomization.yaml").read_text())
    out = {"Kustomization": kustomization}
    for name in kustomization["resources"]:
        for doc in yaml.safe_load_all(BATCH.joinpath(name).read_text()):
            assert doc["kind"] not in out, f"two {doc['kind']}s"
            out[doc["kind"]] = doc
    return out


def job_container() -> tuple[dict, dict]:
    job = docs()["Job"]
    (container,) = job["spec"]["template"]["spec"]["containers"]
    return job, container


def command_line(container: dict) -> list[str]:
    """The container's argv, the image's ENTRYPOINT standing in for a missing `command`."""
    command = container.get("command") or ["posefuse"]
    return [*command, *container.get("args", [])]


def test_the_kustomization_ships_the_job_and_its_claim():
    d = docs()
    assert set(d) == {"Kustomization", "Job", "PersistentVolumeClaim"}
    assert "configMapGenerator" not in d["Kustomization"], "no script beside the image any more"
    assert not list(BATCH.glob("*.py"))
    claim = d["PersistentVolumeClaim"]
    assert claim["metadata"]["name"] == "posefuse-data"
    # The shards' pods run at once, on any nodes.
    assert "ReadWriteMany" in claim["spec"]["accessModes"]
    assert quantity(claim["spec"]["resources"]["requests"]["storage"]) > 0
    volumes = {v["name"]: v for v in d["Job"]["spec"]["template"]["spec"]["volumes"]}
    claims = {v["persistentVolumeClaim"]["claimName"] for v in volumes.values() if "persistentVolumeClaim" in v}
    assert claims == {"posefuse-data"}


def test_the_job_runs_posefuses_own_scorer():
    job, c = job_container()
    assert c["image"].split(":")[0] == dockerfile()["image"]
    argv = command_line(c)
    assert Path(argv[0]).name == "posefuse" and argv[1:3] == ["waymo", "score"]
    flags = parse_flags(argv[3:])
    assert set(flags) <= cli_flags("WaymoScoreArgs"), f"{set(flags) - cli_flags('WaymoScoreArgs')} unknown"
    assert {"--dataset", "--out", "--shard", "--model-dir"} <= set(flags)
    # In-process, with the image's own bundle (the one the Deployment serves), not through a server.
    assert "--server" not in flags
    assert flags["--model-dir"] == dockerfile()["env"]["POSEFUSE_MODEL_DIR"]


def test_each_index_scores_its_own_shard_into_its_own_folder():
    job, c = job_container()
    spec = job["spec"]
    assert spec["completionMode"] == "Indexed"
    flags = parse_flags(command_line(c)[3:])
    shard = re.fullmatch(re.escape(INDEX) + r"/(\d+)", flags["--shard"])
    assert shard, f"--shard {flags['--shard']} is not {INDEX}/k"
    count = int(shard.group(1))
    assert spec["completions"] == spec["parallelism"] == count
    for index in range(count):
        # What the scorer's parse_shard accepts: 0 <= i < k.
        i, k = (int(v) for v in flags["--shard"].replace(INDEX, str(index)).split("/"))
        assert 0 <= i < k
    assert INDEX in flags["--out"], "each shard writes its own folder"
    assert INDEX not in flags["--dataset"]
    # A $(VAR) that is not declared would reach the scorer verbatim.
    env = {e["name"]: e for e in c.get("env", [])}
    for var in re.findall(r"\$\(([A-Z0-9_]+)\)", " ".join(command_line(c))):
        assert var in env, f"$({var}) is not declared in the container's env"
    assert env["JOB_COMPLETION_INDEX"]["valueFrom"]["fieldRef"]["fieldPath"] == (
        "metadata.annotations['batch.kubernetes.io/job-completion-index']"
    )
    # A failed shard retries alone; node drains do not use up its retries.
    assert spec["backoffLimitPerIndex"] >= 1
    rules = spec["podFailurePolicy"]["rules"]
    assert any(r["action"] == "Ignore" and r["onPodConditions"][0]["type"] == "DisruptionTarget" for r in rules)


def test_the_dataset_is_read_only_and_the_results_are_on_the_claim():
    job, c = job_container()
    flags = parse_flags(command_line(c)[3:])
    mounts = {m["mountPath"]: m for m in c["volumeMounts"]}
    volumes = {v["name"]: v for v in job["spec"]["template"]["spec"]["volumes"]}

    def mount_of(path: str) -> dict:
        (m,) = [m for p, m in mounts.items() if path == p or path.startswith(p.rstrip("/") + "/")]
        return m

    dataset, out = mount_of(flags["--dataset"]), mount_of(flags["--out"])
    assert dataset.get("readOnly") is True and not out.get("readOnly")
    for m in (dataset, out):
        assert volumes[m["name"]]["persistentVolumeClaim"]["claimName"] == "posefuse-data"
    assert dataset.get("subPath") != out.get("subPath")
    sc = job["spec"]["template"]["spec"]["securityContext"]
    assert sc["runAsUser"] == dockerfile()["uid"] and sc["fsGroup"]
    assert c["securityContext"]["readOnlyRootFilesystem"] is True


def pod_command(container: dict, index: int, mounts: dict[str, Path]) -> list[str]:
    """The Job's argv for pod `index`, its mount paths and the image's bundle moved to `mounts`."""
    out = []
    for arg in command_line(container)[1:]:
        arg = arg.replace(INDEX, str(index))
        for inside, outside in mounts.items():
            if arg == inside or arg.startswith(inside + "/"):
                arg = str(outside) + arg[len(inside):]
        out.append(arg)
    return out


def run(argv: list[str], timeout: float = 300) -> subprocess.CompletedProcess:
    env = {**os.environ, "ORT_DYLIB_PATH": os.environ.get("ORT_DYLIB_PATH", str(ROOT / ".ort/lib/libonnxruntime.so"))}
    env.setdefault("RUST_LOG", "warn")
    return subprocess.run(argv, env=env, capture_output=True, text=True, timeout=timeout)


def test_the_jobs_pods_score_every_segment_once(tmp_path):
    reason = live_server.missing_reason()
    if reason:
        pytest.skip(f"no posefuse binary: {reason}")
    binary = str(live_server.binary())
    job, c = job_container()
    count = job["spec"]["completions"]
    data = tmp_path / "claim"
    sim = run([binary, "waymo", "simulate", "--out", str(data / "in"), "--segments", str(count + 1), "--frames", "2",
               "--top-rows", "32", "--top-cols", "600", "--short-rows", "16", "--short-cols", "60",
               "--image-scale", "0.25", "--keypoint-fraction", "1", "--jobs", "2", "--seed", "4",
               "--profile", "clean"])
    assert sim.returncode == 0, sim.stderr
    segments = sorted(p.stem for p in (data / "in" / "lidar").glob("*.parquet"))
    assert len(segments) == count + 1
    mounts = {m["mountPath"]: data / m.get("subPath", "") for m in c["volumeMounts"] if m["name"] == "data"}
    mounts[dockerfile()["env"]["POSEFUSE_MODEL_DIR"]] = ROOT / "models" / "default"
    seen = []
    for index in range(count):
        argv = pod_command(c, index, mounts)
        r = run([binary, *argv])
        assert r.returncode == 0, r.stderr
        out = Path(parse_flags(argv[2:])["--out"])
        assert out.parent == data / "out"
        written = sorted(p.stem for p in out.glob("*.parquet"))
        assert written == segments[index::count], f"shard {index}"
        assert not [p for p in out.iterdir() if p.name.startswith(".")], "no partial file left"
        seen += written
    assert sorted(seen) == segments
    # A retried pod skips the segments it already wrote.
    again = run([binary, *pod_command(c, 0, mounts)])
    assert again.returncode == 0 and f"({len(segments[0::count])} already done)" in again.stderr, again.stderr
    # The shards' folders together are one predictions folder for `waymo eval`.
    merged = tmp_path / "merged"
    merged.mkdir()
    for p in (data / "out").glob("shard-*/*.parquet"):
        (merged / p.name).symlink_to(p)
    ev = run([binary, "waymo", "eval", "--dataset", str(data / "in"), "--predictions", str(merged), "--json"])
    assert ev.returncode == 0, ev.stderr
    assert json.loads(ev.stdout)["segments"] == len(segments)
